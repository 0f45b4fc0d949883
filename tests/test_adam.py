"""Our Adam: the rate read from a device tensor (as a recorded CUDA graph does) gives the
same updates as a plain float rate (on the CPU, and on CUDA where there is one); StepGraph
without CUDA just calls the step."""

from __future__ import annotations

import pytest
import torch

from rotavg_ros.core.optim.adam import Adam
from rotavg_ros.core.optim.step_graph import StepGraph

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", DEVICES)
def test_rate_tensor_gives_the_same_updates_as_a_float_rate(device: str) -> None:
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(6, 3, generator=gen).to(device)
    b = a.clone()
    plain, tensor_lr = Adam([a], lr=0.01), Adam([b], lr=0.01)
    tensor_lr.use_lr_tensor()
    for k in range(20):
        g = torch.randn(6, 3, generator=gen).to(device)
        a.grad, b.grad = g.clone(), g.clone()
        rate = 0.01 / (k + 1)
        plain.set_lr(rate)
        tensor_lr.set_lr(rate)
        assert tensor_lr.lr_tensor is not None
        assert abs(float(tensor_lr.lr_tensor) - rate) <= 1e-7 * rate
        plain.step()
        tensor_lr.step()
    assert not torch.equal(a, torch.zeros_like(a))
    torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)


def test_step_graph_disabled_calls_the_step_every_time() -> None:
    calls = []
    graphed = StepGraph(lambda: calls.append(1), enabled=False)
    for _ in range(5):
        graphed()
    assert len(calls) == 5 and graphed.graph is None
