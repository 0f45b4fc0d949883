"""Pairwise consistency of loop closures over an odometry chain (PCM, Mangelson et al. 2018).

A group of mutually consistent false closures (perceptual aliasing: several wrong closures
between the same two places) hides from every test that judges one edge at a time: each
false closure is supported by the others. What gives the group away is a loop that holds two
closures and the odometry between their ends. For closures ``e = (a, b)`` and ``f = (c, d)``
(``a < b``, ``c < d``, all four ends on one unbroken piece of the chain) the loop
``a -> b`` (closure ``e``), ``b -> d`` (odometry), ``d -> c`` (closure ``f``, reversed),
``c -> a`` (odometry) has the error rotation ``E_e E_f^T`` (conjugated), where
``E_e = Q_a^T R_ab Q_b`` and ``Q`` are the odometry chain's composed rotations. The odometry
noise enters it over the chain between ``b`` and ``d`` and between ``a`` and ``c``, where
these stretches do not cancel (the symmetric difference of the two), so its variance per
axis is ``sigma^2`` times the sum of ``1 / w`` over those odometry edges plus the two
closures' own ``1 / w``. A pair whose squared loop angle exceeds ``CHI2_3_999`` times that
variance is inconsistent. Far-apart closures are loosely tested (the drift between them
excuses much), closures between the same two places tightly.

The set kept is a large mutually consistent one: the closure in the most inconsistent pairs
is dropped, then again, until no inconsistent pair is left (a greedy maximum independent set
of the conflict graph, where PCM takes a maximum clique of the consistency graph).

Conventions: world-to-node ``R_i``, ``R_ij ~= R_i R_j^T``; odometry edges join consecutive
node indices.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from rotavg_ros.core.robust.odometry_start import odometry_rotations
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray

CHI2_3_999 = 16.27
"""99.9% quantile of the chi-square distribution with 3 degrees of freedom: a pair of true
closures is called inconsistent with probability 0.1%."""

MAX_CLOSURES = 6000
"""Above this many testable closures the pairwise test is not run and every closure is kept:
its time and memory are quadratic in them (4 bytes per pair: 144 MB at this limit; 1.2 s
for the 4,600 closures of parking-garage on the project's 2-core machine)."""

_ROWS = 1024  # pairs are tested in blocks of this many rows


def consistent_closures(
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    odometry: BoolArray, sigmas: Sequence[float],
) -> list[BoolArray]:
    """The edges kept by the pairwise test (module docstring) at each noise scale of
    ``sigmas`` (per axis of a unit-weight edge, radians): every odometry edge, every closure
    the test cannot reach (its ends on different pieces of the chain, or too many closures),
    and a mutually consistent set of the others."""
    everything = [np.ones(i.size, bool) for _ in sigmas]
    if not odometry.any():
        return everything
    Q, piece = odometry_rotations(num_nodes, i, j, R, odometry)
    a, b = np.minimum(i, j), np.maximum(i, j)
    testable = np.flatnonzero(~odometry & (piece[a] == piece[b]))
    if testable.size < 2 or testable.size > MAX_CLOSURES:
        return everything
    a, b = a[testable], b[testable]
    Rab = np.where((i[testable] < j[testable])[:, None, None], R[testable],
                   R[testable].transpose(0, 2, 1))
    E = (Q[a].transpose(0, 2, 1) @ Rab @ Q[b]).reshape(-1, 9)
    # Odometry variance (in units of a unit-weight edge's) along the chain: from x to y in
    # one piece, prefix[y] - prefix[x].
    # (A zero-weight edge has infinite variance: the pairs through it are never in conflict.)
    with np.errstate(divide="ignore"):
        inv_w = np.zeros(num_nodes)
        oi, oj = i[odometry], j[odometry]
        inv_w[np.minimum(oi, oj)] = 1.0 / w[odometry]
        own = (1.0 / w[testable]).astype(np.float32)
    prefix = np.concatenate([[0.0], np.cumsum(inv_w)[:-1]])
    pa, pb = prefix[a].astype(np.float32), prefix[b].astype(np.float32)
    E = E.astype(np.float32)
    one_piece = bool(np.all(piece[a] == piece[a[0]]))
    # ratio: squared loop angle over its variance for a unit noise scale (0 where the two
    # closures lie on different pieces: never in conflict).
    ratio = np.empty((testable.size, testable.size), np.float32)
    for lo in range(0, testable.size, _ROWS):
        rows = slice(lo, lo + _ROWS)
        angle = np.arccos(np.clip((E[rows] @ E.T - 1.0) * 0.5, -1.0, 1.0))
        # Stretches between the closures' first ends and between their second ends, in
        # odometry variance (prefix is monotone along a piece); their overlap cancels.
        ra, rb = pa[rows, None], pb[rows, None]
        lo1, hi1 = np.minimum(ra, pa), np.maximum(ra, pa)
        lo2, hi2 = np.minimum(rb, pb), np.maximum(rb, pb)
        overlap = np.maximum(np.minimum(hi1, hi2) - np.maximum(lo1, lo2), 0.0)
        var = (hi1 - lo1) + (hi2 - lo2) - 2.0 * overlap + own[rows, None] + own
        with np.errstate(invalid="ignore"):  # inf - inf: through a zero-weight edge
            block = np.nan_to_num(angle * angle / var, nan=0.0)
        if not one_piece:
            block[piece[a[rows], None] != piece[None, a]] = 0.0
        ratio[rows] = block
    np.fill_diagonal(ratio, 0.0)
    out = []
    for sigma in sigmas:
        keep = np.ones(i.size, bool)
        if np.isfinite(sigma) and sigma > 0.0:
            keep[testable[~_mutually_consistent(ratio > CHI2_3_999 * sigma * sigma)]] = False
        out.append(keep)
    return out


def _mutually_consistent(conflict: BoolArray) -> BoolArray:
    """A set with no pair in ``conflict`` (symmetric): the member in the most conflicts is
    dropped, then again, until none is left (ties: the lowest index)."""
    conflict = conflict.copy()
    degree = conflict.sum(axis=1)
    alive = np.ones(conflict.shape[0], bool)
    while degree.max(initial=0) > 0:
        worst = int(np.argmax(degree))
        alive[worst] = False
        degree -= conflict[worst]
        degree[worst] = 0
        conflict[:, worst] = False
        conflict[worst] = False
    return alive
