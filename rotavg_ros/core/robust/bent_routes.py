"""A route bent around a wrong step: the trusted jump whose cut explains the data best.

Where a car's turns make jumps common (:func:`~.odometry_breaks.rare_jumps` finds none), a
wrong odometry step is one jump among many, and on a long route least squares bends the
trusted odometry around it until no residual is an outlier: no closure points at it, no
first pass left it out, and the break test has nothing to try (a route driven twice, one
wrong step of 165 deg among 72 turns: 14.7 deg median error against the oracle's 4.5). The
fit still holds the bend as squares spread over the steps between the closures around the
wrong step, and cutting that step removes them at once. So each trusted jump is scored by
how much the least-squares sum would fall without it, to first order
(:func:`leave_one_out_drops`); steps between the same closures score alike (the closures
cannot tell them apart), so the jumps of the few best distinct scores above the penalty are
refitted without their step: least squares unbends the route, GNC-TLS at the cap judges
every edge again from there, and the refit whose truncated squares fall by more than the
penalty, the most, stands (:func:`cut_bent_jump`). The GNC brings back the closures the
bend had rejected where the cut explains them. Re-admitting only those within the cap of
the unbent route left them out, that route being least squares on the bent fit's closures
(a route driven twice, one wrong step of 108 deg among 76 turns: 84 of 117 closures kept
with the cut as without it, so the cut did not pay, 19.9 deg mean error against the
oracle's 3.7; with the GNC 115 kept, 3.9 deg).
A true turn's cut frees nothing and bends the route elsewhere. The verification runs it on
odometry chains with sparse loop closures only (:func:`~.verify.robust_resolve`): on a pose
graph dense with loops a biased odometry strains every step, and a cut that relieves the
strain can turn a block.

Conventions: odometry edges join consecutive node indices; ``R_ij ~= R_i R_j^T``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rotavg_ros.core.robust.gauss_newton import (
    edge_residuals,
    effective_resistances,
    refine_least_squares,
)
from rotavg_ros.core.robust.gnc import gnc_tls
from rotavg_ros.core.so3 import rotation_angle
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray

CANDIDATE_SCORES = 3
"""Distinct leave-one-out scores whose jumps are refitted, the best first: the steps between
the same closures tie, and the segment of the wrong step need not score best (a second wrong
step's, or a short loop's, may)."""

UNBEND_ITERATIONS = 20
"""Gauss-Newton iterations of the refit without a jump: the route may turn back by tens of
degrees."""


@dataclass(frozen=True)
class JumpCut:
    """:func:`cut_bent_jump`'s answer."""

    rotations: FloatArray
    """The refit without the jump (world-to-node, as the input)."""
    inlier: BoolArray
    """The edges it rests on: within the cap, or still trusted; never the cut jump."""
    edge: int
    """The jump cut (an index into the edge arrays)."""
    gain: float
    """How far its truncated squares fell, beyond the penalty."""


def leave_one_out_drops(rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray,
                        w: FloatArray, fit: BoolArray, edges: IntArray) -> FloatArray:
    """Per edge of ``edges`` (indices; edges of the fit ``fit``, of which ``rot`` is the
    least-squares solution at weights ``w``): how far the fit's weighted sum of squared
    residual angles falls were the edge left out, to first order, ``w r^2 / (1 - h)``
    with ``h = w q`` its leverage (:func:`~.gauss_newton.effective_resistances`, exact). An
    edge on no loop of the fit (``h`` = 1) has no residual to free: 0."""
    weights = w * fit
    q = effective_resistances(rot.shape[0], i, j, weights, edges)
    free = 1.0 - weights[edges] * q
    squares = np.sum(edge_residuals(rot, i[edges], j[edges], R[edges]) ** 2, axis=1)
    return np.asarray(np.where(free > 1e-9, weights[edges] * squares / np.maximum(free, 1e-9),
                               0.0))


def _distinct_best(candidates: IntArray, drops: FloatArray, sizes: FloatArray, floor: float,
                   count: int) -> list[int]:
    """Up to ``count`` of the ``candidates``, one per distinct drop above ``floor`` (within
    0.1%: steps between the same closures), the largest drops first; of the steps with one
    drop, the largest (``sizes``, the measured angles): the closures cannot tell those
    steps apart, and a lost track's step is more often than not larger than a turn's."""
    chosen: list[int] = []
    for k in np.argsort(-drops, kind="stable"):
        d = float(drops[k])
        if d <= floor or len(chosen) == count:
            break
        if any(abs(d - float(drops[c])) <= 1e-3 * d for c in chosen):
            continue
        tied = np.flatnonzero(np.abs(drops - d) <= 1e-3 * d)
        chosen.append(int(tied[np.argmax(sizes[tied])]))
    return [int(candidates[c]) for c in chosen]


def cut_bent_jump(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    fit: BoolArray, trusted: BoolArray, jumps: BoolArray, c: float, penalty: float,
    cost: Callable[..., float],
) -> JumpCut | None:
    """The cut of one of the ``jumps`` in the fit ``fit`` (``rot`` its least-squares
    solution, ``trusted`` the edges it trusts) that lowers ``cost`` (the truncated squares
    at the cap ``c``, called with the rotations and ``trusted=`` the edges left uncapped;
    the jump is capped in both) the most, by more than ``penalty`` caps; each refit is
    least squares without the jump from ``rot``, then GNC-TLS at ``c`` over every edge,
    the rest of ``trusted`` kept (module docstring). None where none does."""
    candidates = np.flatnonzero(jumps & fit)
    if candidates.size == 0:
        return None
    drops = leave_one_out_drops(rot, i, j, R, w, fit, candidates)
    best: JumpCut | None = None
    sizes = rotation_angle(R[candidates])
    fitted = w * fit
    for e in _distinct_best(candidates, drops, sizes, penalty * c * c, CANDIDATE_SCORES):
        still = trusted.copy()
        still[e] = False
        weights = fitted.copy()
        weights[e] = 0.0
        unbent = refine_least_squares(rot, i, j, R, weights, iterations=UNBEND_ITERATIONS)
        # Every edge judged again from the unbent route: the closures the bend had
        # rejected return where the cut explains them (module docstring).
        judged = gnc_tls(unbent, i, j, R, w, c, still)
        refit = (judged.weights > 0.0) | still
        refit[e] = False
        unbent = refine_least_squares(judged.rotations, i, j, R, w * refit)
        gain = cost(rot, trusted=still) - cost(unbent, trusted=still) - penalty * c * c
        if gain > 0.0 and (best is None or gain > best.gain):
            best = JumpCut(unbent, refit, e, gain)
    return best
