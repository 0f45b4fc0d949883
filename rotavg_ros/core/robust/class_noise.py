"""One noise scale for the odometry, one for the loop closures, where the weights say none.

A SLAM front end that reports no covariances sends every edge at the same weight, yet its
odometry is usually far more precise than its loop closures. Least squares (and the DMF's
weighted loss) with equal weights then spreads each loop's misclosure over the odometry as
much as over the closures. The two noise scales are *variance components* (Helmert, Förstner):
on the inliers' weighted least-squares fit, class ``g`` (odometry, or the other edges) has

    s_g^2 = sum_{e in g} w_e |e_e|^2 / (3 r_g),      r_g = sum_{e in g} (1 - h_e),

with ``h_e = w_e q_e`` the edge's leverage (:func:`~.gauss_newton.prediction_variance`) and
``r_g`` the class's share of the fit's redundancy (the ``r_g`` sum to ``m - n + 1``). The
odometry's weights are scaled by ``s_loop^2 / s_odometry^2`` and the fit repeated until the
ratio settles (the leverages move with the weights; secant steps on its log).

The verification cut the inliers at a standardized residual, but it trusts the odometry
whatever its residual: only the loop closures lost their tail. Both classes are counted up to
that same cut (on the first fit; the same edges on every refit). Without it, equal noise read
as noisier odometry wherever the verification had rejected true closures (a planar
sphere2500 at 20 deg of heading noise, 145 rejected: 1.08 x, 4.0 standard errors).

Leverages come from random probes (:func:`~.gauss_newton.prediction_variance`), exact
where the probes cannot tell an edge's side of the cut (:data:`PROBE_MARGIN`). The probes'
error is relative to the leverage, so the class of the larger leverages (odometry weighted
up) takes its sum from the fit's rank, which all leverages sum to, minus the other class's.

The scales are used only where they differ beyond doubt: ``|log(s_odo^2 / s_loop^2)|``
above :data:`SIGNIFICANCE_Z` standard errors, each class's relative variance taken from its
own residuals (no Gaussian assumption: folded, peaked noise has heavier ``|e|^2`` tails). An
odometry chain with a few loop closures has a loop redundancy of a few units, and closures
that may be false: the solver does not ask there (below ``least_squares_below_redundancy``,
where such a refit ran away on a planar chain whose false closures the verification kept).
Conventions as in :mod:`.gauss_newton`: world-to-node rotations, ``R_ij ~= R_i R_j^T``, node
0 fixed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from rotavg_ros.core.robust.gauss_newton import (
    prediction_variance,
    refine_least_squares,
    residual_angles,
)
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray

SIGNIFICANCE_Z = 3.29
"""Standard errors of the log variance ratio beyond which the two classes' noise differs
(two-sided 0.1%: equal noise passes for different about once in a thousand graphs)."""
ITERATIONS = 8
"""Refits of the inliers at most while the ratio settles."""
MAX_STEP = math.log(10.0)
"""Largest change of the odometry's weight in one refit: a factor of 10."""
SETTLED = 0.01
"""The ratio has settled when a refit moves its log by less than this."""
MIN_REDUNDANCY = 3.0
"""Each class needs at least this share of the redundancy ``r_g`` to be estimated at all."""
PROBE_MARGIN = 0.3
"""Two standard errors of :func:`~.gauss_newton.prediction_variance`'s leverages from 32
probes (relative error ``sqrt(2 / 96)``): an edge whose standardized residual is within
that of the cut is counted or not on its exact leverage. On the probes alone, an edge of
high leverage (odometry between few closures) whose ``1 - h`` they underestimated was
dropped, one they overestimated kept: the counted odometry's redundancy read high and its
noise low. A planar chain of 600 keyframes with closures on 18% of them, 40% of those
false, odometry at 1 deg and closures at 2: the odometry's variance read 0.53 x the
closures' (3.7 standard errors apart), the refit weighted it 9.5 x, 1.62 deg median
against the oracle's 1.04; now 0.61 x (3.0, equal weights kept), 0.97 deg. (3 standard
errors gave the same results at twice the exact solves: torus3D rand10 0.32 s against
0.16 s in the class-noise step.)"""


@dataclass(frozen=True)
class ClassNoise:
    """The variance components of one graph's inliers.

    ``ratio``: the first fit's ``s_odometry^2 / s_loop^2`` (equal weights, or the weights
    given); ``z``: its log in standard errors; ``significant``: ``z`` above
    :data:`SIGNIFICANCE_Z`; ``factor``: where significant, the weight multiplier of the
    odometry edges at which the refits' ratio settled, else 1."""

    ratio: float
    z: float
    factor: float
    significant: bool


def _components(rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
                odometry: BoolArray, use: BoolArray | None, cut: float, seed: int,
                rank: int) -> tuple[float, float, float, float, BoolArray]:
    """``(s_odo^2, s_loop^2, relative variance of each, edges counted)`` on the fit ``rot``
    of these edges, counting the edges ``use`` (None: those whose standardized residual is
    at most ``cut``); ``rank``: :func:`_rank` of the fitted edges."""
    q = w * residual_angles(rot, i, j, R) ** 2
    cut2 = cut * cut

    def near_the_cut(q_probe: FloatArray) -> BoolArray:
        """The edges whose side of the cut the probes' leverage cannot tell."""
        h_probe = w * q_probe
        if use is not None or math.isinf(cut):
            return np.zeros(q_probe.shape, bool)
        return np.abs(q - cut2 * (1.0 - h_probe)) <= PROBE_MARGIN * cut2 * h_probe

    h = w * prediction_variance(rot, i, j, w, seed=seed, exact=near_the_cut)
    if use is None:
        use = (np.ones(q.shape, bool) if math.isinf(cut)
               else q <= cut2 * np.maximum(1.0 - h, 0.0))  # standardized residual <= cut
    # The leverages sum to the fit's rank. The probes' error grows with the leverage, so
    # the class of the larger leverages takes its sum from the rank minus the other's.
    odo_h, loop_h = float(np.sum(h[odometry])), float(np.sum(h[~odometry]))
    if np.sum(h[odometry] ** 2) > np.sum(h[~odometry] ** 2):
        odo_h = rank - loop_h
    else:
        loop_h = rank - odo_h
    out: list[float] = []
    spreads: list[float] = []
    for cls, cls_h in ((odometry, odo_h), (~odometry, loop_h)):
        g = cls & use
        r = float(np.count_nonzero(g)) - (cls_h - float(np.sum(h[cls & ~use])))
        if not r >= MIN_REDUNDANCY:
            return math.nan, math.nan, math.nan, math.nan, use
        s2 = float(np.sum(q[g])) / (3.0 * r)
        # Var of sum q over its mean: each edge's q scatters about 3 s^2 (1 - h).
        spread = float(np.sum((q[g] - 3.0 * s2 * (1.0 - h[g])) ** 2)) / (3.0 * r * s2) ** 2
        out.append(s2)
        spreads.append(spread)
    return out[0], out[1], spreads[0], spreads[1], use


def _rank(n: int, i: IntArray, j: IntArray) -> int:
    """Rank of the graph Laplacian of the edges ``(i, j)`` on ``n`` nodes: the nodes they
    reach minus their connected pieces (the sum of the fit's leverages, per axis)."""
    reached = np.zeros(n, bool)
    reached[i] = reached[j] = True
    pieces = connected_components(coo_matrix((np.ones(i.size), (i, j)), shape=(n, n)),
                                  directed=False)[1]
    return int(np.count_nonzero(reached) - np.unique(pieces[reached]).size)


def class_noise(rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
                inlier: BoolArray, odometry: BoolArray, cut: float = math.inf, seed: int = 0,
                ) -> ClassNoise | None:
    """The odometry's and the loop closures' noise on the ``inlier`` edges, from the solution
    ``rot`` (module docstring), counting in both classes only the edges whose standardized
    residual on the first fit is at most ``cut`` (the verification's inlier threshold, radians
    of a unit-weight edge); None where either class has too little redundancy to say (a
    chain with few closures, no odometry), the fit degenerates or the ratio does not settle
    within :data:`ITERATIONS` refits."""
    keep = np.asarray(inlier, bool)
    ii, jj, RR, ww, odo = i[keep], j[keep], R[keep], w[keep], odometry[keep]
    if not (odo.any() and (~odo).any()):
        return None
    # Root of g(f) = log(s_odo^2 / s_loop^2) at odometry weights e^f, which grows with f:
    # plain refits (f -= g) approach it slowly where the first fit's leverages are far off
    # (0.42 -> 0.89 in eight refits on a chain with odometry 6 x more precise), so secant
    # steps, each at most MAX_STEP in f.
    fs: list[float] = []
    gs: list[float] = []
    use: BoolArray | None = None
    f, ratio, z = 0.0, math.nan, math.nan
    fitted = ww > 0  # the same edges at every refit (the odometry's factor is positive)
    rank = _rank(rot.shape[0], ii[fitted], jj[fitted])
    for _ in range(ITERATIONS):
        wk = ww * np.where(odo, math.exp(f), 1.0)
        rot = refine_least_squares(rot, ii, jj, RR, wk)
        s_odo, s_loop, v_odo, v_loop, use = _components(rot, ii, jj, RR, wk, odo, use, cut,
                                                        seed, rank)
        if not (s_odo > 0.0 and s_loop > 0.0 and math.isfinite(v_odo + v_loop)):
            return None
        g = math.log(s_odo / s_loop)
        if not fs:
            ratio, z = s_odo / s_loop, abs(g) / math.sqrt(max(v_odo + v_loop, 1e-300))
            if not z > SIGNIFICANCE_Z:  # equal, as far as the data can tell
                return ClassNoise(ratio, z, 1.0, False)
        elif abs(g) < SETTLED:
            return ClassNoise(ratio, z, math.exp(f), True)
        slope = (g - gs[-1]) / (f - fs[-1]) if fs else 0.0
        fs.append(f)
        gs.append(g)
        step = -g / slope if slope > 0.0 else -g
        f += max(-MAX_STEP, min(MAX_STEP, step))
    return None  # the ratio did not settle: the data cannot say it
