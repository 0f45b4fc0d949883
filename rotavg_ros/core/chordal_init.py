"""Weighted chordal least-squares rotations, used to initialise DMF on sparse graphs.

Solves ``min sum_ij w_ij ||R_i - R_ij R_j||_F^2`` over unconstrained 3x3 blocks with one
anchor block fixed to identity, then projects each block onto SO(3) and moves the gauge so
that node 0 is the identity. ``R_i`` is
world-to-node and ``R_ij ~= R_i R_j^T``, so ``R_i = R_ij R_j`` for exact data. This is the
classic linear relaxation (Martinec & Pajdla; GTSAM's chordal initialisation): one sparse
SPD solve, O(N + E) memory. SuperLU runs in symmetric mode with a minimum-degree ordering
of A + A^T (what suits an SPD matrix); its default column ordering filled in 4x more on a
random 1000-node graph (0.9 s against 0.2 s) and was never faster on the SE-Sync graphs.

The anchor is a central node, not node 0. The relaxed blocks shrink with graph distance from
the anchor as the noise grows, so far nodes are poorly placed; node 0 of a SLAM graph is the
start of the trajectory, often the farthest node of all. On parking-garage at 20 deg per edge
(docs/benchmarks.md) the node-0 anchor's solution led least squares into a local minimum at
41.5 deg mean error, a central anchor's into the better one at 34.0 deg. GTSAM's FAST-Sync
anchors the last key of a nested-dissection ordering, also a central node, for the same reason.

One anchor can still be unlucky: on a planar torus3D at 17 deg of heading noise (stress seed
20) the central node's relaxation read 57.9 deg median and least squares from it ended in a
local minimum at 54.8 deg, where from the node three quarters of the way along the same
path it reaches the optimum (9.5 deg). So the relaxation is solved at a few anchors along
the double sweep's path (:data:`ANCHOR_FRACTIONS`) and the projected solution with the
lowest chordal cost ``sum w ||R_i - R_ij R_j||_F^2`` is kept (there: 1020.9 at the centre,
864.7 at the three-quarter point); where the centre is cheapest the result is the one-anchor
result. One sparse factorization serves every anchor: the block Laplacian with the centre
pinned softly, ``M = L + pin E_c E_c^T``, and a 6x6 system per anchor
(:func:`_anchored_solution`). That halves the relaxation's time against one factorization
per anchor (torus3D with 10% false closures: 254 -> 118 ms, measured side by side).

Where the factor fills in heavily (a 3D lattice: grid3D's 20^3 poses, 22,800 edges), SuperLU's
own supernode settings factor it twice as fast as the settings that suit pose graphs and
chains (:mod:`~rotavg_ros.core.sparse_factor`); the fill of the scalar Laplacian's factor
tells which (:func:`fills_heavily`). A solve relaxes the same edges more than once (the
robust re-solve's inliers, then the DMF fit's warm start on them): within
:func:`reused_relaxations` a relaxation of edges already relaxed is not solved again.
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order

from rotavg_ros.core.so3 import project_to_so3
from rotavg_ros.core.sparse_factor import factor_fills_heavily, factor_spd
from rotavg_ros.core.types import FloatArray, IntArray

ANCHOR_FRACTIONS = (0.5, 0.25, 0.75)
"""Anchors of the relaxation, as fractions of the way along the double sweep's path
(:func:`anchor_candidates`; 0.5 is :func:`central_node`)."""


SUPERNODE_MIN_NODES = 2000
"""Nodes from which :func:`fills_heavily` factors the scalar Laplacian to find out (a
tenth of the relaxation's own factorization time); below, the factor never fills in
enough for SuperLU's supernodes to pay."""
RELAXATIONS_KEPT = 4
"""Relaxations :func:`reused_relaxations` keeps (the latest)."""
RELAXATIONS: ContextVar[dict[bytes, FloatArray] | None] = ContextVar(
    "RELAXATIONS", default=None)
"""The current solve's relaxations by a digest of their input (:func:`reused_relaxations`)."""
_RELAXATIONS_LOCK = threading.Lock()


@contextmanager
def reused_relaxations() -> Iterator[None]:
    """Within this block, :func:`chordal_rotations` of an input it has already relaxed
    returns that result again (a copy) instead of solving it anew: the same arrays give the
    same rotations, bit for bit. Nested blocks share the outermost block's results."""
    if RELAXATIONS.get() is not None:
        yield
        return
    token = RELAXATIONS.set({})
    try:
        yield
    finally:
        RELAXATIONS.reset(token)


def _digest(num_nodes: int, *arrays: FloatArray | IntArray) -> bytes:
    h = hashlib.blake2b(np.int64(num_nodes).tobytes(), digest_size=20)
    for array in arrays:
        flat = np.ascontiguousarray(array)
        h.update(f"{flat.dtype.str}{flat.shape}".encode())
        h.update(flat.tobytes())
    return h.digest()


def fills_heavily(num_nodes: int, i: IntArray, j: IntArray, w: FloatArray,
                  deg: NDArray[Any], centre: int, pin: float) -> bool:
    """Whether the factor of the graph's scalar Laplacian (weights ``w``, degrees ``deg``,
    ``centre`` pinned by ``pin``) holds at least
    :data:`~rotavg_ros.core.sparse_factor.SUPERNODE_MIN_FILL` entries per
    node (from :data:`SUPERNODE_MIN_NODES` nodes on; fewer: False). The relaxation's block
    matrix fills in as it does, nine times over."""
    if num_nodes < SUPERNODE_MIN_NODES:
        return False
    diagonal = np.asarray(deg, np.float64).copy()
    diagonal[centre] += pin
    nodes = np.arange(num_nodes)
    L = coo_matrix((np.concatenate([diagonal, -w, -w]),
                    (np.concatenate([nodes, i, j]), np.concatenate([nodes, j, i]))),
                   shape=(num_nodes, num_nodes)).tocsc()
    return factor_fills_heavily(factor_spd(L), num_nodes)


def anchor_candidates(num_nodes: int, i: IntArray, j: IntArray) -> list[int]:
    """The nodes at :data:`ANCHOR_FRACTIONS` of the way along the path of
    :func:`central_node`'s double sweep, first the centre, each once."""
    path = _sweep_path(num_nodes, i, j)
    out: list[int] = []
    for fraction in ANCHOR_FRACTIONS:
        node = path[min(int(len(path) * fraction), len(path) - 1)]
        if node not in out:
            out.append(node)
    return out


def central_node(num_nodes: int, i: IntArray, j: IntArray) -> int:
    """A node near the centre of the graph, by hop count: the middle of a long shortest path.

    Double sweep: the farthest node ``a`` from node 0, then the farthest node ``b`` from ``a``,
    and the node halfway along the BFS path from ``a`` to ``b``. On a tree that is the centre
    (minimum eccentricity); on other graphs it is the usual cheap stand-in for it (on
    parking-garage: eccentricity 76, the minimum, against node 0's 147). Two BFS passes,
    O(N + E). Nodes not connected to node 0 are ignored.
    """
    path = _sweep_path(num_nodes, i, j)
    return path[len(path) // 2]


def _sweep_path(num_nodes: int, i: IntArray, j: IntArray) -> list[int]:
    """The BFS path between the double sweep's two far nodes (from ``b`` back to ``a``)."""
    adj = coo_matrix((np.ones(i.size), (i, j)), shape=(num_nodes, num_nodes)).tocsr()

    def sweep(source: int) -> tuple[int, IntArray]:
        order, pred = breadth_first_order(adj, source, directed=False)
        return int(order[-1]), pred

    a, _ = sweep(0)
    b, pred = sweep(a)  # (sweep's BFS from ``a`` gives the path back to it)
    path = [b]
    while path[-1] != a:
        path.append(int(pred[path[-1]]))
    return path


def chordal_rotations(
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray
) -> FloatArray:
    """Chordal LS estimate of world-to-node rotations of a connected graph; node 0 = I.

    The linear system is anchored at each of :func:`anchor_candidates` (the centre first),
    and the projected solution of the lowest chordal cost is kept (module docstring); the
    gauge is moved to node 0 after the projection (``R_i <- R_i R_0^T``). Within
    :func:`reused_relaxations`, an input relaxed before returns that result again.
    """
    if num_nodes == 1:
        return np.eye(3)[None]
    cache = RELAXATIONS.get()
    if cache is None:
        return _chordal_rotations(num_nodes, i, j, R, w)
    key = _digest(num_nodes, i, j, R, w)
    with _RELAXATIONS_LOCK:  # (the verification's threads share the solve's results)
        known = cache.get(key)
    if known is None:
        known = _chordal_rotations(num_nodes, i, j, R, w)
        with _RELAXATIONS_LOCK:
            cache[key] = known
            while len(cache) > RELAXATIONS_KEPT:
                del cache[next(iter(cache))]  # the oldest
    return known.copy()


def _chordal_rotations(
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray
) -> FloatArray:
    """:func:`chordal_rotations` itself, solved."""
    n3 = 3 * num_nodes
    rows: list[IntArray] = []
    cols: list[IntArray] = []
    vals: list[FloatArray] = []
    a = np.arange(3)
    # Diagonal blocks: w I on both end nodes.
    deg = np.bincount(i, weights=w, minlength=num_nodes) + np.bincount(
        j, weights=w, minlength=num_nodes)
    rows.append(np.repeat(3 * np.arange(num_nodes), 3) + np.tile(a, num_nodes))
    cols.append(rows[-1])
    vals.append(np.repeat(deg, 3))
    # Off-diagonal blocks: -w R_ij at (i, j) and -w R_ij^T at (j, i).
    r_off = (3 * i)[:, None, None] + a[None, :, None] + 0 * a[None, None, :]
    c_off = (3 * j)[:, None, None] + 0 * a[None, :, None] + a[None, None, :]
    blk = -w[:, None, None] * R
    rows += [r_off.ravel(), c_off.ravel()]
    cols += [c_off.ravel(), r_off.ravel()]
    vals += [blk.ravel(), blk.ravel()]
    anchors = anchor_candidates(num_nodes, i, j)
    centre = anchors[0]
    pin = float(np.mean(deg))  # the centre's soft pin, at the Laplacian's own scale
    rows.append(3 * centre + a)
    cols.append(3 * centre + a)
    vals.append(np.full(3, pin))
    M = coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                   shape=(n3, n3)).tocsc()
    lu = factor_spd(M, supernodes=fills_heavily(num_nodes, i, j, w, deg, centre, pin))
    # M^-1 E_k for every anchor k (E_k: the anchor's three unit columns); the centre's first.
    E = np.zeros((n3, 3 * len(anchors)))
    for k, anchor in enumerate(anchors):
        E[3 * anchor + a, 3 * k + a] = 1.0
    MinvE = lu.solve(E)
    Q = MinvE[:, :3]  # M^-1 E_c
    best: FloatArray | None = None
    best_cost = np.inf
    for k, anchor in enumerate(anchors):
        X = _anchored_solution(MinvE[:, 3 * k:3 * k + 3], Q, anchor, centre, pin)
        out = project_to_so3(X.reshape(num_nodes, 3, 3))
        miss = out[i] - np.einsum("eab,ebc->eac", R, out[j])  # R_i - R_ij R_j
        cost = float(np.sum(w * np.sum(miss * miss, axis=(1, 2))))
        if cost < best_cost:
            best, best_cost = out, cost
    assert best is not None
    return np.einsum("nab,cb->nac", best, best[0])


def _anchored_solution(P: FloatArray, Q: FloatArray, anchor: int, centre: int,
                       pin: float) -> FloatArray:
    """The relaxation's minimiser with the anchor's block fixed to I, from one factor of M.

    ``min tr(X^T L X)`` subject to ``E_a^T X = I`` has ``L X = E_a Lam``. With
    ``M = L + pin E_c E_c^T`` and ``mu = E_c^T X`` that is ``M X = E_a Lam + pin E_c mu``,
    so ``X = P Lam + pin Q mu`` (``P = M^-1 E_a``, ``Q = M^-1 E_c``), and the constraint and
    the definition of ``mu`` give a 6x6 system for ``Lam`` and ``mu``. It is the same
    minimiser as eliminating the anchor's columns from ``L``, up to rounding (1e-14 on the
    SE-Sync graphs), with one factorization for all anchors instead of one each.
    """
    a = np.arange(3)
    Pa, Qa = P[3 * anchor + a], Q[3 * anchor + a]
    Pc, Qc = P[3 * centre + a], Q[3 * centre + a]
    K = np.block([[Pa, pin * Qa], [Pc, pin * Qc - np.eye(3)]])
    lam_mu = np.linalg.solve(K, np.vstack([np.eye(3), np.zeros((3, 3))]))
    return np.asarray(P @ lam_mu[:3] + pin * (Q @ lam_mu[3:]))
