"""Parallel measurements of one node pair that disagree, settled against a solution.

The view graph merges the measurements of one node pair into one edge (``RepeatPolicy.MERGE``:
their chordal L1 median, weighted by the sum of their weights). Where a front end re-observes
a loop closure, that averages the noise away. Where it sends two hypotheses for the same pair
(a right match and a wrong one, as gtsam's City10000 does at 200 of its odometry steps), the
median of two lies between them, and the merged edge is wrong: the verification then rejects
it, and the right measurement is lost with the wrong one (or, on a trusted odometry step,
the wrong one bends the trajectory).

Here, after a solve, each measurement of a pair measured more than once is compared with the
solution's prediction ``R_i R_j^T``: its residual angle over the spread the solve predicts it
with (``sigma sqrt(1 / w_k + q)``: the measurement's own noise at its weight ``w_k`` and the
prediction variance ``q`` of the pair from the solution's other inliers, the effective
resistance between its ends; :func:`~.gauss_newton.effective_resistances`). Where some of a
pair's measurements agree (within :data:`AGREE_SPREADS`) and others do not, the others are
set aside and the pair's edge is merged again from those that agree; the caller solves again.
Only pairs whose measurements disagree with each other (beyond :data:`AGREE_SPREADS` of
their own noise combined) are judged. One all of whose measurements agree is left merged;
one none of whose measurements agrees, or whose ends only its own edge joins in the fit
(every measurement fits it exactly), is undecided: the caller withholds those
(:attr:`ParallelVerdict.withhold`), solves without them and judges them again, where their
own edge no longer bends the solution (a pair absent from the solved edges is predicted
by the fit alone). What stays undecided is left merged and counted.

Conventions: world-to-node rotations ``R_i``, ``R_ij ~= R_i R_j^T``, measurements oriented
``i < j`` (as :meth:`~rotavg_ros.core.view_graph.ViewGraph.measurement_arrays` gives them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from rotavg_ros.core.robust.gauss_newton import effective_resistances
from rotavg_ros.core.so3 import exp_map, log_map, rotation_angle
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray

AGREE_SPREADS = 4.0
"""A measurement agrees with the solution where its residual angle is at most this many
predicted spreads (the verification's ``GNC_SIGMAS``: an inlier's residual angle exceeds
4.0 sigma with probability about 0.1%)."""

BRIDGE_LEVERAGE = 1.0 - 1e-6
"""A kept edge with leverage ``w q`` above this is a bridge: nothing else predicts its pair."""


@dataclass(frozen=True)
class ParallelVerdict:
    """What :func:`settle_parallel` found."""

    keep: BoolArray
    """Per raw measurement (arrival order): whether it stays in the graph."""
    set_aside: int
    """Measurements set aside: they disagreed with the solution where others of their pair
    agreed."""
    undecided: int
    """Pairs whose measurements disagree with each other that the solution could not settle:
    none of them agrees with it, or only the pair's own edge joins its ends. (Where all of
    them agree with it, its prediction of the pair is looser than their disagreement: the
    merged edge stands, not counted.)"""
    withhold: BoolArray
    """Per raw measurement: of an undecided pair. Its merged edge may have bent the solution
    towards itself, or made itself a bridge of the fit by pushing the loop closures across
    it out: the caller may solve without these and judge them again (a bridge of the whole
    graph then has no prediction and stays undecided)."""


def settle_parallel(
    num_nodes: int, mi: IntArray, mj: IntArray, mR: FloatArray, mw: FloatArray,
    edge_i: IntArray, edge_j: IntArray, edge_R: FloatArray, edge_w: FloatArray,
    kept: BoolArray, rotations: FloatArray, sigma: float,
) -> ParallelVerdict | None:
    """The measurements ``(mi, mj, mR, mw)`` (raw, ``mi < mj``) of the pairs measured more
    than once, judged against ``rotations`` (world-to-node, one per node), the solution of
    the merged edges ``(edge_i, edge_j, edge_R)`` (one per pair, weights ``edge_w``) whose inliers
    are ``kept``; ``sigma``: the solve's noise scale (radians per axis of an edge of mean
    weight). None where no pair is measured more than once or ``sigma`` is not finite."""
    if mi.size == 0 or not (np.isfinite(sigma) and sigma > 0):
        return None
    key = mi * num_nodes + mj
    pairs, group, counts = np.unique(key, return_inverse=True, return_counts=True)
    scale = float(np.mean(edge_w))
    own_spread = sigma * np.sqrt(scale / mw)
    multi = np.flatnonzero(counts > 1)
    if multi.size == 0:
        return None
    k = np.flatnonzero(counts[group] > 1)
    at = np.searchsorted(multi, group[k])  # each measurement's row in ``multi``
    # Only pairs whose measurements disagree with each other are judged: the others' merged
    # edge is their average, as it should be.
    disagree = _disagree_within(mR[k], at, multi.size, own_spread[k])
    keep = np.ones(mi.size, bool)
    if not disagree.any():
        return ParallelVerdict(keep, 0, 0, np.zeros(mi.size, bool))
    judged = multi[disagree]
    k = np.flatnonzero(np.isin(group, judged))
    at = np.searchsorted(judged, group[k])  # each judged measurement's row in ``judged``
    pi, pj = pairs[judged] // num_nodes, pairs[judged] % num_nodes
    # Each judged pair's edge among those solved (absent: withheld from the solve).
    edge_key = edge_i * num_nodes + edge_j
    pos = np.minimum(np.searchsorted(edge_key, pairs[judged]), max(edge_key.size - 1, 0))
    present = (edge_key.size > 0) & (edge_key[pos] == pairs[judged])
    w_fit = np.where(kept, edge_w / scale, 0.0)
    own = np.where(present, w_fit[pos], 0.0)
    q, leverage, predicted = _prediction_variance(num_nodes, edge_i, edge_j, w_fit, pi, pj,
                                                  own)
    # The pair's prediction from the other edges: where its merged edge is in the fit, the
    # solution leans towards it; without it, the fitted residual grows by 1 / (1 - h)
    # (the deletion formula of least squares, in the merged edge's tangent space).
    fitted = rotations[pi] @ np.swapaxes(rotations[pj], 1, 2)
    merged = np.where(present[:, None, None], edge_R[pos], fitted)
    lean = log_map(fitted @ np.swapaxes(merged, 1, 2))
    alone = exp_map(lean / np.maximum(1.0 - leverage, 1e-12)[:, None]) @ merged
    r = rotation_angle(mR[k] @ np.swapaxes(alone[at], 1, 2))
    spread = np.sqrt(own_spread[k] ** 2 + sigma ** 2 * q[at])
    agree = predicted[at] & (r <= AGREE_SPREADS * spread)
    n_agree = np.bincount(at, agree.astype(np.float64), judged.size)
    settled = (n_agree > 0) & (n_agree < counts[judged])
    keep[k] = ~(settled[at] & ~agree)
    undecided = ~settled & ((n_agree == 0) | ~predicted)
    withhold = np.zeros(mi.size, bool)
    withhold[k] = undecided[at]
    return ParallelVerdict(keep, int((~keep).sum()), int(undecided.sum()), withhold)


def _prediction_variance(n: int, i: IntArray, j: IntArray, w_fit: FloatArray,
                         pi: IntArray, pj: IntArray, own: FloatArray,
                         ) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Per pair ``(pi, pj)``: ``q``, the variance of its prediction from the edges of the
    fit other than its own (weights ``w_fit``; 0: not in the fit; ``own``: the pair's own
    edge's weight in it, 0 where it has none there), in units of a unit-weight edge's noise
    variance; its own edge's leverage ``h = own q_with``; and whether there is a prediction
    (False: a bridge of the fit, or ends in different pieces of it). Each piece of the fit
    is factored on its own."""
    q = np.zeros(pi.size)
    leverage = np.zeros(pi.size)
    predicted = np.zeros(pi.size, bool)
    fit = w_fit > 0
    pieces = connected_components(
        coo_matrix((np.ones(int(fit.sum())), (i[fit], j[fit])), shape=(n, n)),
        directed=False)[1]
    a, b = pieces[pi], pieces[pj]
    for piece in np.unique(a[a == b]):
        rows = np.flatnonzero((a == piece) & (b == piece))
        nodes = np.flatnonzero(pieces == piece)
        local = np.full(n, -1, np.int64)
        local[nodes] = np.arange(nodes.size)
        inside = fit & (pieces[i] == piece)
        li, lj = local[i[inside]], local[j[inside]]
        # the pairs, appended with weight 0: their resistances in the fit as it is
        q_with = effective_resistances(
            nodes.size, np.r_[li, local[pi[rows]]], np.r_[lj, local[pj[rows]]],
            np.r_[w_fit[inside], np.zeros(rows.size)], np.arange(li.size, li.size + rows.size))
        h = own[rows] * q_with
        bridge = h > BRIDGE_LEVERAGE
        q[rows] = q_with / np.maximum(1.0 - h, 1e-12)
        leverage[rows] = np.where(bridge, 0.0, h)
        predicted[rows] = ~bridge
    return q, leverage, predicted


def _disagree_within(R: FloatArray, pair_of: IntArray, num_pairs: int,
                     spread: FloatArray) -> BoolArray:
    """Per pair: whether some of its measurements lie farther from its first one than
    :data:`AGREE_SPREADS` times both their spreads combined (``spread``: each measurement's
    own, radians)."""
    first = np.full(num_pairs, -1, np.int64)
    order = np.arange(pair_of.size)
    first[pair_of[::-1]] = order[::-1]  # each pair's first measurement
    f = first[pair_of]
    d = rotation_angle(R @ np.swapaxes(R[f], 1, 2))
    far = d > AGREE_SPREADS * np.hypot(spread, spread[f])
    return np.bincount(pair_of, far.astype(np.float64), num_pairs) > 0
