"""Node relocalization: global moves of single nodes that lower the truncated L1 cost.

A least-squares (or GNC) re-solve can leave a few nodes far off: a node whose true edges
were all dropped as outliers at some stage sits where its false edges put it, and every
local method then keeps it there (its true edges look like outliers from there). Each
node's own data says so: the rotations its edges predict for it, ``P_e = R_ij R_j`` (node
``i``) or ``R_ij^T R_i`` (node ``j``), cluster at the true rotation when its true edges
agree with each other.

For each node that explains no more of its edges than it leaves unexplained, every ``P_e``
is tried as a hypothesis, scored by the node's share of the truncated L1 cost (each edge's
residual angle, capped). The node moves to the cheapest hypothesis that either lowers its
cost by more than one capped edge, or lies far from its rotation (more than ``FAR_CAPS``
caps), explains more of its edges (residual within the cap) and lowers its cost at all; it
moves to the chordal mean of the predictions that agree with that hypothesis (or the
hypothesis itself, if that costs less). The cost of every other node's edges is unchanged
by the move, so each move lowers the total cost over all edges (the verification's choice
cost): the sweeps descend that cost and stop.

Why the second rule: a true edge's residual at the true rotation is itself a good part of
the cap (a few noise scales), so the truncated L1 cost alone tells a node left on one of its
false edges from its true rotation by less than one capped edge even where most of its
edges are true (a random graph of mean degree 10 with 30% false edges: nodes with 7 true
edges of 9 stayed 135-165 deg off). More explained edges is the evidence there. Far only:
a hypothesis near the node's rotation is a local correction, which the least-squares
re-fit makes; there the count follows the noise (parking-garage at 5 deg per edge: 13
nodes moved a few degrees and the median error rose 2%).

Conventions: world-to-node ``R_i``, ``R_ij ~= R_i R_j^T``.
"""

from __future__ import annotations

import numpy as np

from rotavg_ros.core.robust.gauss_newton import residual_angles
from rotavg_ros.core.so3 import project_to_so3
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray

FAR_CAPS = 2.0
"""A move that explains more edges but does not lower the cost by a whole capped edge must go
farther than this many caps from the node's rotation (two caps: edges explained there are at
least a cap from it)."""


def _angles(X: FloatArray, P: FloatArray) -> FloatArray:
    """``angle(X_x P_p^T)`` for every pair: (len(X), len(P)) radians."""
    tr = np.einsum("xab,pab->xp", X, P)
    return np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))


def relocalize_nodes(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray, cap: float,
    trusted: BoolArray | None = None, sweeps: int = 3,
) -> tuple[FloatArray, int]:
    """``(rotations, moves)``: ``rot`` after up to ``sweeps`` sweeps of single-node moves
    (see the module docstring); ``cap`` bounds each edge's cost, in radians of a unit-weight
    edge (an edge's residual counts as ``sqrt(w) * angle``), except ``trusted`` edges'."""
    rot = rot.copy()
    n = rot.shape[0]
    sw = np.sqrt(w)
    limit = np.where(np.zeros(i.size, bool) if trusted is None else trusted, np.inf, cap)
    # Incidence lists: node -> (edge, node is the edge's first end).
    ends = np.concatenate([i, j])
    order = np.argsort(ends, kind="stable")
    starts = np.searchsorted(ends[order], np.arange(n + 1))
    edge_of = np.concatenate([np.arange(i.size)] * 2)[order]
    first = (order < i.size)
    Rt = np.transpose(R, (0, 2, 1))
    total = 0
    for _ in range(sweeps):
        over = residual_angles(rot, i, j, R) * sw > cap
        bad = np.bincount(i, over, n) + np.bincount(j, over, n)
        good = np.bincount(i, ~over, n) + np.bincount(j, ~over, n)
        suspects = np.flatnonzero((bad >= good) & (bad > 0))
        moves = 0
        for a in suspects[np.argsort(good[suspects] - bad[suspects], kind="stable")]:
            sl = slice(starts[a], starts[a + 1])
            e, f = edge_of[sl], first[sl]
            other = np.where(f, j[e], i[e])
            P = np.where(f[:, None, None], R[e] @ rot[other], Rt[e] @ rot[other])
            X = np.concatenate([rot[a][None], P])
            ang = _angles(X, P) * sw[e]
            cost = np.minimum(ang, limit[e]).sum(axis=1)
            # Moves: by more than one capped edge cheaper; or, far from the node's rotation,
            # cheaper at all and explaining more of its edges (row 0 never qualifies).
            explained = (ang <= cap).sum(axis=1)
            far = _angles(X, X[:1])[:, 0] > FAR_CAPS * cap
            better = (cost < cost[0] - cap) | ((cost < cost[0]) & (explained > explained[0])
                                                & far)
            best = int(np.argmin(np.where(better, cost, np.inf)))
            if better[best]:
                # The chordal mean of the predictions that agree with the hypothesis: one
                # edge's prediction carries that edge's noise, the mean all of theirs.
                agree = ang[best] <= cap
                mean = project_to_so3(np.einsum("e,eab->ab", w[e][agree], P[agree]))
                mean_cost = np.minimum(_angles(mean[None], P)[0] * sw[e], limit[e]).sum()
                rot[a] = mean if mean_cost <= cost[best] else X[best]
                moves += 1
        total += moves
        if moves == 0:
            break
    return rot, total
