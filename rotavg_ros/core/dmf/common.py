"""Pieces shared by the DMF fits: the fit spec and result, factor shapes and
initialisation, the structure-of-arrays edge blocks and the step-size schedule. The model
and the loss are described in :mod:`.dense`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from rotavg_ros.core.options import DenseFitOptions
from rotavg_ros.core.types import FloatArray, IntArray


@dataclass(frozen=True)
class FitSpec:
    """What differs between the fits of one solve, resolved by the solver (no defaults:
    the options themselves are :class:`~rotavg_ros.core.options.DenseFitOptions` and
    :class:`~rotavg_ros.core.options.SparseFitOptions`)."""

    depth: int
    hidden_width: int
    seed: int
    """Seed of this fit's generator (the solver uses ``RuntimeOptions.seed + depth``)."""
    device: str
    """A resolved torch device (not ``auto``)."""
    cuda_graph: bool
    """CUDA only: replay each Adam step of the dense fit as one recorded CUDA graph."""


@dataclass
class DMFFit:
    """Result of one fit: the stacked factor product and the final edge weights."""

    H: FloatArray  # (N, 3, 3) blocks H_i ~= R_i Q
    weights: FloatArray  # (E,) final reweighted edge weights
    loss: float
    iterations: int = 0  # iterations run (fewer than asked when stopped early)
    stopped: bool = False  # ended by its monitor (a candidate race), not by convergence


def init_factors(
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


def warm_factors(
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


def lr_at(step: int, s: DenseFitOptions) -> float:
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
    A: torch.Tensor, B: torch.Tensor, transpose_a: bool = False, transpose_b: bool = False,
    out: torch.Tensor | None = None,
) -> torch.Tensor:
    """Batched 3x3 product on (3, 3, E) tensors: op(A) op(B) with op = optional transpose;
    into ``out`` (3, 3, E) when given (it must not overlap ``A`` or ``B``)."""
    a = A.transpose(0, 1) if transpose_a else A
    b = B.transpose(0, 1) if transpose_b else B
    if out is None:
        out = a[:, None, 0] * b[None, 0, :]
    else:
        torch.mul(a[:, None, 0], b[None, 0, :], out=out)
    out.addcmul_(a[:, None, 1], b[None, 1, :])
    out.addcmul_(a[:, None, 2], b[None, 2, :])
    return out


def stacked(Hn: torch.Tensor) -> FloatArray:
    """(3, 3, N) node blocks as a float64 (N, 3, 3) array."""
    return Hn.permute(2, 0, 1).double().cpu().numpy()
