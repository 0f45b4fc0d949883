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
variance is inconsistent (``CHI2_1_999`` on a planar problem, whose noise turns about one
axis: :data:`~.noise.NOISE_AXES`; likewise the quantile below). Far-apart closures are
loosely tested (the drift between them excuses much), closures between the same two places
tightly.

The same loops, one closure at a time, give a noise scale that no solution's fit enters
(:func:`loop_noise_scale`): a true closure's squared loop angle is its loop's variance
times a chi-square with 3 degrees of freedom, so a low quantile of the ratios reads the
scale while most closures are true.

The set kept is a large mutually consistent one: the closure in the most inconsistent pairs
is dropped, then again, until no inconsistent pair is left (a greedy maximum independent set
of the conflict graph, where PCM takes a maximum clique of the consistency graph).

Conventions: world-to-node ``R_i``, ``R_ij ~= R_i R_j^T``; odometry edges join consecutive
node indices.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from rotavg_ros.core.robust.noise import NOISE_AXES
from rotavg_ros.core.robust.odometry_start import odometry_rotations
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray

CHI2_3_999 = 16.27
"""99.9% quantile of the chi-square distribution with 3 degrees of freedom: a pair of true
closures is called inconsistent with probability 0.1%."""
CHI2_1_999 = 10.83
"""The same with 1 degree of freedom (a planar problem)."""

MAX_CLOSURES = 6000
"""Above this many testable closures the pairwise test is not run and every closure is kept:
its time and memory are quadratic in them (4 bytes per pair: 144 MB at this limit; 0.6 s
for the 4,615 closures of parking-garage at three noise scales on the project's 2-core
machine, 1.1-1.5 s before the blocks were computed in place)."""

LOOP_QUANTILE = 0.25
"""The quantile of the closures' standardized squared loop angles that
:func:`loop_noise_scale` reads the noise scale from."""
CHI2_3_Q25 = 1.2125
"""The 25% quantile of the chi-square distribution with 3 degrees of freedom
(:data:`LOOP_QUANTILE`'s; a test checks it against scipy)."""
CHI2_1_Q25 = 0.1015
"""The same with 1 degree of freedom (a planar problem)."""
LOOP_MIN_CLOSURES = 4
"""Fewer testable closures than this give :func:`loop_noise_scale` no answer."""
LOOP_BOUND_CONFIDENCE = 0.99
""":func:`loop_noise_scale`'s upper bound would hold with this probability were the loops
independent."""
LOOP_BOUND_Z = 2.326
"""The standard normal quantile at :data:`LOOP_BOUND_CONFIDENCE` (written out: importing
``scipy.stats`` costs 0.3-0.4 s)."""

NEIGHBOUR_REACH = 2
"""Poses by which each end of one loop closure may lie from the same end of another for
the two to be neighbours (:func:`neighbour_supported`)."""

_ROWS = 256  # pairs are tested in blocks of this many rows (4 MB temporaries at the limit)


@dataclass
class ClosureLoops:
    """Each testable loop closure ``e = (a, b)`` (``a < b``, both ends on one piece of the
    odometry) with the loop it closes over the odometry: ``E`` its error rotation
    ``Q_a^T R_ab Q_b`` (``Q`` the odometry chain's composed rotations), ``pa``, ``pb`` the
    odometry variance (in units of a unit-weight edge's: the sum of ``1 / w``) from the
    piece's start to ``a`` and to ``b``, ``own`` the closure's own ``1 / w``."""

    testable: IntArray
    a: IntArray
    piece: IntArray
    """(num_nodes,) the odometry piece of each node."""
    E: FloatArray
    pa: FloatArray
    pb: FloatArray
    own: FloatArray


def closure_loops(num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
                   odometry: BoolArray) -> ClosureLoops | None:
    """The loops the closures close over the odometry (:class:`ClosureLoops`); None without
    odometry. :func:`loop_noise_scale` and :func:`consistent_closures` take them (``loops``)
    where a caller needs both."""
    if not odometry.any():
        return None
    Q, piece = odometry_rotations(num_nodes, i, j, R, odometry)
    a, b = np.minimum(i, j), np.maximum(i, j)
    testable = np.flatnonzero(~odometry & (piece[a] == piece[b]))
    a, b = a[testable], b[testable]
    Rab = np.where((i[testable] < j[testable])[:, None, None], R[testable],
                   R[testable].transpose(0, 2, 1))
    E = Q[a].transpose(0, 2, 1) @ Rab @ Q[b]
    # Odometry variance along the chain: from x to y in one piece, prefix[y] - prefix[x].
    # (A zero-weight edge has infinite variance: the pairs through it are never in conflict.)
    with np.errstate(divide="ignore"):
        inv_w = np.zeros(num_nodes)
        oi, oj = i[odometry], j[odometry]
        inv_w[np.minimum(oi, oj)] = 1.0 / w[odometry]
        own = 1.0 / w[testable]
    prefix = np.concatenate([[0.0], np.cumsum(inv_w)[:-1]])
    return ClosureLoops(testable, a, piece, E, prefix[a], prefix[b], own)


def loop_noise_scale(num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
                     odometry: BoolArray, loops: ClosureLoops | None = None,
                     upper: bool = False) -> float:
    """The noise scale (per axis of a unit-weight edge, radians) that the loops the closures
    close over the odometry show, whatever any solution says: a true closure's loop angle
    ``theta`` has ``theta^2 ~ sigma^2 (v + own) chi2_3`` (``v`` the odometry variance along
    it; ``chi2_1`` on a planar problem), so ``sigma^2`` is the :data:`LOOP_QUANTILE` quantile
    of ``theta^2 / (v + own)`` over that of the chi-square. The lower quantile stands while
    false closures, whose loops are far off, are fewer than about three quarters. NaN with
    fewer than :data:`LOOP_MIN_CLOSURES` testable closures. ``loops``: :func:`closure_loops`
    of these edges, if already known.

    ``upper``: instead, an upper bound of that scale that widens as the closures get
    fewer: the ratios' order statistic that would lie above their :data:`LOOP_QUANTILE`
    quantile with probability :data:`LOOP_BOUND_CONFIDENCE` were they independent (the
    count below the quantile binomial; its normal approximation, continuity-corrected, gives
    the rank: with 8 closures the 6th lowest ratio, with 40 the 17th, with 100 the 36th),
    over the chi-square's quantile (the normal approximation makes it about 99%: 98.6-99%
    by the exact binomial). Loops over shared odometry are not independent, so the bound
    is less sure than that (Gaussian noise, 40 closures: below the true scale in 3 of 12
    draws). It stands while the false closures are fewer than ``n - rank + 1`` (2 of 8,
    23 of 40); with more, it is a false closure's ratio, which errs high."""
    scale, bound = loop_noise_scale_and_bound(num_nodes, i, j, R, w, odometry, loops)
    return bound if upper else scale


def loop_noise_scale_and_bound(
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    odometry: BoolArray, loops: ClosureLoops | None = None,
) -> tuple[float, float]:
    """:func:`loop_noise_scale` and its upper bound (``upper``) from one pass over the
    loops: ``(scale, bound)``, both NaN with too few testable closures."""
    if loops is None:
        loops = closure_loops(num_nodes, i, j, R, w, odometry)
    if loops is None or loops.testable.size < LOOP_MIN_CLOSURES:
        return math.nan, math.nan
    angle = np.arccos(np.clip((np.trace(loops.E, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))
    with np.errstate(invalid="ignore"):
        ratio = angle ** 2 / (loops.pb - loops.pa + loops.own)
    ratio = ratio[np.isfinite(ratio)]
    if ratio.size < LOOP_MIN_CLOSURES:
        return math.nan, math.nan
    q25 = CHI2_3_Q25 if NOISE_AXES.get() == 3 else CHI2_1_Q25
    n, p = ratio.size, LOOP_QUANTILE
    rank = math.ceil(n * p + LOOP_BOUND_Z * math.sqrt(n * p * (1.0 - p)) + 0.5)
    k = min(rank, n) - 1  # (0-based)
    return (math.sqrt(float(np.quantile(ratio, LOOP_QUANTILE)) / q25),
            math.sqrt(float(np.partition(ratio, k)[k]) / q25))


def consistent_closures(
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    odometry: BoolArray, sigmas: Sequence[float], loops: ClosureLoops | None = None,
) -> list[BoolArray]:
    """The edges kept by the pairwise test (module docstring) at each noise scale of
    ``sigmas`` (per axis of a unit-weight edge, radians): every odometry edge, every closure
    the test cannot reach (its ends on different pieces of the chain, or too many closures),
    and a mutually consistent set of the others. ``loops``: :func:`closure_loops` of these
    edges, if already known."""
    everything = [np.ones(i.size, bool) for _ in sigmas]
    if loops is None:
        loops = closure_loops(num_nodes, i, j, R, w, odometry)
    if loops is None or not 2 <= loops.testable.size <= MAX_CLOSURES:
        return everything
    testable, a = loops.testable, loops.a
    piece = loops.piece
    E = loops.E.reshape(-1, 9).astype(np.float32)
    pa, pb = loops.pa.astype(np.float32), loops.pb.astype(np.float32)
    own = loops.own.astype(np.float32)
    one_piece = bool(np.all(piece[a] == piece[a[0]]))
    # ratio: squared loop angle over its variance for a unit noise scale (0 where the two
    # closures lie on different pieces: never in conflict), a block of rows at a time, in
    # place (the temporaries of whole expressions cost more than the arithmetic).
    ratio = np.empty((testable.size, testable.size), np.float32)
    for lo in range(0, testable.size, _ROWS):
        rows = slice(lo, lo + _ROWS)
        block = ratio[rows]
        np.matmul(E[rows], E.T, out=block)  # trace of E_e^T E_f
        block -= 1.0
        block *= 0.5
        np.clip(block, -1.0, 1.0, out=block)
        np.arccos(block, out=block)
        block *= block
        # Stretches between the closures' first ends and between their second ends, in
        # odometry variance; their overlap cancels. (prefix is monotone and a <= b, so the
        # stretches are [min, max] of (pa_e, pa_f) and of (pb_e, pb_f), and the first ends
        # below the second: they overlap by max(pa_e, pa_f) - min(pb_e, pb_f) at most.)
        ra, rb = pa[rows, None], pb[rows, None]
        var = np.abs(ra - pa)
        stretch = np.abs(rb - pb)
        var += stretch
        overlap = np.maximum(ra, pa, out=stretch)
        overlap -= np.minimum(rb, pb)
        np.maximum(overlap, 0.0, out=overlap)
        overlap *= 2.0
        var -= overlap
        var += own[rows, None]
        var += own
        with np.errstate(invalid="ignore"):  # inf - inf: through a zero-weight edge
            block /= var
        np.nan_to_num(block, copy=False, nan=0.0)
        if not one_piece:
            block[piece[a[rows], None] != piece[None, a]] = 0.0
    np.fill_diagonal(ratio, 0.0)
    chi2_999 = CHI2_3_999 if NOISE_AXES.get() == 3 else CHI2_1_999
    out = []
    for sigma in sigmas:
        keep = np.ones(i.size, bool)
        if np.isfinite(sigma) and sigma > 0.0:
            keep[testable[~_mutually_consistent(ratio > chi2_999 * sigma * sigma)]] = False
        out.append(keep)
    return out


def neighbour_supported(num_nodes: int, i: IntArray, j: IntArray, loops: ClosureLoops,
                        sigma: float, reach: int = NEIGHBOUR_REACH
                        ) -> tuple[BoolArray, IntArray]:
    """Per closure of ``loops.testable``: whether its neighbours support it, more of them
    agreeing with it than not. Neighbours are closures whose ends lie within ``reach``
    poses of its own (``|a - c|``, ``|b - d|``) on the same piece of the odometry; one
    agrees where the loop of the two and the odometry between their ends passes the
    pairwise test (module docstring) at noise scale ``sigma`` (per axis of a unit-weight
    edge, radians). A front end that recognises a place does so over several keyframes in
    a row, so true closures come in runs of neighbours that agree. A random false closure
    has no neighbour that agrees with it, or, where it replaced a true match among such a
    run, more that disagree; a run of false closures is supported among itself (the run
    test and the tight pass judge those). Neighbours are found by the closures' ends, not
    by pairs: linear in the closures, however many.

    Returns ``(supported, run)``: ``run`` labels each closure by the group that agreeing
    neighbours join it to (a run of a front end's closures; a closure no neighbour agrees
    with is a group of its own)."""
    a = loops.a
    b = np.maximum(i, j)[loops.testable]
    votes = np.zeros(a.size, np.int64)  # neighbours that agree less those that do not
    joined: list[tuple[IntArray, IntArray]] = []  # pairs of neighbours that agree
    if a.size < 2 or not (math.isfinite(sigma) and sigma > 0.0):
        return votes > 0, np.arange(a.size)
    key = a * np.int64(num_nodes) + b
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    chi2_999 = CHI2_3_999 if NOISE_AXES.get() == 3 else CHI2_1_999
    for da in range(-reach, reach + 1):
        for db in range(-reach, reach + 1):
            if da == 0 and db == 0:
                continue
            wanted = (a + da) * np.int64(num_nodes) + (b + db)
            at = np.minimum(np.searchsorted(sorted_key, wanted), key.size - 1)
            found = sorted_key[at] == wanted
            e, f = np.flatnonzero(found), order[at[found]]
            same = loops.piece[a[e]] == loops.piece[a[f]]
            e, f = e[same], f[same]
            if not e.size:
                continue
            cos = (np.einsum("kab,kab->k", loops.E[e], loops.E[f]) - 1.0) / 2.0
            angle = np.arccos(np.clip(cos, -1.0, 1.0))  # of E_e E_f^T
            # The odometry between the first ends and between the second ends, less their
            # overlap (as in :func:`consistent_closures`), and the two closures' own.
            overlap = np.maximum(np.maximum(loops.pa[e], loops.pa[f])
                                 - np.minimum(loops.pb[e], loops.pb[f]), 0.0)
            var = (np.abs(loops.pa[e] - loops.pa[f]) + np.abs(loops.pb[e] - loops.pb[f])
                   - 2.0 * overlap + loops.own[e] + loops.own[f])
            with np.errstate(invalid="ignore"):  # inf - inf: through a zero-weight edge
                agree = angle ** 2 <= chi2_999 * sigma ** 2 * var
            np.add.at(votes, e, np.where(agree, 1, -1))
            joined.append((e[agree], f[agree]))
    e = np.concatenate([x for x, _ in joined]) if joined else np.zeros(0, np.int64)
    f = np.concatenate([y for _, y in joined]) if joined else np.zeros(0, np.int64)
    run = connected_components(coo_matrix((np.ones(e.size), (e, f)), shape=(a.size,) * 2),
                               directed=False)[1]
    return votes > 0, run


def _mutually_consistent(conflict: BoolArray) -> BoolArray:
    """A set with no pair in ``conflict`` (symmetric): the member in the most conflicts is
    dropped, then again, until none is left (ties: the lowest index)."""
    degree = conflict.sum(axis=1, dtype=np.int64)
    alive = np.ones(conflict.shape[0], bool)
    dropped = np.iinfo(np.int64).min // 2  # below any count, however many decrements follow
    while degree.size:
        worst = int(np.argmax(degree))
        if degree[worst] <= 0:
            break
        alive[worst] = False
        degree -= conflict[worst]  # (conflict is symmetric: its neighbours lose one each)
        degree[worst] = dropped
    return alive
