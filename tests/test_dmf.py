"""The DMF fit's hand-written pieces: the factor chain's gradients and early stopping."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from rotavg_ros.core.dmf import FitSpec, factor_shapes, fit_symmetric
from rotavg_ros.core.optim.factor_chain import FactorChain
from rotavg_ros.core.options import DenseFitOptions
from rotavg_ros.core.so3 import random_rotations
from rotavg_ros.core.solver import rotations_from_factor


@pytest.mark.parametrize("depth", [2, 4, 6, 8])
def test_factor_chain_matches_autograd(depth: int) -> None:
    gen = torch.Generator().manual_seed(depth)
    shapes = factor_shapes(7, depth, 10)
    ws = [torch.randn(r, c, generator=gen, dtype=torch.float64) for r, c in shapes]
    target = torch.randn(21, 3, generator=gen, dtype=torch.float64)

    auto = [w.clone().requires_grad_(True) for w in ws]
    H = auto[0]
    for w in auto[1:]:
        H = H @ w
    loss = ((H - target) ** 3).sum()  # any non-linear function of H
    loss.backward()

    chain = FactorChain([w.clone() for w in ws])
    h_t = chain.forward()
    torch.testing.assert_close(h_t.T, H.detach())
    chain.backward((3 * (h_t.T - target) ** 2).T)
    for mine, ref in zip(chain.factors, auto, strict=True):
        assert ref.grad is not None and mine.grad is not None
        torch.testing.assert_close(mine.grad, ref.grad)


def _clean_problem(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    R = random_rotations(n, rng)
    i, j = np.triu_indices(n, 1)
    return R, i, j, np.einsum("eab,ecb->eac", R[i], R[j])


def _error_deg(H: np.ndarray, R: np.ndarray) -> float:
    rot = rotations_from_factor(H)
    Q = rot[0].T @ R[0]  # gauge: H_i ~= R_i Q^T up to the anchor
    C = np.einsum("nab,bc,ndc->nad", rot, Q, R)
    return float(np.degrees(np.arccos(np.clip((np.trace(C, axis1=1, axis2=2) - 1) / 2, -1, 1)))
                 .max())


def test_early_stopping_ends_a_converged_fit() -> None:
    R, i, j, Rij = _clean_problem(12, 3)
    s = DenseFitOptions(iterations=1000, lr=0.01, warmup=100, reweight_every=25,
                        dtype="float64", tolerance=2e-3)
    spec = FitSpec(depth=4, hidden_width=36, seed=1, device="cpu", cuda_graph=True)
    stopped = fit_symmetric(12, i, j, Rij, np.ones(i.size), s, spec)
    assert 100 < stopped.iterations < 1000
    assert stopped.iterations % 25 == 0  # it stops at a check
    assert _error_deg(stopped.H, R) < 0.2


def test_float32_fit_matches_float64() -> None:
    R, i, j, Rij = _clean_problem(10, 4)
    w = np.ones(i.size)
    base: dict[str, Any] = dict(iterations=600, lr=0.01, warmup=100, reweight_every=25,
                                tolerance=0.0)
    spec = FitSpec(depth=2, hidden_width=30, seed=2, device="cpu", cuda_graph=True)
    f32 = fit_symmetric(10, i, j, Rij, w, DenseFitOptions(**base, dtype="float32"), spec)
    f64 = fit_symmetric(10, i, j, Rij, w, DenseFitOptions(**base, dtype="float64"), spec)
    assert f32.H.dtype == np.float64  # results are returned as float64 either way
    assert _error_deg(f32.H, R) < 0.01 and _error_deg(f64.H, R) < 0.01
