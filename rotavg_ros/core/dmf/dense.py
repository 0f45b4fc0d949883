"""The paper's DMF fit (Sec. IV-B to IV-D): near-zero (or warm) factors, the entry-wise
L1 loss of the observed blocks, Adam with cosine decay, reweighting and early stopping.

Symmetric, explicitly rank-3 model (the paper's design)::

    G_hat = H H^T,   H = W_1 W_2 ... W_{d/2},   W_{d/2} in R^{h x 3}, W_1 in R^{3N x h}

with hidden width ``h`` (the paper uses h = 3N). The 3x3 block ``H_i`` (rows 3i..3i+2)
estimates ``R_i Q`` for one unknown ``Q`` in O(3): world-to-node rotations up to gauge.

Loss (Sec. IV-D), evaluated per observed block in O(|E|), or on a small graph that observes
most pairs from the whole G_hat (:mod:`.residuals`)::

    L = sum_{(i,j) in E} w_ij |H_i H_j^T - R_ij|_1  +  sum_i w_d |H_i H_i^T - I|_1

Reweighting (Sec. IV-C): every ``reweight_every`` iterations after ``warmup``, with
``r_ij = ||H_i H_j^T - R_ij||_F`` and ``tau = median(r)``: ``w_ij *= tau / r_ij`` where
``r_ij > tau`` (the paper's rule), or by default ``w_ij = w0_ij * tau / max(r_ij, f tau)``
afresh from the input weights (``DenseFitOptions.reweight_floor``, :func:`reweight`).
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import nullcontext

import torch

from rotavg_ros.core.dmf.common import (
    DMFFit,
    FitSpec,
    factor_shapes,
    init_factors,
    lr_at,
    stacked,
    warm_factors,
)
from rotavg_ros.core.dmf.residuals import (
    BlockResiduals,
    DenseResiduals,
    GatherResiduals,
    observed_fraction,
)
from rotavg_ros.core.optim.adam import Adam
from rotavg_ros.core.optim.factor_chain import FactorChain
from rotavg_ros.core.optim.step_graph import StepGraph
from rotavg_ros.core.options import DenseFitOptions
from rotavg_ros.core.types import FloatArray, IntArray


def fit_symmetric(
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    s: DenseFitOptions, fit: FitSpec,
    progress: Callable[[int, float], None] | None = None,
    H0: FloatArray | None = None,
    monitor: Callable[[int, FloatArray], bool | None] | None = None,
) -> DMFFit:
    """Fit H H^T to the observed blocks with Adam; returns H's blocks and the final weights.

    ``H0`` (N, 3, 3), when given, is a warm start: the factors start with product ``H0``
    instead of near zero (used for incremental re-solves).

    The gradient of the L1 loss with respect to H is formed by hand (sign of the block
    residual, scattered onto both end nodes) and taken through the factor product by
    :class:`~rotavg_ros.core.optim.factor_chain.FactorChain`; no autograd graph is built.

    Early stopping (``s.tolerance > 0``): after the warm-up, every ``s.check_every``
    iterations the relative change ``|H - H_prev|_F / |H|_F`` since the previous check is
    compared with ``s.tolerance``. Once it stays below for ``s.patience`` checks, the step
    size decays geometrically to ``lr * lr_final_ratio`` over ``s.cooldown`` iterations
    (what the cosine schedule's tail does for a full run: it makes L1 fits exact) and the
    fit ends. ``monitor(step, H)`` (N, 3, 3) is called every ``s.check_every`` iterations;
    when it returns True the fit ends there (``DMFFit.stopped``: a candidate race's verdict).
    """
    dev = fit.device
    on_gpu = torch.device(dev).type == "cuda"
    # CUDA: a stream per depth, so parallel candidates overlap on the device.
    with torch.cuda.stream(_fit_stream(dev, fit.depth)) if on_gpu else nullcontext():
        return _fit_symmetric(num_nodes, i, j, R, w, s, fit, progress, H0, monitor,
                              use_graph=on_gpu and fit.cuda_graph)


_FIT_STREAMS: dict[tuple[str, int], torch.cuda.Stream] = {}


def _fit_stream(device: str, depth: int) -> torch.cuda.Stream:
    """The CUDA stream of the fits of one depth, made once per process and reused.

    Candidates of different depths fit in parallel threads, one stream each. Reusing the
    streams across solves matters: the caching allocator reuses a freed block only on the
    stream it was allocated on, so a fresh stream per fit would strand cached memory.
    """
    key = (str(torch.device(device)), depth)
    if key not in _FIT_STREAMS:
        _FIT_STREAMS.setdefault(key, torch.cuda.Stream(device=device))
    return _FIT_STREAMS[key]


def _fit_symmetric(
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    s: DenseFitOptions, fit: FitSpec,
    progress: Callable[[int, float], None] | None, H0: FloatArray | None,
    monitor: Callable[[int, FloatArray], bool | None] | None, use_graph: bool,
) -> DMFFit:
    dev = fit.device
    dt = getattr(torch, s.dtype)
    gen = torch.Generator().manual_seed(fit.seed)
    shapes = factor_shapes(num_nodes, fit.depth, fit.hidden_width)
    if H0 is None:
        factors = init_factors(shapes, s.init_scale, gen, dev, dt)
    else:
        factors = warm_factors(H0, shapes, s.init_scale, gen, dev, dt)
    chain = FactorChain(factors)
    weights = torch.as_tensor(w, device=dev).to(dt, copy=True)
    base = weights.clone()
    res = _residuals(num_nodes, i, j, R, weights, s)
    opt = Adam(factors, lr=s.lr)
    use_graph = use_graph and opt.fused
    if use_graph:
        opt.use_lr_tensor()
    out: dict[str, torch.Tensor] = {}

    def step() -> None:
        """One Adam step; leaves the pre-update blocks in ``out`` (residuals in ``res``)."""
        Hn, grad_h_t = res.gradient(chain.forward())
        chain.backward(grad_h_t)
        opt.step()
        out["Hn"] = Hn

    run_step = StepGraph(step, enabled=use_graph)
    loss_val = float("nan")
    calm, previous = 0, None
    end, anneal_from = s.iterations, -1
    step_no, stopped = 0, False
    while step_no < end:
        opt.set_lr(lr_at(step_no, s) if anneal_from < 0
                   else _anneal_lr(step_no, anneal_from, end, s))
        run_step()
        Hn = out["Hn"]
        if progress is not None and (step_no + 1) % 250 == 0:
            loss_val = res.loss()
            progress(step_no + 1, loss_val)
        if (s.reweighting and step_no + 1 > s.warmup
                and (step_no + 1 - s.warmup) % s.reweight_every == 0):
            reweight(weights, base, res.edge_norms(), s.reweight_floor)
            res.reweighted()
        step_no += 1
        if monitor is not None and step_no % s.check_every == 0 and monitor(step_no,
                                                                           stacked(Hn)):
            stopped = True
            break
        if s.tolerance > 0 and anneal_from < 0 and step_no % s.check_every == 0:
            if previous is not None and step_no > s.warmup:
                change = float((Hn - previous).norm() / Hn.norm().clamp_min(1e-30))
                calm = calm + 1 if change < s.tolerance else 0
                if calm >= s.patience:  # converged at this step size: anneal, then stop
                    anneal_from, end = step_no, min(end, step_no + s.cooldown)
            previous = Hn.clone()  # a replayed graph overwrites Hn in place
    with torch.no_grad():
        Hn = res.gradient(chain.forward())[0]
        loss_val = res.loss()
    return DMFFit(stacked(Hn), weights.double().cpu().numpy(), loss_val, step_no, stopped)


def reweight(weights: torch.Tensor, base: torch.Tensor, r: torch.Tensor,
             floor: float | None) -> None:
    """Sec. IV-C's reweighting of ``weights`` (E,), in place, from the residual norms ``r``
    and their median ``tau``. ``floor=None``: the paper's rule, cumulative,
    ``w *= tau / r`` where ``r > tau``. Else afresh from the input weights ``base``:
    ``w = base * tau / max(r, floor * tau)`` (a zero median gives the exactly fitted edges
    the most weight and the others almost none)."""
    tau = torch.median(r)
    if floor is None:
        weights *= torch.where(r > tau, tau / r.clamp_min(1e-12), torch.ones_like(r))
        return
    ratio = (r / tau.clamp_min(1e-30)).clamp_min(floor)
    torch.div(base, ratio, out=weights)


def _anneal_lr(step: int, start: int, end: int, s: DenseFitOptions) -> float:
    """After early convergence: geometric decay from the schedule's rate at ``start`` to
    ``lr * lr_final_ratio`` at ``end`` (the cosine schedule's tail, compressed)."""
    lo, hi = s.lr * s.lr_final_ratio, lr_at(start, s)
    return hi * (lo / hi) ** ((step - start) / max(1, end - start - 1))


def _residuals(num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, weights: torch.Tensor,
               s: DenseFitOptions) -> BlockResiduals:
    """The loss on the whole ``H H^T`` for a graph on the CPU of at most
    ``s.dense_product_max_nodes`` nodes that observes at least ``s.dense_product_density``
    of the node pairs; else over the observed blocks."""
    dense = (weights.device.type == "cpu" and s.dense_product_density is not None
             and num_nodes <= s.dense_product_max_nodes
             and observed_fraction(num_nodes, int(i.shape[0])) >= s.dense_product_density)
    kind = DenseResiduals if dense else GatherResiduals
    return kind(num_nodes, i, j, R, weights, s.diagonal_weight)
