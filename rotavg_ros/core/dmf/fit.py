"""Deep matrix factorization of the observed rotation blocks (Sec. IV-B to IV-D).

Symmetric, explicitly rank-3 model (the paper's design)::

    G_hat = H H^T,   H = W_1 W_2 ... W_{d/2},   W_{d/2} in R^{h x 3}, W_1 in R^{3N x h}

with hidden width ``h`` (the paper uses h = 3N). The 3x3 block ``H_i`` (rows 3i..3i+2)
estimates ``R_i Q`` for one unknown ``Q`` in O(3): world-to-node rotations up to gauge.

Loss (Sec. IV-D), evaluated per observed block in O(|E|), never forming G_hat::

    L = sum_{(i,j) in E} w_ij |H_i H_j^T - R_ij|_1  +  sum_i w_d |H_i H_i^T - I|_1

Reweighting (Sec. IV-C): every ``reweight_every`` iterations after ``warmup``, with
``r_ij = ||H_i H_j^T - R_ij||_F`` and ``tau = median(r)``: ``w_ij *= tau / r_ij`` where
``r_ij > tau``.

``VanillaDMF`` is ablation (c): G_hat = W_1 ... W_d with every W in R^{3N x 3N} (no
symmetry, no bottleneck), the loss on the same blocks, and rotations recovered afterwards
from the top-3 eigenvectors of the symmetrised G_hat.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np
import torch
from numpy.typing import NDArray

from rotavg_ros.core.optim.adam import Adam
from rotavg_ros.core.optim.factor_chain import FactorChain
from rotavg_ros.core.optim.lbfgs import minimize_lbfgs
from rotavg_ros.core.optim.step_graph import StepGraph

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class DMFSettings:
    """Optimisation settings of one DMF fit."""

    depth: int
    hidden_width: int
    iterations: int = 3000
    lr: float = 0.01
    lr_final_ratio: float = 0.01
    reweighting: bool = True
    reweight_every: int = 100
    warmup: int = 500
    init_scale: float = 1e-2
    diagonal_weight: float = 1.0
    huber_delta: float = 0.0
    """Sparse-graph L-BFGS fit only: entry-wise Huber threshold (quadratic below it)."""
    tolerance: float = 0.0
    """Early stopping of the Adam fit: relative change of H per check; 0 = off."""
    check_every: int = 25
    patience: int = 2
    """Converged after this many consecutive checks below ``tolerance`` (after the
    warm-up); the fit then anneals the step size over ``cooldown`` iterations and stops."""
    cooldown: int = 50
    seed: int = 0
    device: str = "cpu"
    cuda_graph: bool = True
    """CUDA only: replay each Adam step of the dense fit as one recorded CUDA graph."""
    dtype: str = "float64"
    """Torch dtype of the Adam fit: ``float32`` halves memory traffic (the full-width
    factors are memory-bound); residuals of ~1e-3 rad are far above its precision."""


@dataclass
class DMFFit:
    """Result of one fit: the stacked factor product and the final edge weights."""

    H: FloatArray  # (N, 3, 3) blocks H_i ~= R_i Q
    weights: FloatArray  # (E,) final reweighted edge weights
    loss: float
    iterations: int = 0  # iterations run (fewer than asked when stopped early)


def _init_factors(
    shapes: list[tuple[int, int]], scale: float, gen: torch.Generator, device: str,
    dtype: torch.dtype = torch.float64,
) -> list[torch.Tensor]:
    """Near-zero Gaussian factors; each scaled so the product's entries are about ``scale``."""
    k = len(shapes)
    per = scale ** (1.0 / k)
    factors = []
    for rows, cols in shapes:
        std = per / math.sqrt(cols) if k > 1 else scale
        w = torch.randn(rows, cols, generator=gen, dtype=torch.float64) * std
        factors.append(w.to(device=device, dtype=dtype).requires_grad_(True))
    return factors


def _warm_factors(
    H0: FloatArray, shapes: list[tuple[int, int]], noise: float, gen: torch.Generator,
    device: str, dtype: torch.dtype = torch.float64,
) -> list[torch.Tensor]:
    """Factors whose product is exactly ``H0`` (3N x 3).

    ``W_1 = [H0 | e]``, middle factors ``I``, ``W_k = [I_3; 0]``: the hidden directions
    beyond the first three start at small noise ``e`` (near zero, as in the paper) and get
    non-zero gradients, while the product starts at ``H0``.
    """
    H0t = torch.as_tensor(H0, dtype=torch.float64).reshape(-1, 3)
    if len(shapes) == 1:
        return [H0t.to(device=device, dtype=dtype, copy=True).requires_grad_(True)]
    factors = []
    for idx, (rows, cols) in enumerate(shapes):
        if idx == 0:
            w = torch.randn(rows, cols, generator=gen, dtype=torch.float64) * noise
            w[:, :3] = H0t
        else:
            w = torch.eye(rows, cols, dtype=torch.float64)
        factors.append(w.to(device=device, dtype=dtype).requires_grad_(True))
    return factors


def factor_shapes(num_nodes: int, depth: int, width: int) -> list[tuple[int, int]]:
    """Shapes of W_1 ... W_{d/2}: (3N, h), (h, h) ..., (h, 3); just (3N, 3) for d = 2."""
    n3, k = 3 * num_nodes, depth // 2
    return [(n3, 3)] if k == 1 else [(n3, width)] + [(width, width)] * (k - 2) + [(width, 3)]


def _product(factors: list[torch.Tensor]) -> torch.Tensor:
    """W_1 (W_2 (... W_k)): right to left so every product is thin (x 3 columns)."""
    out = factors[-1]
    for w in reversed(factors[:-1]):
        out = w @ out
    return out


LBFGS_FTOL = 1e-12
"""Sparse mode: an L-BFGS run ends when a step lowers the loss by less than this,
relative to max(|loss|, 1)."""
ROUND_TOLERANCE = 1e-3
"""Sparse mode: the reweighting rounds end when one moves the factors by less than this,
relative (|x - x_prev| / |x|). On sphere2500 (no outliers) later rounds only shaved the
noise tail, 0.5-0.8 s each, and left the errors as they were (median 0.381 vs 0.379 deg
after all 8); on a stream graph with 5% outliers the rounds that mattered moved x by
1e-1 to 1e-2."""


def _lr_at(step: int, s: DMFSettings) -> float:
    """Cosine decay from lr to lr * lr_final_ratio."""
    t = step / max(1, s.iterations - 1)
    lo = s.lr * s.lr_final_ratio
    return lo + 0.5 * (s.lr - lo) * (1.0 + math.cos(math.pi * t))


class EdgeBlocks:
    """Observed blocks in a structure-of-arrays layout, for O(|E|) products.

    Node blocks are held as ``(3, 3, N)`` and edge blocks as ``(3, 3, E)`` tensors, so the
    3x3 products of every edge are a few vectorised multiply-adds over E (several times
    faster on CPU than ``bmm`` on ``(E, 3, 3)``, which loops over tiny matrices).
    """

    def __init__(self, num_nodes: int, i: IntArray, j: IntArray, device: str) -> None:
        self.num_nodes = num_nodes
        self.num_edges = int(i.shape[0])
        self.ti = torch.as_tensor(i, dtype=torch.int64, device=device)
        self.tj = torch.as_tensor(j, dtype=torch.int64, device=device)

    def products(
        self, Hn: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(H_i, H_j, H_i H_j^T)`` for every edge as (3, 3, E); ``Hn`` is (3, 3, N)."""
        flat = Hn.view(9, self.num_nodes)  # 2-D gather: the fast index_select path
        Hi = flat.index_select(1, self.ti).view(3, 3, self.num_edges)
        Hj = flat.index_select(1, self.tj).view(3, 3, self.num_edges)
        return Hi, Hj, soa_matmul(Hi, Hj, transpose_b=True)

    def node_gradient(
        self, G: torch.Tensor, Hi: torch.Tensor, Hj: torch.Tensor
    ) -> torch.Tensor:
        """d/dH of sum_e <G_e, H_i H_j^T> as (3, 3, N): G_e H_j onto i, G_e^T H_i onto j."""
        out = torch.zeros(9, self.num_nodes, dtype=G.dtype, device=G.device)
        out.index_add_(1, self.ti, soa_matmul(G, Hj).view(9, self.num_edges))
        out.index_add_(1, self.tj, soa_matmul(G, Hi, transpose_a=True).view(9, self.num_edges))
        return out.view(3, 3, self.num_nodes)


def nodes_from_h_t(h_t: torch.Tensor) -> torch.Tensor:
    """``H^T`` (3, 3N), entry [b, 3i + a] = H_i[a, b], as node blocks (3, 3, N) [a, b, i]."""
    return h_t.view(3, -1, 3).permute(2, 0, 1).contiguous()


def h_t_from_nodes(Hn: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`nodes_from_h_t`: (3, 3, N) node blocks to ``H^T`` (3, 3N)."""
    return Hn.permute(1, 2, 0).reshape(3, -1)


def nodes_from_stacked(H: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) blocks as (3, 3, N)."""
    return H.permute(1, 2, 0).contiguous()


def soa_matmul(
    A: torch.Tensor, B: torch.Tensor, transpose_a: bool = False, transpose_b: bool = False
) -> torch.Tensor:
    """Batched 3x3 product on (3, 3, E) tensors: op(A) op(B) with op = optional transpose."""
    a = A.transpose(0, 1) if transpose_a else A
    b = B.transpose(0, 1) if transpose_b else B
    out = a[:, None, 0] * b[None, 0, :]
    out.addcmul_(a[:, None, 1], b[None, 1, :])
    out.addcmul_(a[:, None, 2], b[None, 2, :])
    return out


def fit_symmetric(
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray, s: DMFSettings,
    progress: Callable[[int, float], None] | None = None,
    H0: FloatArray | None = None,
    monitor: Callable[[int, FloatArray], None] | None = None,
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
    fit ends. ``monitor(step, H)`` (N, 3, 3) is called every ``s.check_every`` iterations.
    """
    dev = s.device
    on_gpu = torch.device(dev).type == "cuda"
    # CUDA: a stream per depth, so parallel candidates overlap on the device.
    with torch.cuda.stream(_fit_stream(dev, s.depth)) if on_gpu else nullcontext():
        return _fit_symmetric(num_nodes, i, j, R, w, s, progress, H0, monitor,
                              use_graph=on_gpu and s.cuda_graph)


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
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray, s: DMFSettings,
    progress: Callable[[int, float], None] | None, H0: FloatArray | None,
    monitor: Callable[[int, FloatArray], None] | None, use_graph: bool,
) -> DMFFit:
    dev = s.device
    dt = getattr(torch, s.dtype)
    gen = torch.Generator().manual_seed(s.seed)
    shapes = factor_shapes(num_nodes, s.depth, s.hidden_width)
    if H0 is None:
        factors = _init_factors(shapes, s.init_scale, gen, dev, dt)
    else:
        factors = _warm_factors(H0, shapes, s.init_scale, gen, dev, dt)
    chain = FactorChain(factors)
    blocks = EdgeBlocks(num_nodes, i, j, dev)
    tR = torch.as_tensor(R, device=dev).to(dt).permute(1, 2, 0).contiguous()
    weights = torch.as_tensor(w, device=dev).to(dt, copy=True)
    eye = torch.eye(3, dtype=dt, device=dev)[:, :, None]
    opt = Adam(factors, lr=s.lr)
    use_graph = use_graph and opt.fused
    if use_graph:
        opt.use_lr_tensor()
    out: dict[str, torch.Tensor] = {}

    def step() -> None:
        """One Adam step; leaves the pre-update blocks and residuals in ``out``."""
        Hn = nodes_from_h_t(chain.forward())
        Hi, Hj, P = blocks.products(Hn)
        D = P.sub_(tR)
        Dd = soa_matmul(Hn, Hn, transpose_b=True).sub_(eye)
        G = torch.sign(D).mul_(weights)
        grad = blocks.node_gradient(G, Hi, Hj)
        grad.add_(soa_matmul(torch.sign(Dd), Hn), alpha=2.0 * s.diagonal_weight)
        chain.backward(h_t_from_nodes(grad))
        opt.step()
        out["Hn"], out["D"], out["Dd"] = Hn, D, Dd

    run_step = StepGraph(step, enabled=use_graph)
    loss_val = float("nan")
    calm, previous = 0, None
    end, anneal_from = s.iterations, -1
    step_no = 0
    while step_no < end:
        opt.set_lr(_lr_at(step_no, s) if anneal_from < 0
                   else _anneal_lr(step_no, anneal_from, end, s))
        run_step()
        Hn, D, Dd = out["Hn"], out["D"], out["Dd"]
        if progress is not None and (step_no + 1) % 250 == 0:
            loss_val = _l1_loss(D, Dd, weights, s.diagonal_weight)
            progress(step_no + 1, loss_val)
        if (s.reweighting and step_no + 1 > s.warmup
                and (step_no + 1 - s.warmup) % s.reweight_every == 0):
            r = D.pow(2).sum(dim=(0, 1)).sqrt()
            tau = torch.median(r)
            weights *= torch.where(r > tau, tau / r.clamp_min(1e-12), torch.ones_like(r))
        step_no += 1
        if monitor is not None and step_no % s.check_every == 0:
            monitor(step_no, _stacked(Hn))
        if s.tolerance > 0 and anneal_from < 0 and step_no % s.check_every == 0:
            if previous is not None and step_no > s.warmup:
                change = float((Hn - previous).norm() / Hn.norm().clamp_min(1e-30))
                calm = calm + 1 if change < s.tolerance else 0
                if calm >= s.patience:  # converged at this step size: anneal, then stop
                    anneal_from, end = step_no, min(end, step_no + s.cooldown)
            previous = Hn.clone()  # a replayed graph overwrites Hn in place
    with torch.no_grad():
        Hn = nodes_from_h_t(chain.forward())
        Hi, Hj, P = blocks.products(Hn)
        D = P.sub_(tR)
        Dd = soa_matmul(Hn, Hn, transpose_b=True).sub_(eye)
        loss_val = _l1_loss(D, Dd, weights, s.diagonal_weight)
    return DMFFit(_stacked(Hn), weights.double().cpu().numpy(), loss_val, end)


def _anneal_lr(step: int, start: int, end: int, s: DMFSettings) -> float:
    """After early convergence: geometric decay from the schedule's rate at ``start`` to
    ``lr * lr_final_ratio`` at ``end`` (the cosine schedule's tail, compressed)."""
    lo, hi = s.lr * s.lr_final_ratio, _lr_at(start, s)
    return hi * (lo / hi) ** ((step - start) / max(1, end - start - 1))


def _l1_loss(D: torch.Tensor, Dd: torch.Tensor, weights: torch.Tensor, diag: float) -> float:
    """The weighted entry-wise L1 loss from the edge and diagonal residual blocks."""
    return float((weights * D.abs().sum(dim=(0, 1))).sum() + diag * Dd.abs().sum())


def _stacked(Hn: torch.Tensor) -> FloatArray:
    """(3, 3, N) node blocks as a float64 (N, 3, 3) array."""
    return Hn.permute(2, 0, 1).double().cpu().numpy()


def fit_symmetric_lbfgs(
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray, s: DMFSettings,
    H0: FloatArray, rounds: int = 3, inner_iterations: int = 200,
    outlier_factor: float = 3.0, progress: Callable[[int, float], None] | None = None,
) -> DMFFit:
    """Sparse-graph variant: same H H^T model, entry-wise Huber loss, L-BFGS, warm start.

    Chain-like SLAM graphs are badly conditioned for first-order steps from near zero
    (information must diffuse along long chains), so this variant starts from ``H0`` (the
    chordal solution) and uses L-BFGS on a smooth loss: Huber with ``delta`` =
    ``s.huber_delta``, i.e. L2 on inlier-sized residuals and L1 beyond. Between the
    ``rounds`` L-BFGS runs, weights are updated like Sec. IV-C but only above
    ``outlier_factor * tau`` (tau = median chordal residual), so clean edges keep their
    weight while gross outliers are scaled down by ``outlier_factor * tau / r``. Residuals
    are first scaled by sqrt(initial weight), so each edge is judged against its own
    stated noise level (SLAM graphs mix very different information matrices); the
    rounds stop early once no edge is above that threshold, or once a round moved the
    factors by less than ``ROUND_TOLERANCE`` (relative).

    The optimiser is :func:`~rotavg_ros.core.optim.lbfgs.minimize_lbfgs` (float64, at most
    ``inner_iterations`` steps per round, ending early when a step improves the loss by
    less than ``LBFGS_FTOL`` relative); the gradient through the factors comes from
    :class:`~rotavg_ros.core.optim.factor_chain.FactorChain`.
    """
    dev = s.device
    f64 = torch.float64
    gen = torch.Generator().manual_seed(s.seed)
    shapes = factor_shapes(num_nodes, s.depth, s.hidden_width)
    start = _warm_factors(H0, shapes, s.init_scale, gen, dev)
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
    delta = max(s.huber_delta, 1e-9)

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

    loss_val, total = float("nan"), 0
    for rnd in range(rounds):
        res = minimize_lbfgs(loss_and_grad, x, inner_iterations, ftol=LBFGS_FTOL)
        moved = float((res.x - x).norm() / res.x.norm().clamp_min(1e-30))
        x, loss_val, total = res.x, res.loss, total + res.iterations
        if progress is not None:
            progress(total, loss_val)
        if not s.reweighting or rnd + 1 == rounds or (rnd > 0 and moved < ROUND_TOLERANCE):
            break
        with torch.no_grad():
            flat.copy_(x)
            Hn = nodes_from_h_t(chain.forward())
            r = blocks.products(Hn)[2].sub_(tR).pow(2).sum(dim=(0, 1)).sqrt() * noise_scale
            thresh = outlier_factor * torch.median(r)
            scale = torch.where(r > thresh, thresh / r.clamp_min(1e-12), torch.ones_like(r))
            weights *= scale
            if float((1.0 - scale).abs().max()) < 1e-3:
                break  # no edge is an outlier any more: converged
    flat.copy_(x)
    H = chain.product().reshape(num_nodes, 3, 3)
    return DMFFit(H.cpu().numpy().copy(), weights.cpu().numpy(), loss_val, total)


def fit_vanilla(
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray, s: DMFSettings,
    progress: Callable[[int, float], None] | None = None,
) -> DMFFit:
    """Ablation (c): G_hat = W_1 ... W_d, all 3N x 3N, then top-3 eigenvectors.

    Both (i, j) and (j, i) blocks and the identity diagonal are fitted, since G_hat is not
    symmetric by construction. Materialises G_hat (3N x 3N): only for the ablation.
    """
    dev = s.device
    gen = torch.Generator().manual_seed(s.seed)
    n3 = 3 * num_nodes
    factors = _init_factors([(n3, n3)] * s.depth, s.init_scale, gen, dev)
    nodes = torch.arange(num_nodes, device=dev)
    ti = torch.cat([torch.as_tensor(i, device=dev), torch.as_tensor(j, device=dev), nodes])
    tj = torch.cat([torch.as_tensor(j, device=dev), torch.as_tensor(i, device=dev), nodes])
    tR0 = torch.as_tensor(R, dtype=torch.float64, device=dev)
    eye = torch.eye(3, dtype=torch.float64, device=dev).expand(num_nodes, 3, 3)
    tR = torch.cat([tR0, tR0.transpose(1, 2), eye])
    e = int(i.shape[0])
    w_edges = torch.as_tensor(w, dtype=torch.float64, device=dev).clone()
    opt = torch.optim.Adam(factors, lr=s.lr, fused=True)
    loss_val = float("nan")
    for step in range(s.iterations):
        for group in opt.param_groups:
            group["lr"] = _lr_at(step, s)
        G = _chain(factors).view(num_nodes, 3, num_nodes, 3)
        P = G[ti, :, tj, :]
        D = P - tR
        weights = torch.cat([w_edges, w_edges, torch.full((num_nodes,), s.diagonal_weight,
                                                          dtype=torch.float64, device=dev)])
        loss = (weights * D.abs().sum(dim=(1, 2))).sum()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        loss_val = float(loss.detach())
        if (s.reweighting and step + 1 > s.warmup
                and (step + 1 - s.warmup) % s.reweight_every == 0):
            with torch.no_grad():
                r = D[:e].pow(2).sum(dim=(1, 2)).sqrt() + D[e:2 * e].pow(2).sum(dim=(1, 2)).sqrt()
                tau = torch.median(r)
                w_edges *= torch.where(r > tau, tau / r.clamp_min(1e-12), torch.ones_like(r))
        if progress is not None and (step + 1) % 250 == 0:
            progress(step + 1, loss_val)
    with torch.no_grad():
        G = _chain(factors)
        G = 0.5 * (G + G.T)
        evals, evecs = torch.linalg.eigh(G)
        top = evecs[:, -3:] * evals[-3:].clamp_min(0).sqrt()
    return DMFFit(top.view(num_nodes, 3, 3).cpu().numpy(), w_edges.cpu().numpy(), loss_val)


def _chain(factors: list[torch.Tensor]) -> torch.Tensor:
    out = factors[0]
    for w in factors[1:]:
        out = out @ w
    return out
