"""Sparse-graph fit: the H H^T model from a chordal warm start, entry-wise Huber loss,
L-BFGS with outlier reweighting between runs (chain-like SLAM graphs)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from rotavg_ros.core.dmf.common import (
    DMFFit,
    EdgeBlocks,
    FitSpec,
    factor_shapes,
    h_t_from_nodes,
    nodes_from_h_t,
    soa_matmul,
    warm_factors,
)
from rotavg_ros.core.dmf.precondition import LaplacianPreconditioner
from rotavg_ros.core.optim.factor_chain import FactorChain
from rotavg_ros.core.optim.lbfgs import minimize_lbfgs
from rotavg_ros.core.options import DenseFitOptions, SparseFitOptions
from rotavg_ros.core.types import FloatArray, IntArray

PRECONDITIONER_STEPS = 30
"""Sparse mode, with :attr:`SparseFitOptions.precondition`: L-BFGS steps before the
preconditioner is built again at the current factors."""
LBFGS_FTOL = 1e-12
"""Sparse mode: an L-BFGS run ends when a step lowers the loss by less than this,
relative to max(|loss|, 1)."""
ROUND_LOOSE_FTOL = 1e-3
"""Sparse mode, with :attr:`SparseFitOptions.loose_rounds`: a reweighting round that another
will follow ends once one of its L-BFGS runs (after the first) lowers the loss by less than
this, relative; the last round converges fully (``LBFGS_FTOL``)."""
ROUND_TOLERANCE = 1e-3
"""Sparse mode: the reweighting rounds end when one moves the factors by less than this,
relative (|x - x_prev| / |x|). On sphere2500 (no outliers) later rounds only shaved the
noise tail, 0.5-0.8 s each, and left the errors as they were (median 0.381 vs 0.379 deg
after all 8); on a stream graph with 5% outliers the rounds that mattered moved x by
1e-1 to 1e-2."""


STRUCTURAL_ZERO = 1e-12
"""An entry of the residual blocks at or below this on every edge is a structural zero
(:func:`huber_delta`)."""


def huber_delta(H0: FloatArray, i: IntArray, j: IntArray, R: FloatArray,
                factor: float) -> float:
    """The sparse fit's Huber ``delta``: ``factor`` x the median absolute entry of the
    residual blocks ``H0_i H0_j^T - R_ij`` at the start ``H0``, over the entries (row,
    column) that are not zero on every edge. Where every rotation turns about one common
    axis (a planar robot's graph), five of the nine entries are zero on every edge, and
    over all entries the median was 0: ``delta`` fell to its floor and the "Huber" fit was
    an L1 fit (docs/benchmarks.md, "Planar graphs: the sparse fit's Huber scale"). On a 3D
    graph no entry is zero on every edge, and ``delta`` is the median over all of them, as
    before."""
    a = np.abs(np.einsum("eab,ecb->eac", H0[i], H0[j]) - R)
    carries = a.max(axis=0, initial=0.0) > STRUCTURAL_ZERO  # (3, 3): some edge's noise
    a = a[:, carries]
    return factor * float(np.median(a)) if a.size else 0.0


def shows_outliers(H: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
                   outlier_factor: float) -> bool:
    """Whether some edge's noise-scaled residual ``|H_i H_j^T - R_ij|_F sqrt(w)`` at the
    blocks ``H`` (N, 3, 3) is above ``outlier_factor`` x the median: what the reweighting
    rounds would scale down."""
    r = np.linalg.norm(H[i] @ np.swapaxes(H[j], 1, 2) - R, axis=(1, 2)) * np.sqrt(w)
    return bool(np.any(r > outlier_factor * np.median(r) / (1.0 - 1e-3)))


def fit_symmetric_lbfgs(
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    s: SparseFitOptions, model: DenseFitOptions, fit: FitSpec, H0: FloatArray,
    huber_delta: float, progress: Callable[[int, float], None] | None = None,
    trusted_start: bool = False,
) -> DMFFit:
    """Sparse-graph variant: same H H^T model, entry-wise Huber loss, L-BFGS, warm start.

    Chain-like SLAM graphs are badly conditioned for first-order steps from near zero
    (information must diffuse along long chains), so this variant starts from ``H0`` (the
    chordal solution) and uses L-BFGS on a smooth loss: Huber with ``delta`` =
    ``huber_delta``, i.e. L2 on inlier-sized residuals and L1 beyond. Between the
    ``s.rounds`` L-BFGS runs, weights are updated like Sec. IV-C but only above
    ``s.outlier_factor * tau`` (tau = median chordal residual), so clean edges keep their
    weight while gross outliers are scaled down by ``outlier_factor * tau / r``. Residuals
    are first scaled by sqrt(initial weight), so each edge is judged against its own
    stated noise level (SLAM graphs mix very different information matrices); the
    rounds stop early once no edge is above that threshold, or once a round moved the
    factors by less than ``ROUND_TOLERANCE`` (relative). With ``s.loose_rounds``, a round
    that another follows ends once an L-BFGS run lowers the loss by less than
    ``ROUND_LOOSE_FTOL`` (relative); where the rounds then end after all, that round goes on
    to full convergence, so the last round always converges. With ``trusted_start`` (``H0`` a
    previous or verified solution, not the chordal one) the weights are first updated at
    ``H0`` itself, so the first run does not bend a good start towards the outliers. The
    L-BFGS is preconditioned (:mod:`.precondition`) where its start is near a solution.

    The optimiser is :func:`~rotavg_ros.core.optim.lbfgs.minimize_lbfgs` (float64, at most
    ``s.inner_iterations`` steps per round, ending early when a step improves the loss by
    less than ``LBFGS_FTOL`` relative); the gradient through the factors comes from
    :class:`~rotavg_ros.core.optim.factor_chain.FactorChain`.
    """
    dev = fit.device
    f64 = torch.float64
    gen = torch.Generator().manual_seed(fit.seed)
    shapes = factor_shapes(num_nodes, fit.depth, fit.hidden_width)
    start = warm_factors(H0, shapes, model.init_scale, gen, dev)
    x = torch.cat([f.detach().reshape(-1) for f in start])
    flat = torch.zeros_like(x)  # the factors are views into it
    flat_grad = torch.zeros_like(flat)
    factors, offset = [], 0
    for rows, cols in shapes:
        factors.append(flat[offset:offset + rows * cols].view(rows, cols))
        offset += rows * cols
    chain = FactorChain(factors)
    offset = 0
    for f in factors:
        f.grad = flat_grad[offset:offset + f.numel()].view_as(f)
        offset += f.numel()
    blocks = EdgeBlocks(num_nodes, i, j, dev)
    tR = torch.as_tensor(R, dtype=f64, device=dev).permute(1, 2, 0).contiguous()
    weights = torch.as_tensor(w, dtype=f64, device=dev).clone()
    noise_scale = weights.sqrt()  # residual x sqrt(information): comparable across edges
    eye = torch.eye(3, dtype=f64, device=dev)[:, :, None]
    delta = max(huber_delta, 1e-9)

    def huber(x: torch.Tensor) -> torch.Tensor:
        a = x.abs()
        return torch.where(a <= delta, 0.5 * x * x / delta, a - 0.5 * delta)

    def loss_and_grad(x: torch.Tensor) -> tuple[float, torch.Tensor]:
        flat.copy_(x)
        Hn = nodes_from_h_t(chain.forward())
        Hi, Hj, P = blocks.products(Hn)
        D = P.sub_(tR)
        Dd = soa_matmul(Hn, Hn, transpose_b=True).sub_(eye)
        loss = (weights * huber(D).sum(dim=(0, 1))).sum() + s.diagonal_weight * huber(Dd).sum()
        G = (D / delta).clamp_(-1.0, 1.0).mul_(weights)
        grad = blocks.node_gradient(G, Hi, Hj)
        grad.add_(soa_matmul((Dd / delta).clamp_(-1.0, 1.0), Hn), alpha=2.0 * s.diagonal_weight)
        chain.backward(h_t_from_nodes(grad))
        return float(loss), flat_grad.clone()

    def outlier_scales(x: torch.Tensor) -> torch.Tensor:
        """Per edge, threshold / residual where the noise-scaled residual at ``x`` is above
        the threshold ``s.outlier_factor`` x the median, else 1."""
        with torch.no_grad():
            flat.copy_(x)
            Hn = nodes_from_h_t(chain.forward())
            r = blocks.products(Hn)[2].sub_(tR).pow(2).sum(dim=(0, 1)).sqrt() * noise_scale
            thresh = s.outlier_factor * torch.median(r)
            return torch.where(r > thresh, thresh / r.clamp_min(1e-12), torch.ones_like(r))

    def reweights(scale: torch.Tensor) -> bool:
        """Whether ``scale`` (:func:`outlier_scales`) changes some weight (by 1e-3 or more)."""
        return float((1.0 - scale).abs().max()) >= 1e-3

    if trusted_start and model.reweighting:
        weights.mul_(outlier_scales(x))  # a start already near the answer: judge by it
    # The preconditioner's model holds near a solution: from a trusted start, or from a
    # chordal one that shows no outlier (far from the answer, with outliers bending the
    # start, it was slower per step and no faster to converge). A round that does not
    # converge within its steps shows the model does not hold: the rest of the fit goes
    # without (seen from a start that kept a third of a 3,000-keyframe chain's false
    # closures: every preconditioned round ran its 300 steps, slower than without).
    precondition = (s.precondition and len(shapes) == 1
                    and (trusted_start or not shows_outliers(H0, i, j, R, w, s.outlier_factor)))

    def preconditioner(x: torch.Tensor) -> LaplacianPreconditioner:
        """The curvature at ``x`` as a graph Laplacian (depth 2 only: ``x`` is H)."""
        with torch.no_grad():
            flat.copy_(x)
            Hn = nodes_from_h_t(chain.forward())
            D = blocks.products(Hn)[2].sub_(tR).abs_()
            # Huber's IRLS weight per entry, min(1/delta, 1/|r|), averaged over the block
            curvature = weights * torch.minimum(1.0 / D.clamp_min(1e-300),
                                                torch.full_like(D, 1.0 / delta)).mean(dim=(0, 1))
            return LaplacianPreconditioner(
                Hn.permute(2, 0, 1).cpu().numpy(), i, j, curvature.cpu().numpy(),
                4.0 * s.diagonal_weight / delta)

    def run(x: torch.Tensor, used: int, loose: bool, loss: float = float("nan")
            ) -> tuple[torch.Tensor, float, int, bool]:
        """L-BFGS runs from ``x`` (its ``loss``, where known) until converged or
        ``s.inner_iterations`` steps (``used`` of them already taken this round): ``(x,
        loss, used, ended loose)``. With ``loose``, the round also ends, steps left, where a
        run after its first lowered the loss by less than ``ROUND_LOOSE_FTOL`` (relative)."""
        runs = 0
        while used < s.inner_iterations:
            # With a preconditioner, a fresh one (and a fresh L-BFGS history) every
            # PRECONDITIONER_STEPS: it holds near the blocks it was built at.
            pre = preconditioner(x) if precondition else None
            budget = s.inner_iterations - used
            if pre is not None:
                budget = min(budget, PRECONDITIONER_STEPS)
            res = minimize_lbfgs(loss_and_grad, x, budget, ftol=LBFGS_FTOL, precondition=pre)
            before, runs = loss, runs + 1
            x, loss, used = res.x, res.loss, used + res.iterations
            if res.iterations < budget:
                break  # converged (or no further progress)
            if (loose and runs > 1 and used < s.inner_iterations
                    and before - loss < ROUND_LOOSE_FTOL * max(abs(loss), 1.0)):
                return x, loss, used, True
        return x, loss, used, False

    def moved_from(start: torch.Tensor, x: torch.Tensor) -> float:
        return float((x - start).norm() / x.norm().clamp_min(1e-30))

    loss_val, total = float("nan"), 0
    for rnd in range(s.rounds):
        round_start = x
        x, loss_val, used, loose = run(x, 0, s.loose_rounds and model.reweighting
                                       and rnd + 1 < s.rounds)
        scale: torch.Tensor | None = None  # the edges' outlier scales at x, once taken
        if loose:
            scale = outlier_scales(x)
            if (rnd > 0 and moved_from(round_start, x) < ROUND_TOLERANCE) or not reweights(scale):
                # The rounds end here: this one converges as the last one always does, and
                # its scales are taken at the converged fit.
                x, loss_val, used, _ = run(x, used, False, loss_val)
                scale = None
        moved = moved_from(round_start, x)
        total += used
        precondition = precondition and used < s.inner_iterations
        if progress is not None:
            progress(total, loss_val)
        if not model.reweighting or rnd + 1 == s.rounds or (rnd > 0 and moved < ROUND_TOLERANCE):
            break
        # Scale down (by threshold / residual) the edges above the outlier threshold.
        scale = outlier_scales(x) if scale is None else scale
        weights.mul_(scale)
        if not reweights(scale):
            break  # no edge is an outlier any more: converged
    flat.copy_(x)
    H = chain.product().reshape(num_nodes, 3, 3)
    return DMFFit(H.cpu().numpy().copy(), weights.cpu().numpy(), loss_val, total)
