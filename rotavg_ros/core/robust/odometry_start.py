"""The odometry chain's rotations, a start of the robust re-solve that no loop closure bends.

Within one unbroken piece of the chain (nodes ``k``, ``k + 1`` joined by odometry) the
rotations are the odometry composed. A chain can break into pieces: a front end that lost
its track and started a new map, a second session, a dropped odometry message. Only loop
closures join the pieces then, and a spanning tree takes one of them per join, whichever it
meets first: where that one is false, a whole piece starts turned, and a re-solve from there
rejects the true closures to it instead.

So each join is the one most closures agree with. With ``Q`` the rotations composed within
each piece (its first node at identity), the true rotations are ``R_k = Q_k M_p`` for node
``k`` of piece ``p`` and one unknown ``M_p`` per piece. A closure ``(a, b)`` from piece
``p`` to piece ``q`` then measures the join ``M_p M_q^T = Q_a^T R_ab Q_b``. True closures
between the same two pieces measure the same join up to the drift between their ends; false
ones are scattered. Each closure's support is the weight of the closures between the same
two groups of pieces whose joins lie within a tolerance of its own. The two groups with the
best supported closure merge by it, and the supports are counted again: a group's closures
to the rest then support each other whichever of its pieces they leave from, where two
single pieces often share one closure only, true or false (support 1 either way).

Conventions: world-to-node ``R_i``, ``R_ij ~= R_i R_j^T``; odometry edges join consecutive
node indices.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import minimum_spanning_tree

from rotavg_ros.core.filter.edge_filter import tree_rotations
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray

_ROWS = 1024  # supports are counted in blocks of this many closures

MAX_MERGED = 256
"""Up to this many pieces, groups of pieces are merged one pair at a time, the supports
counted again after each merge (quadratic in the pieces); above, in one round."""


def odometry_rotations(num_nodes: int, i: IntArray, j: IntArray, R: FloatArray,
                       odometry: BoolArray) -> tuple[FloatArray, IntArray]:
    """``(Q, piece)``: world-to-node rotations composed along the odometry chain
    (:func:`~rotavg_ros.core.filter.edge_filter.tree_rotations` over the odometry edges; the
    first node of each unbroken piece is identity), and the piece of each node (nodes ``k``,
    ``k + 1`` share a piece when the odometry joins them)."""
    linked = np.zeros(num_nodes, bool)  # linked[k]: k -- k+1 is odometry
    linked[np.minimum(i[odometry], j[odometry])] = True
    piece = np.concatenate([[0], np.cumsum(~linked[:-1])]).astype(np.int64)
    return tree_rotations(i, j, R, np.flatnonzero(odometry), num_nodes), piece


def odometry_start(num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
                   odometry: BoolArray, tolerance: float) -> FloatArray:
    """World-to-node rotations of the odometry chain, its pieces joined by the best
    supported closures (module docstring); two joins agree when they differ by less than
    ``tolerance`` (radians). Nodes no edge reaches stay at identity."""
    Q, piece = odometry_rotations(num_nodes, i, j, R, odometry)
    a, b = np.minimum(i, j), np.maximum(i, j)
    joins = np.flatnonzero(~odometry & (piece[a] != piece[b]))
    if joins.size == 0:
        return Q
    a, b = a[joins], b[joins]
    p, q = piece[a], piece[b]
    Rab = np.where((i[joins] < j[joins])[:, None, None], R[joins],
                   R[joins].transpose(0, 2, 1))
    D = Q[a].transpose(0, 2, 1) @ Rab @ Q[b]  # M_p M_q^T as each closure measures it
    return Q @ _join_pieces(p, q, D, w[joins], int(piece[-1]) + 1, tolerance)[piece]


def _join_pieces(p: IntArray, q: IntArray, D: FloatArray, w: FloatArray, num_pieces: int,
                 tolerance: float) -> FloatArray:
    """``M`` (one rotation per piece, the first piece's identity) from the joins ``D``
    (``M_p M_q^T`` as each closure measures it). Groups of pieces already joined are
    merged, the best supported pair first: ``M_p = L_p K_g`` for piece ``p`` of group
    ``g``, so a closure between groups ``g`` and ``h`` measures ``K_g K_h^T = L_p^T D L_q``,
    and the closures between two groups support each other whichever of their pieces they
    join. Above ``MAX_MERGED`` pieces the pairs of pieces are joined in one round instead
    (a maximum spanning tree of their supports)."""
    if num_pieces > MAX_MERGED:  # one round: a maximum spanning tree of the pairs
        pair = p * num_pieces + q  # (p < q: pieces are numbered along the node order)
        support = _support(D.reshape(-1, 9), pair, w, tolerance)
        order = np.lexsort((-support, pair))
        first = order[np.r_[True, pair[order][1:] != pair[order][:-1]]]
        tree = minimum_spanning_tree(coo_matrix(
            (1.0 + support.max() - support[first], (p[first], q[first])),
            shape=(num_pieces, num_pieces))).tocoo()
        keys = (np.minimum(tree.row, tree.col).astype(np.int64) * num_pieces
                + np.maximum(tree.row, tree.col))
        chosen = first[np.isin(pair[first], keys)]
        return tree_rotations(p[chosen], q[chosen], D[chosen], np.arange(chosen.size),
                              num_pieces)
    L = np.tile(np.eye(3), (num_pieces, 1, 1))
    group = np.arange(num_pieces)
    for _ in range(num_pieces - 1):
        g, h = group[p], group[q]
        cross = np.flatnonzero(g != h)
        if cross.size == 0:
            break
        J = L[p[cross]].transpose(0, 2, 1) @ D[cross] @ L[q[cross]]  # K_g K_h^T
        g, h = g[cross], h[cross]
        flip = g > h
        J[flip] = J[flip].transpose(0, 2, 1)
        lo, hi = np.where(flip, h, g), np.where(flip, g, h)
        support = _support(J.reshape(-1, 9), lo * num_pieces + hi, w[cross], tolerance)
        best = int(np.argmax(support))
        # K_hi = J^T K_lo: the pieces of group hi join group lo.
        moved = group == hi[best]
        L[moved] = L[moved] @ J[best].T
        group[moved] = lo[best]
    return L


def _support(D: FloatArray, pair: IntArray, w: FloatArray, tolerance: float) -> FloatArray:
    """Per closure, the weight of the closures of its own pair of pieces whose joins ``D``
    (flattened 3x3, rows) lie within ``tolerance`` of its own (itself included)."""
    # Rotations within angle t: trace(A B^T) = 1 + 2 cos(angle) > 1 + 2 cos(t).
    bound = 1.0 + 2.0 * np.cos(tolerance)
    support = np.zeros(pair.size)
    by_pair = np.argsort(pair, kind="stable")
    starts = np.flatnonzero(np.r_[True, pair[by_pair][1:] != pair[by_pair][:-1]])
    for members in np.split(by_pair, starts[1:]):
        Dm, wm = D[members], w[members]
        for lo in range(0, members.size, _ROWS):
            rows = slice(lo, lo + _ROWS)
            support[members[rows]] = (Dm[rows] @ Dm.T > bound) @ wm
    return support
