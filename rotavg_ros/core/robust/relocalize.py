"""Node relocalization: global moves of single nodes that lower their share of the cost.

A least-squares (or GNC) re-solve can leave a few nodes far off: a node whose true edges
were all dropped as outliers at some stage sits where its false edges put it, and every
local method then keeps it there (its true edges look like outliers from there). Each
node's own data says so: the rotations its edges predict for it, ``P_e = R_ij R_j`` (node
``i``) or ``R_ij^T R_i`` (node ``j``), cluster at the true rotation when its true edges
agree with each other.

For each node that explains no more of its edges than it leaves unexplained, every ``P_e``
is tried as a hypothesis, and one more: the chordal mean of the largest group of
predictions within ``sqrt(2) TLS_CAPS`` caps of one of them (two predictions differ by two
edges' noise, so three true edges whose predictions lie a little over a cap apart are no
single prediction's, but all are their mean's). The node moves to the cheapest hypothesis
by its share of the truncated L1 cost (each edge's residual angle, capped) that either
lowers that cost by more than one capped edge, or lies far from its rotation (more than
``FAR_CAPS`` caps), explains more of its edges (residual within ``TLS_CAPS`` caps) and
lowers its share of the truncated squares at that cap; it moves to the chordal mean of the
predictions that agree with that hypothesis (or the hypothesis itself, if that costs
less). The caller keeps the moves only where they lower its choice cost over all edges.

Why the second rule: a true edge's residual at the true rotation is itself a good part of
the cap (a few noise scales), so the truncated L1 cost alone tells a node left on one of its
false edges from its true rotation by less than one capped edge even where most of its
edges are true (a random graph of mean degree 10 with 30% false edges: nodes with 7 true
edges of 9 stayed 135-165 deg off). More explained edges is the evidence there. A node on
one false edge fits it exactly and saves a whole cap in the L1 cost; three true edges at
about 0.7 cap each then cost more than the two caps their agreement saves (``sfm/sparse200/
out30`` drawn with seed 1: two or three nodes, by the re-solve's start, with 2-3 true edges
of 5-7 stayed 140-177 deg off).
Truncated squares at four noise scales (the second GNC pass's threshold and objective)
count three such edges at about half a cap's square each. Far only: a hypothesis near the
node's rotation is a local correction, which the least-squares re-fit makes; there the
count follows the noise (parking-garage at 5 deg per edge: 13 nodes moved a few degrees and
the median error rose 2%).

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


TLS_CAPS = 4.0 / 3.0
"""Far moves count explained edges within, and truncated squares at, this many caps: four
noise scales against the cap's three, the threshold of the verification's second GNC pass
(see the module docstring)."""
SQRT2 = float(np.sqrt(2.0))


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
            # Hypotheses: the node's rotation, each prediction, and the chordal mean of the
            # largest group of predictions within sqrt(2) TLS_CAPS caps of one of them (two
            # predictions differ by two edges' noise: three true edges a little over a cap
            # from each other's predictions all agree with their mean).
            X = np.concatenate([rot[a][None], P])
            ang = _angles(X, P) * sw[e]
            near = ang[1:] <= SQRT2 * TLS_CAPS * cap
            group = near[int(np.argmax(near.sum(axis=1)))]
            if group.sum() > 1:
                mean = project_to_so3(np.einsum("e,eab->ab", w[e][group], P[group]))
                X = np.concatenate([X, mean[None]])
                ang = np.concatenate([ang, _angles(mean[None], P) * sw[e]])
            cost = np.minimum(ang, limit[e]).sum(axis=1)
            explained = (ang <= TLS_CAPS * cap).sum(axis=1)
            squares = np.minimum(ang, TLS_CAPS * limit[e]) ** 2 @ np.ones(e.size)
            # Moves: by more than one capped edge cheaper; or, far from the node's rotation,
            # lower truncated squares and more of its edges explained (row 0 never
            # qualifies).
            far = _angles(X, X[:1])[:, 0] > FAR_CAPS * cap
            better = (cost < cost[0] - cap) | ((squares < squares[0])
                                                & (explained > explained[0]) & far)
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
