"""The DMF fit's hand-written pieces: the factor chain's gradients and early stopping."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from rotavg_ros.core.depth_choice import rotations_from_factor
from rotavg_ros.core.dmf import FitSpec, factor_shapes, fit_symmetric
from rotavg_ros.core.dmf.dense import _residuals, reweight
from rotavg_ros.core.dmf.residuals import DenseResiduals, GatherResiduals
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.optim.factor_chain import FactorChain
from rotavg_ros.core.options import DenseFitOptions
from rotavg_ros.core.so3 import exp_map, random_rotations


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


def _reference_loss(h_t: torch.Tensor, i: np.ndarray, j: np.ndarray, R: np.ndarray,
                    w: torch.Tensor, diag: float) -> torch.Tensor:
    """The loss written out (float64, autograd): blocks H_i are rows 3i..3i+2 of H^T^T."""
    H = h_t.T.reshape(-1, 3, 3)
    pred = H[i] @ H[j].transpose(1, 2)
    own = H @ H.transpose(1, 2)
    return ((w[:, None, None] * (pred - torch.as_tensor(R)).abs()).sum()
            + diag * (own - torch.eye(3, dtype=h_t.dtype)).abs().sum())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_dense_residuals_match_the_gathered_blocks(dtype: torch.dtype) -> None:
    """The whole-H H^T evaluation: same loss, gradient and edge residual norms as the
    gather (to rounding), both as the loss written out, also after a reweighting."""
    rng = np.random.default_rng(4)
    n = 9
    i, j = np.triu_indices(n, 1)
    keep = rng.random(i.size) < 0.6
    i, j = i[keep], j[keep]
    R = random_rotations(i.size, rng)
    h64 = torch.as_tensor(rng.normal(size=(3, 3 * n)))
    h_t = h64.to(dtype)
    w = torch.as_tensor(np.linspace(0.5, 2.0, i.size))
    runs = []
    for kind in (GatherResiduals, DenseResiduals):
        weights = w.to(dtype, copy=True)
        res = kind(n, i, j, R, weights, diagonal_weight=1.5)
        first = (*res.gradient(h_t), res.edge_norms(), res.loss())
        weights[::2] *= 0.25  # a reweighting, in place
        res.reweighted()
        runs.append((first, (*res.gradient(h_t), res.edge_norms(), res.loss())))
    tol = 2e-5 if dtype == torch.float32 else 1e-7
    scales = (torch.ones(i.size, dtype=torch.float64),
              torch.where(torch.arange(i.size) % 2 == 0, 0.25, 1.0).double())
    for k, scale in enumerate(scales):
        ref = h64.clone().requires_grad_(True)
        loss = _reference_loss(ref, i, j, R, w * scale, 1.5)
        loss.backward()
        assert ref.grad is not None
        for Hn, grad, norms, value in (runs[0][k], runs[1][k]):
            assert value == pytest.approx(float(loss.detach()), rel=1e-5)
            torch.testing.assert_close(grad, ref.grad.to(dtype), rtol=tol, atol=tol)
            torch.testing.assert_close(Hn, runs[0][k][0])
            torch.testing.assert_close(norms, runs[0][k][2], rtol=tol, atol=tol)
    assert runs[0][0][3] != pytest.approx(runs[0][1][3])


def test_dense_fit_switches_by_density_and_matches_the_gather() -> None:
    R, i, j, Rij = _clean_problem(12, 5)
    spec = FitSpec(depth=2, hidden_width=36, seed=1, device="cpu", cuda_graph=False)
    fits = [fit_symmetric(12, i, j, Rij, np.ones(i.size),
                          DenseFitOptions(dtype="float64", iterations=600,
                                          dense_product_density=density), spec)
            for density in (None, 0.5)]
    assert max(_error_deg(f.H, R) for f in fits) < 0.5
    np.testing.assert_allclose(fits[1].H, fits[0].H, atol=1e-6)
    w = torch.ones(i.size, dtype=torch.float64)
    for density, nodes, kind in ((0.5, 300, DenseResiduals), (None, 300, GatherResiduals),
                                 (1.0, 300, DenseResiduals), (0.5, 11, GatherResiduals)):
        s = DenseFitOptions(dense_product_density=density, dense_product_max_nodes=nodes)
        assert isinstance(_residuals(12, i, j, Rij, w, s), kind)
    sparse = DenseFitOptions(dense_product_density=0.5)  # a fifth of the pairs observed
    assert isinstance(_residuals(12, i[::5], j[::5], Rij[::5], w[::5], sparse),
                      GatherResiduals)


def test_reweighting_rules() -> None:
    """The paper's rule shrinks the weights above the median residual, cumulatively; the
    default sets every weight afresh from the input weights, ``tau / max(r, f tau)``."""
    r = torch.tensor([0.5, 1.0, 2.0, 4.0, 0.01], dtype=torch.float64)  # median 1.0
    base = torch.tensor([1.0, 1.0, 1.0, 2.0, 1.0], dtype=torch.float64)
    paper = base.clone()
    reweight(paper, base, r, None)
    reweight(paper, base, r, None)
    torch.testing.assert_close(paper, torch.tensor([1.0, 1.0, 0.25, 2 / 16, 1.0],
                                                   dtype=torch.float64))
    fresh = base.clone()
    reweight(fresh, base, r, 0.1)
    reweight(fresh, base, r, 0.1)  # not cumulative
    torch.testing.assert_close(fresh, torch.tensor([2.0, 1.0, 0.5, 0.5, 10.0],
                                                   dtype=torch.float64))
    exact = torch.tensor([0.0, 0.0, 0.0, 3.0, 5.0], dtype=torch.float64)  # median 0
    reweight(fresh, base, exact, 0.1)
    assert torch.isfinite(fresh).all()
    torch.testing.assert_close(fresh[:3], torch.full((3,), 10.0, dtype=torch.float64))
    assert float(fresh[3:].max()) < 1e-20


def test_fresh_reweighting_beats_the_papers_under_folded_noise_and_outliers() -> None:
    """200 nodes, mean degree 40, errors ``|N(0, 5 deg)|`` about random axes, 20% false
    edges: the default reweighting's fit has a clearly lower median error than the paper's
    rule (0.77x on this draw, 0.75-0.80x on six; on 60-node graphs the ratio varies by draw,
    0.71-1.2x)."""
    n = 200
    R, i, j, Rij = _clean_problem(n, 0)
    rng = np.random.default_rng(1)
    keep = rng.random(i.size) < 0.2
    i, j, Rij = i[keep], j[keep], Rij[keep]
    axes = rng.normal(size=(i.size, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.abs(rng.normal(0.0, np.radians(5.0), i.size))
    Rij = Rij @ exp_map(axes * angles[:, None])
    false = rng.random(i.size) < 0.2
    Rij[false] = random_rotations(int(false.sum()), rng)
    spec = FitSpec(depth=2, hidden_width=64, seed=1, device="cpu", cuda_graph=False)
    medians = {}
    for floor in (None, 0.1):
        fit = fit_symmetric(n, i, j, Rij, np.ones(i.size),
                            DenseFitOptions(reweight_floor=floor), spec)
        stats = evaluate(dict(enumerate(rotations_from_factor(fit.H))), dict(enumerate(R)))
        medians[floor] = stats.median_deg
    assert medians[0.1] < 0.85 * medians[None]  # measured 0.346 against 0.450 deg
