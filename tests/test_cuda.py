"""The CUDA path: the same pipeline with ``device="cuda"``.

Skipped where torch sees no CUDA device (CI and the 2-core development machine have none);
run on a GPU machine with ``python -m pytest tests/test_cuda.py``. Every check compares the
GPU result with ground truth or with the CPU result of the same seed.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np
import pytest
import torch

from rotavg_ros.core.depth_choice import rotations_from_factor
from rotavg_ros.core.dmf import FitSpec, fit_symmetric
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.optim.step_graph import StepGraph
from rotavg_ros.core.options import DenseFitOptions, SolverOptions
from rotavg_ros.core.so3 import random_rotations, rotation_about_axis
from rotavg_ros.core.solver import RotationAverager, average_rotations
from rotavg_ros.core.view_graph import ViewGraph

pytestmark = pytest.mark.skipif(
    not torch.cuda.is_available(),
    reason="no CUDA device: the CUDA path is checked on a GPU machine (see README)")

GPU = SolverOptions.from_flat(device="cuda", depths=(2, 4), iterations=1000)


def _graph(n: int, p: float, noise_deg: float, outliers: float, seed: int,
           chain: bool = False) -> tuple[ViewGraph, np.ndarray]:
    rng = np.random.default_rng(seed)
    R = random_rotations(n, rng)
    if chain:
        pairs = [(k, k + 1) for k in range(n - 1)] + [(k, k + 7) for k in range(0, n - 7, 3)]
    else:
        pairs = [(a, b) for a, b in combinations(range(n), 2) if rng.random() < p]
    g = ViewGraph()
    for a, b in pairs:
        Rij = R[a] @ R[b].T
        if outliers and rng.random() < outliers:
            Rij = random_rotations(1, rng)[0]
        elif noise_deg:
            Rij = rotation_about_axis(rng.normal(size=3),
                                      np.radians(noise_deg) * rng.normal()) @ Rij
        g.add_edge(a, b, Rij)
    return g, R


def _stats(res, R):  # type: ignore[no-untyped-def]
    return evaluate({k: res.rotations[x] for x, k in enumerate(res.node_ids)}, dict(enumerate(R)))


def test_dense_exact_recovery_on_gpu() -> None:
    g, R = _graph(40, 0.4, 0.0, 0.0, seed=1)
    res = RotationAverager(GPU.replace_flat(dtype="float64")).solve(g)
    assert _stats(res, R).max_deg < 0.01


def test_dense_gpu_matches_cpu_with_noise_and_outliers() -> None:
    g, R = _graph(60, 0.3, 2.0, 0.15, seed=2)
    gpu = _stats(RotationAverager(GPU).solve(g), R)
    cpu = _stats(RotationAverager(GPU.replace_flat(device="cpu")).solve(g), R)
    assert gpu.mean_deg < 1.5
    assert abs(gpu.mean_deg - cpu.mean_deg) < 0.05
    assert abs(gpu.median_deg - cpu.median_deg) < 0.05


def test_sparse_mode_on_gpu() -> None:
    g, R = _graph(200, 0.0, 1.0, 0.0, seed=3, chain=True)
    opt = GPU.replace_flat(mode="sparse")
    gpu = _stats(RotationAverager(opt).solve(g), R)
    cpu = _stats(RotationAverager(opt.replace_flat(device="cpu")).solve(g), R)
    assert gpu.median_deg < 2.0
    assert abs(gpu.median_deg - cpu.median_deg) < 0.01


def test_warm_resolve_on_gpu() -> None:
    g, R = _graph(60, 0.3, 1.0, 0.1, seed=4)
    averager = RotationAverager(GPU)
    first = averager.solve(g)
    previous = {k: first.rotations[x] for x, k in enumerate(first.node_ids)}
    warm = averager.solve(g, initial=previous, initial_depth=first.depth)
    assert _stats(warm, R).mean_deg <= _stats(first, R).mean_deg + 0.05


def test_vanilla_ablation_on_gpu() -> None:
    g, R = _graph(30, 0.5, 0.0, 0.0, seed=5)
    opt = GPU.replace_flat(depths=(2,), explicit_constraint=False, use_filter=False)
    assert _stats(RotationAverager(opt).solve(g), R).median_deg < 0.5


def test_auto_device_picks_cuda() -> None:
    g, _ = _graph(20, 0.5, 0.0, 0.0, seed=6)
    e = g.edge_arrays()
    out = average_rotations(g.num_nodes, e.i, e.j, e.R, e.weight,
                            GPU.replace_flat(device="auto", depths=(2,), iterations=200))
    assert np.all(np.isfinite(out.rotations))


def test_step_graph_records_once_and_replays_with_new_inputs() -> None:
    # Called from the default stream (where capture is not allowed), with a cuBLAS product.
    x = torch.zeros(4, device="cuda")
    rate = torch.zeros((), device="cuda")
    m = torch.randn(8, 8, device="cuda", dtype=torch.float64)
    prod = torch.zeros(8, 8, device="cuda", dtype=torch.float64)
    calls = []

    def step() -> None:
        calls.append(1)
        x.add_(rate)
        torch.mm(m, m, out=prod)

    graphed = StepGraph(step, enabled=True, eager_calls=2)
    for k in range(6):
        rate.fill_(float(k + 1))
        m.add_(1.0)  # new input on the caller's stream before every call
        graphed()
    assert torch.cuda.current_stream() == torch.cuda.default_stream()
    torch.cuda.synchronize()
    assert graphed.graph is not None
    assert len(calls) == 3  # two eager calls and the recording; the rest were replays
    assert torch.equal(x, torch.full((4,), 21.0, device="cuda"))  # 1 + 2 + ... + 6
    torch.testing.assert_close(prod, m @ m)  # the last replay saw the last input


def test_graphed_dense_fit_records_once_and_recovers_exactly(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # An L1 fit is exact only if the step size decays: the replayed step must follow the
    # rate tensor, not the rate at capture time.
    recorded = []
    original = StepGraph._record

    def counting(self: StepGraph) -> torch.cuda.CUDAGraph:
        recorded.append(1)
        return original(self)

    monkeypatch.setattr(StepGraph, "_record", counting)
    g, R = _graph(30, 0.5, 0.0, 0.0, seed=9)
    e = g.edge_arrays()
    # The settings DMFSettings(iterations=1000, tolerance=0.0, dtype="float64") gave.
    s = DenseFitOptions(iterations=1000, tolerance=0.0, dtype="float64", reweight_every=100,
                        warmup=500)
    spec = FitSpec(depth=4, hidden_width=90, seed=0, device="cuda", cuda_graph=True)
    fit = fit_symmetric(g.num_nodes, e.i, e.j, e.R, e.weight, s, spec)
    assert recorded == [1]
    rot = rotations_from_factor(fit.H)
    est = {k: rot[x] for x, k in enumerate(g.node_ids)}
    assert evaluate(est, dict(enumerate(R))).max_deg < 0.01


def test_cuda_graphs_and_parallel_candidates_match_eager_launches() -> None:
    g, R = _graph(60, 0.3, 2.0, 0.15, seed=7)
    graphed = RotationAverager(GPU).solve(g)
    eager = RotationAverager(GPU.replace_flat(cuda_graphs=False)).solve(g)
    a, b = _stats(graphed, R), _stats(eager, R)
    assert abs(a.mean_deg - b.mean_deg) < 0.02
    assert abs(a.median_deg - b.median_deg) < 0.02


def test_node_solver_child_solves_on_cuda() -> None:
    """The node's spawned solver process, cold and then warm-started, on the GPU."""
    from rotavg_ros.app.solver_process import SubprocessSolver

    g, R = _graph(50, 0.3, 1.0, 0.1, seed=8)
    solver = SubprocessSolver(niceness=0)
    try:
        cold = solver(g, None, GPU)
        previous = {k: cold.rotations[x] for x, k in enumerate(cold.node_ids)}
        warm = solver(g, None, GPU, previous, cold.depth)
    finally:
        solver.close()
    assert _stats(cold, R).mean_deg < 1.5
    assert _stats(warm, R).mean_deg <= _stats(cold, R).mean_deg + 0.05
