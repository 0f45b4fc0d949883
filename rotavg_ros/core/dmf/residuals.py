"""The dense fit's weighted L1 loss and its gradient with respect to H, two ways.

Loss (see :mod:`.dense`), for ``H`` (3N x 3) with 3x3 blocks ``H_i``::

    L = sum_{(i,j) in E} w_ij |H_i H_j^T - R_ij|_1  +  sum_i w_d |H_i H_i^T - I|_1

:class:`GatherResiduals` gathers the two end blocks of every edge (O(|E|)); for a graph that
observes most pairs, :class:`DenseResiduals` forms ``G = H H^T`` (3N x 3N) in one product
instead and masks it with a per-entry weight matrix. Both keep the residual of the last
:meth:`gradient` call for the loss and the per-edge residual norms of the reweighting.
"""

from __future__ import annotations

from typing import Protocol

import torch

from rotavg_ros.core.dmf.common import EdgeBlocks, h_t_from_nodes, nodes_from_h_t, soa_matmul
from rotavg_ros.core.types import FloatArray, IntArray


class BlockResiduals(Protocol):
    """What the dense fit needs of its loss (``weights``: the (E,) edge weights, updated
    in place by the reweighting, which then calls :meth:`reweighted`)."""

    weights: torch.Tensor

    def gradient(self, h_t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(H as node blocks (3, 3, N), dL/dH^T (3, 3N))`` at ``H^T`` = ``h_t``."""

    def edge_norms(self) -> torch.Tensor:
        """(E,) ``||H_i H_j^T - R_ij||_F`` at the last :meth:`gradient` call."""

    def loss(self) -> float:
        """``L`` at the last :meth:`gradient` call."""

    def reweighted(self) -> None:
        """``weights`` changed (in place)."""


def observed_fraction(num_nodes: int, num_edges: int) -> float:
    """Fraction of the node pairs that carry an edge."""
    return num_edges / max(1, num_nodes * (num_nodes - 1) // 2)


EDGE_CHUNK = 32768
"""Edges per chunk of :class:`GatherResiduals`' gradient on the CPU. Each chunk's gathered
blocks and products are written into buffers kept across steps instead of fresh (9, E)
temporaries per step. At 10,000 nodes / 100,000 edges the default solve's peak RSS is
581 -> 538 MB, its time the same within the noise (26.9 -> 28.1 s, one run each). Graphs
with at most this many edges take one chunk: the same sums, bit for bit."""


class GatherResiduals:
    """The loss over the observed blocks only, in the (3, 3, E) layout of :class:`EdgeBlocks`.

    The gradient runs over chunks of :data:`EDGE_CHUNK` edges on the CPU (one chunk on a GPU,
    where a step is best a few large kernels).
    """

    def __init__(self, num_nodes: int, i: IntArray, j: IntArray, R: FloatArray,
                 weights: torch.Tensor, diagonal_weight: float) -> None:
        dev, dt = weights.device, weights.dtype
        self.blocks = EdgeBlocks(num_nodes, i, j, str(dev))
        self.tR = torch.as_tensor(R, device=dev).to(dt).permute(1, 2, 0).contiguous()
        self.eye = torch.eye(3, dtype=dt, device=dev)[:, :, None]
        self.weights = weights
        self.diagonal_weight = diagonal_weight
        num_edges = self.blocks.num_edges
        self.chunk = max(1, num_edges if dev.type != "cpu" else min(num_edges, EDGE_CHUNK))
        self.D = torch.empty(3, 3, num_edges, dtype=dt, device=dev)
        """``H_i H_j^T - R_ij`` per edge at the last :meth:`gradient` call."""
        self.Dd = torch.empty(0)
        self._grad = torch.empty(9, num_nodes, dtype=dt, device=dev)
        # Per chunk: H_i, H_j, the product (then the weighted signs), a gradient term.
        self._buffers = [torch.empty(9 * self.chunk, dtype=dt, device=dev) for _ in range(4)]

    def gradient(self, h_t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        Hn = nodes_from_h_t(h_t)
        flat = Hn.view(9, self.blocks.num_nodes)
        ti, tj = self.blocks.ti, self.blocks.tj
        grad = self._grad.zero_()
        for start in range(0, self.blocks.num_edges, self.chunk):
            end = min(start + self.chunk, self.blocks.num_edges)
            m = end - start
            Hi, Hj, G, term = (b[:9 * m].view(3, 3, m) for b in self._buffers)
            torch.index_select(flat, 1, ti[start:end], out=Hi.view(9, m))
            torch.index_select(flat, 1, tj[start:end], out=Hj.view(9, m))
            D = self.D[:, :, start:end]
            torch.sub(soa_matmul(Hi, Hj, transpose_b=True, out=G), self.tR[:, :, start:end],
                      out=D)
            torch.sign(D, out=G).mul_(self.weights[start:end])
            grad.index_add_(1, ti[start:end], soa_matmul(G, Hj, out=term).view(9, m))
            grad.index_add_(1, tj[start:end],
                            soa_matmul(G, Hi, transpose_a=True, out=term).view(9, m))
        self.Dd = soa_matmul(Hn, Hn, transpose_b=True).sub_(self.eye)
        node_grad = grad.view(3, 3, -1)
        node_grad.add_(soa_matmul(torch.sign(self.Dd), Hn), alpha=2.0 * self.diagonal_weight)
        return Hn, h_t_from_nodes(node_grad)

    def edge_norms(self) -> torch.Tensor:
        return self.D.pow(2).sum(dim=(0, 1)).sqrt()

    def loss(self) -> float:
        return float((self.weights * self.D.abs().sum(dim=(0, 1))).sum()
                     + self.diagonal_weight * self.Dd.abs().sum())

    def reweighted(self) -> None:
        pass


class DenseResiduals:
    """The loss from the whole ``G = H H^T`` (3N x 3N), masked by a weight matrix.

    With ``T`` holding ``R_ij`` at block (i, j), ``R_ij^T`` at (j, i) and ``I`` on the
    diagonal, and ``W`` holding ``w_ij`` at both blocks of an edge, ``2 w_d`` on the
    diagonal blocks and 0 elsewhere: ``L = 1/2 sum W * |G - T|`` and, ``S = W * sign(G - T)``
    being symmetric, ``dL/dH = S H``: two matrix products per step.

    ``W`` is constant on each block's three rows, so it is held as ``(N, 3N)``, one row per
    block row, and broadcast over the three: a third of the memory a step streams through
    for it (Ellis Island, one thread: the multiply 124 -> 64 us, the same products).
    """

    def __init__(self, num_nodes: int, i: IntArray, j: IntArray, R: FloatArray,
                 weights: torch.Tensor, diagonal_weight: float) -> None:
        dev, dt = weights.device, weights.dtype
        n = num_nodes
        self.ti = torch.as_tensor(i, dtype=torch.int64, device=dev)
        self.tj = torch.as_tensor(j, dtype=torch.int64, device=dev)
        self.diag = torch.arange(n, device=dev)
        Rt = torch.as_tensor(R, device=dev).to(dt)
        T = torch.zeros(n, n, 3, 3, dtype=dt, device=dev)
        T[self.ti, self.tj] = Rt
        T[self.tj, self.ti] = Rt.transpose(1, 2)
        T[self.diag, self.diag] = torch.eye(3, dtype=dt, device=dev)
        self.neg_T = T.permute(0, 2, 1, 3).reshape(3 * n, 3 * n).neg_()  # [3a + r, 3b + c]
        """``-T``: ``G - T`` is then one ``addmm``."""
        self.W_rows = torch.zeros(n, 3 * n, dtype=dt, device=dev)
        """``W``'s rows ``3a`` (those of ``3a + 1`` and ``3a + 2`` are the same), (N, 3N)."""
        self.weights = weights
        self.diagonal_weight = diagonal_weight
        self.D = torch.empty_like(self.neg_T)
        """``G - T`` or, after a step, ``S``: one 3N x 3N buffer kept across steps."""
        self._holds_residual = False
        self._h_t = torch.zeros(3, 3 * n, dtype=dt, device=dev)
        """``H^T`` at the last :meth:`gradient` call, to form ``G - T`` again on demand."""
        self.reweighted()

    def gradient(self, h_t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        # In place in one buffer kept across steps: a fresh 3N x 3N tensor per step costs
        # page faults, and a second one its memory traffic (Ellis Island: 557 -> 418 us
        # per call on one thread, the same values bit for bit). The residual the loss and
        # the edge norms need is formed again when they are asked for (every reweighting).
        # Not ``copysign(W, G - T)``: one pass fewer, but +-w_ij, not 0, where an L1 fit
        # has made a residual exactly zero (Ellis Island's median 0.389 -> 0.409 deg).
        self._h_t.copy_(h_t)
        torch.addmm(self.neg_T, h_t.T, h_t, out=self.D).sign_()
        self._blocks(self.D).mul_(self.W_rows[:, None, :])
        self._holds_residual = False
        return nodes_from_h_t(h_t), torch.mm(h_t, self.D)  # (S H)^T = H^T S

    def _residual(self) -> torch.Tensor:
        """``G - T`` at the last :meth:`gradient` call."""
        if not self._holds_residual:
            torch.addmm(self.neg_T, self._h_t.T, self._h_t, out=self.D)
            self._holds_residual = True
        return self.D

    def edge_norms(self) -> torch.Tensor:
        n = self.diag.numel()
        D = self._residual()
        return D.view(n, 3, n, 3).pow(2).sum(dim=(1, 3))[self.ti, self.tj].sqrt()

    def loss(self) -> float:
        return 0.5 * float((self._blocks(self._residual().abs()) * self.W_rows[:, None, :]).sum())

    def reweighted(self) -> None:
        n = self.diag.numel()
        Wb = torch.zeros(n, n, dtype=self.W_rows.dtype, device=self.W_rows.device)
        Wb[self.ti, self.tj] = self.weights
        Wb[self.tj, self.ti] = self.weights
        Wb[self.diag, self.diag] = 2.0 * self.diagonal_weight
        self.W_rows.copy_(Wb[:, :, None].expand(n, n, 3).reshape(n, 3 * n))

    def _blocks(self, M: torch.Tensor) -> torch.Tensor:
        """A 3N x 3N matrix viewed as (N, 3, 3N): block row, row within it, column."""
        n = self.diag.numel()
        return M.view(n, 3, 3 * n)
