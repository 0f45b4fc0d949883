"""A systematic bias of the odometry, estimated from the loop closures and removed.

A gyro's bias turns every odometry step the same small way: the measured step from
keyframe ``k`` to ``k + 1`` is ``S_k = Exp(beta) S_k_true``, one rotation vector ``beta``
(radians a step) in frame ``k``. The loops the closures close over the odometry then miss
by an error that grows with their length, where the odometry's noise makes it grow as a
random walk's square root; the loop tests (:mod:`.closure_consistency`) read that as
inconsistency and reject true closures, and a start composed from the odometry drifts.

The estimate is the ``beta`` under which the closures' loops read the lowest noise scale:
their squared loop angles over their random-walk variance, the lower quantile of
:func:`~.closure_consistency.loop_noise_scale`, which stands while most closures are false.
Each loop's error ``log(E_e(beta))`` (``E_e = Q_a^T R_ab Q_b``, ``Q`` the odometry composed
with every step corrected by ``Exp(-beta)``), taken in the loop's own first frame, is
linearized in ``beta`` by finite differences. Each pair of the shortest loops proposes the
``beta`` that closes it (a long loop's error may have wrapped past a half turn and read
small by chance); from zero and from the best proposal, Gauss-Newton rounds on the loops
consistent at the current scale bring ever longer loops in, as the estimate's uncertainty
keeps their errors in the linear range.

The correction stands only where it passes a test (:func:`_tested`): a generalized
least squares of the loop errors, whose covariance is the odometry the loops share, so that
the realized drift of a random walk, which every loop over the same stretch repeats, is not
read as a bias (the lower quantile alone is: on unbiased graphs it fell below half its
uncorrected value on 26 of 399 record and stress graphs, down to 0.13, and the correction
cost up to 5x the median error there), in the whole trajectory and in each half of it (a
group of mutually consistent false closures in one place can pass for a bias too, but only
in its own half).

Conventions: world-to-node ``R_i``, ``R_ij ~= R_i R_j^T``; odometry edges join consecutive
node indices.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_triangular

from rotavg_ros.core.robust.closure_consistency import (
    CHI2_1_999,
    CHI2_1_Q25,
    CHI2_3_999,
    CHI2_3_Q25,
    LOOP_QUANTILE,
    ClosureLoops,
    closure_loops,
)
from rotavg_ros.core.robust.noise import NOISE_AXES, noise_axes
from rotavg_ros.core.so3 import exp_map, log_map
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray

MIN_CLOSURES = 8
"""Fewer testable closures than this: no estimate (three unknowns need some redundancy)."""
MAX_LOOPS = 1000
"""At most this many closures' loops (evenly spread) enter the estimate: each round
composes the odometry and every loop again."""
ROUND_MAX_ANGLE = math.radians(120.0)
"""Loops whose error is above this are left out of a Gauss-Newton round (outside the
linear range; at 60 and 90 deg a chain of 3,000 keyframes at 1 deg a step crept toward
its bias too slowly to reach it in :data:`REFINE_ROUNDS`)."""
LINEAR_SPREAD = math.radians(45.0)
"""A loop joins a Gauss-Newton round where the current estimate's uncertainty moves its
error by less than this (standard deviation): far from wrapping past a half turn."""
PROPOSERS = 12
"""The shortest this many loops (by odometry variance) propose a bias, in pairs."""
REFINE_ROUNDS = 24
"""At most this many Gauss-Newton rounds from each start."""
TEST_SPREAD = math.radians(15.0)
"""The significance test takes the loops whose error the corrected noise scale spreads by
less than this (per axis): longer loops' errors no longer add up as the random walk's
first-order model says (chains of 3,000 keyframes at 1.5 deg a step, unbiased, all their
loops: the test statistic 32-61 in 4 of 6 draws, where the model says a chi-square)."""
TEST_ROUNDS = 6
"""At most this many rounds of choosing the tested loops and refitting on them."""
GLS_ROUNDS = 2
"""Gauss-Newton rounds of the generalized least-squares refit of the estimate."""
MIN_TESTED = 4
"""Fewer loops than this (in all, or in a half of the trajectory): nothing to test by."""
MAX_TESTED = 200
"""The significance test takes at most this many loops (evenly spread): its covariance is
their number squared, its factorization cubed (at 1,500, 2.2 s of a 2.4 s estimate on
sphere2500)."""
TESTED_BELOW = 0.8
"""Only an estimate under which the loops' scale falls below this share of the uncorrected
one is tested (the test costs more than the estimate; every bias of 0.2 deg a step and
more on the suite's chains read below 0.75, unbiased chains 0.56-0.99)."""
_STEP = 1e-4  # finite-difference step of the linearization (radians a step)


@dataclass(frozen=True)
class OdometryBias:
    """The estimate: ``beta`` (3, rotation vector a step in the step's first frame,
    radians), whether it stands (``applied``), and the loops' noise scale (per axis of a
    unit-weight edge, radians) without and with it."""

    beta: FloatArray
    applied: bool
    scale_before: float
    scale_after: float

    @property
    def degrees_per_step(self) -> float:
        return math.degrees(float(np.linalg.norm(self.beta)))


class _Loops:
    """The odometry steps oriented ``k -> k + 1`` and the closures' loops over them: their
    ends, variances and own ``1 / w`` as :func:`~.closure_consistency.closure_loops` gives
    them (at most :data:`MAX_LOOPS`, those of finite variance)."""

    def __init__(self, num_nodes: int, i: IntArray, j: IntArray, R: FloatArray,
                 odometry: BoolArray, loops: ClosureLoops) -> None:
        lo = np.minimum(i, j)
        forward = i < j
        self.steps = np.tile(np.eye(3), (max(num_nodes - 1, 0), 1, 1))
        self.has_step = np.zeros(max(num_nodes - 1, 0), bool)
        oe = np.flatnonzero(odometry)
        self.steps[lo[oe]] = np.where(forward[oe, None, None], R[oe],
                                      R[oe].transpose(0, 2, 1))
        self.has_step[lo[oe]] = True
        with np.errstate(invalid="ignore"):
            var = loops.pb - loops.pa + loops.own
        # (A zero weight on the way: an infinite variance, a loop that tells nothing.)
        ok = np.isfinite(var) & (var > 0.0)
        if np.count_nonzero(ok) > MAX_LOOPS:  # (evenly spread: plenty for three unknowns)
            spread = np.flatnonzero(ok)
            ok = np.zeros(ok.size, bool)
            ok[spread[np.linspace(0, spread.size - 1, MAX_LOOPS).astype(int)]] = True
        c = loops.testable[ok]
        self.a, self.b = lo[c], np.maximum(i, j)[c]
        self.Rab = np.where(forward[c, None, None], R[c], R[c].transpose(0, 2, 1))
        self.var, self.own = var[ok], loops.own[ok]
        self.pa, self.pb = loops.pa[ok], loops.pb[ok]

    def errors(self, beta: FloatArray, local: bool = False) -> FloatArray:
        """``log(E_e)`` per closure (m, 3) with every step corrected by ``Exp(-beta)``, in
        the world frame; ``local``: in the loop's first frame, ``Q_a log(E_e)``, where it
        depends on the loop's own steps only (in the world frame its direction also turns
        with every step before the loop, by the loop's error times their number: a far
        loop's error is linear in ``beta`` over a far smaller range there)."""
        Qa, world = self._composed(beta)
        return _to_frames(Qa, world) if local else world

    def errors_in_both_frames(self, beta: FloatArray) -> tuple[FloatArray, FloatArray]:
        """:meth:`errors` in the world frame and in the loops' own, from one composition."""
        Qa, world = self._composed(beta)
        return world, _to_frames(Qa, world)

    def _composed(self, beta: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The composed odometry at each loop's first node, ``Q_a`` (m, 3, 3), and the
        loops' world-frame errors ``log(E_e)`` (m, 3), every step corrected by
        ``Exp(-beta)``."""
        fix = exp_map(-beta)
        A = np.where(self.has_step[:, None, None], fix @ self.steps, self.steps)
        # Q_{k+1} = S_k^T Q_k, Q_0 = I: a cumulative product, by doubling.
        C = A.transpose(0, 2, 1).copy()
        d = 1
        while d < C.shape[0]:
            C[d:] = C[d:] @ C[:-d]
            d *= 2
        Q = np.concatenate([np.eye(3)[None], C])
        Qa = Q[self.a]
        return Qa, log_map(Qa.transpose(0, 2, 1) @ self.Rab @ Q[self.b])

    def jacobian(self, beta: FloatArray, at: FloatArray, local: bool = False) -> FloatArray:
        """d log(E_e) / d beta per closure (m, 3, 3), by finite differences from ``at``
        (:meth:`errors` at ``beta``, in the same frame: ``local``)."""
        J = np.empty((at.shape[0], 3, 3))
        for k in range(3):
            J[:, :, k] = (self.errors(beta + _STEP * np.eye(3)[k], local) - at) / _STEP
        return J


def _to_frames(Qa: FloatArray, world: FloatArray) -> FloatArray:
    """World-frame loop errors (m, 3) in each loop's first frame: ``Q_a log(E_e)``."""
    return np.asarray(np.einsum("eij,ej->ei", Qa, world), dtype=np.float64)


def _scale(err: FloatArray, var: FloatArray) -> float:
    """The loops' noise scale: their squared angles over their variance, its
    :data:`~.closure_consistency.LOOP_QUANTILE` quantile over the chi-square's."""
    ratio = np.sum(err * err, axis=1) / var
    q25 = CHI2_3_Q25 if NOISE_AXES.get() == 3 else CHI2_1_Q25
    return math.sqrt(float(np.quantile(ratio, LOOP_QUANTILE)) / q25)


def estimate_odometry_bias(num_nodes: int, i: IntArray, j: IntArray, R: FloatArray,
                           w: FloatArray, odometry: BoolArray) -> OdometryBias | None:
    """The odometry's bias a step (module docstring); None where too few closures lie on
    one piece of the odometry with it to tell."""
    found = closure_loops(num_nodes, i, j, R, w, odometry)
    if found is None or num_nodes < 3:
        return None
    loops = _Loops(num_nodes, i, j, R, odometry, found)
    if loops.var.size < MIN_CLOSURES:
        return None
    zero = np.zeros(3)
    # The search runs on the loops' errors in their own first frames (:meth:`_Loops.errors`);
    # the test, on the world frame's.
    err0, local0 = loops.errors_in_both_frames(zero)
    before = _scale(err0, loops.var)
    if not math.isfinite(before) or before <= 0.0:
        return None
    J0 = loops.jacobian(zero, local0, local=True)
    by_length = np.argsort(loops.var, kind="stable")
    # Proposals: each pair of the shortest loops, and all of them together, solved by least
    # squares in the linearization at zero. (Short loops: a long loop's error may have
    # wrapped past a half turn, and reads small by chance.)
    short = by_length[:PROPOSERS]
    pairs = [(int(a), int(b)) for n, a in enumerate(short) for b in short[n + 1:]]
    groups = [np.array(p) for p in pairs] + [short]
    best, best_scale = zero, before
    for g in groups:
        beta = _gauss_newton_step(zero, J0[g], local0[g], loops.var[g], before)[0]
        s = _scale(loops.errors(beta), loops.var)
        if s < best_scale:
            best, best_scale = beta, s
    chi2 = CHI2_3_999 if NOISE_AXES.get() == 3 else CHI2_1_999
    # From zero and from the best proposal, reweighted Gauss-Newton on the loops consistent
    # at the current scale whose error the estimate's uncertainty keeps in the linear range
    # (the shortest PROPOSERS loops in the first round): each round's estimate brings
    # longer loops in. The lowest scale on either path stands; it need not fall each
    # round (while a strong bias is half removed the long loops still wrap).
    beta, scale = best, best_scale
    first = np.zeros(loops.var.size, bool)
    first[short] = True
    for start in (zero, best):
        path, reach, kept = start, first, np.zeros(0, np.int64)
        for _ in range(REFINE_ROUNDS):
            err = loops.errors(path, local=True)
            s = _scale(err, loops.var)
            if s < scale:
                beta, scale = path, s
            J = loops.jacobian(path, err, local=True)
            ratio = np.sum(err * err, axis=1) / loops.var
            fit = (reach & (ratio < chi2 * s * s)
                   & (np.linalg.norm(err, axis=1) < ROUND_MAX_ANGLE))
            if int(fit.sum()) < 2 or np.array_equal(np.flatnonzero(fit), kept):
                break
            kept = np.flatnonzero(fit)
            path, cov = _gauss_newton_step(path, J[fit], err[fit], loops.var[fit], s)
            with np.errstate(invalid="ignore"):
                spread = np.sqrt(np.einsum("eij,jk,eik->e", J, cov, J))
            reach = spread < LINEAR_SPREAD
    if not scale < TESTED_BELOW * before:
        return OdometryBias(beta, False, before, scale)
    # The test refits by generalized least squares from the estimate and from zero (the
    # loops it takes are those consistent with its fit, so a start it cannot leave, such as
    # an estimate wandered off in a direction the loops do not tell, keeps its own); of the
    # two that pass, the one that explains more loops stands.
    axes = noise_axes(R[odometry])
    passed = [t for t in (_tested(loops, start, err0, scale, axes) for start in (beta, zero))
              if t is not None]
    if not passed:
        return OdometryBias(beta, False, before, scale)
    tested = max(passed, key=lambda t: t[1])[0]
    return OdometryBias(tested, True, before, _scale(loops.errors(tested), loops.var))


def _tested(loops: _Loops, beta: FloatArray, err0: FloatArray, after: float,
            axes: int) -> tuple[FloatArray, int] | None:
    """The bias that stands, or None (``err0``: the loops' errors uncorrected): ``beta``
    refined by generalized least squares (GLS) over the loops consistent with it (at the
    corrected scale ``after``) and short enough for the first-order model
    (:data:`TEST_SPREAD` at the noise the fit shows), where that lowers their GLS by more
    than the 99.9% quantile of a chi-square with ``axes`` degrees of freedom (in units of
    the noise that remains), in all of them and in each half of them along the trajectory
    (by the loop's middle). The errors are in the world frame, where each step's noise is
    isotropic (about one axis on a planar problem), so two loops covary by the odometry
    variance they share: a random walk's realized drift, which every loop over the same
    stretch repeats, is no bias. The GLS refit leaves a direction the loops do not tell at
    zero, where the loops' lower quantile, flat there, may have wandered (a nearly planar
    garage's roll and pitch: up to 0.85 deg a step). A bias is one rotation a step along the
    whole trajectory; a group of mutually consistent false closures in one place can be
    fitted by a rotation a step too, but only its own half shows it."""
    chi2 = CHI2_3_999 if axes == 3 else CHI2_1_999
    fitted, sigma, stat, kept = beta, after, 0.0, np.zeros(0, np.int64)
    for _ in range(TEST_ROUNDS):  # the loops consistent with the fit, at the noise it shows
        err = loops.errors(fitted)
        inlier = np.flatnonzero((np.sum(err * err, axis=1) < chi2 * sigma * sigma * loops.var)
                                & (sigma * np.sqrt(loops.var) < TEST_SPREAD))
        if inlier.size > MAX_TESTED:
            inlier = inlier[np.linspace(0, inlier.size - 1, MAX_TESTED).astype(int)]
        if np.array_equal(inlier, kept):
            break
        kept = inlier
        whiten = _whitener(loops, inlier)
        if whiten is None:
            return None
        for _ in range(GLS_ROUNDS):
            J = loops.jacobian(fitted, err)[inlier]
            A = whiten(J.reshape(-1, 9)).reshape(-1, 3)
            rhs = -whiten(err[inlier]).reshape(-1)
            fitted = fitted + np.linalg.lstsq(A, rhs, rcond=1e-6)[0]
            err = loops.errors(fitted)
        gain = _gls_gain(whiten, err[inlier], err0[inlier], axes)
        if gain is None:
            return None
        stat, noise = gain
        sigma = math.sqrt(noise)
    if not stat > chi2:
        return None
    middle = loops.pa[inlier] + loops.pb[inlier]
    first = middle <= np.median(middle)
    for half in (inlier[first], inlier[~first]):
        whiten = _whitener(loops, half)
        gain = None if whiten is None else _gls_gain(whiten, err[half], err0[half], axes)
        if gain is None or not gain[0] > chi2:
            return None
    return fitted, kept.size


def _whitener(loops: _Loops, inlier: IntArray) -> Callable[[FloatArray], FloatArray] | None:
    """``x -> L^-1 x`` over the loops ``inlier`` (rows), ``L L^T`` their covariance in units
    of a unit-weight step's variance (the odometry they share, and each closure's own);
    None with fewer than :data:`MIN_TESTED` loops."""
    if inlier.size < MIN_TESTED:
        return None
    pa, pb = loops.pa[inlier], loops.pb[inlier]
    shared = np.minimum(pb[:, None], pb) - np.maximum(pa[:, None], pa)
    cov = np.maximum(shared, 0.0) + np.diag(loops.own[inlier])
    try:
        L = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        return None
    # (The inverse once, then products: scipy's triangular solve took 7 ms for 200 loops'
    # nine columns, the product 0.1 ms.)
    inverse = np.asarray(solve_triangular(L, np.eye(inlier.size), lower=True,
                                          check_finite=False), dtype=np.float64)
    return lambda x: inverse @ x


def _gls_gain(whiten: Callable[[FloatArray], FloatArray], err: FloatArray,
              err0: FloatArray, axes: int) -> tuple[float, float] | None:
    """How much the correction lowers the loops' generalized least squares (``err`` with
    it, ``err0`` without), in units of the noise (per axis) that remains, and that noise."""
    with_bias = float(np.sum(whiten(err) ** 2))
    without = float(np.sum(whiten(err0) ** 2))
    noise = with_bias / (axes * (err.shape[0] - 1))
    if not noise > 0.0:
        return None
    return (without - with_bias) / noise, noise


def _gauss_newton_step(beta: FloatArray, J: FloatArray, err: FloatArray,
                       var: FloatArray, sigma: float) -> tuple[FloatArray, FloatArray]:
    """``beta`` moved to where the linearized loop errors ``err + J d`` have the least
    squares, each loop weighted by ``1 / var``, and the covariance of that estimate at the
    noise scale ``sigma`` (the loops taken as independent)."""
    sw = 1.0 / np.sqrt(var)
    A = (J * sw[:, None, None]).reshape(-1, 3)
    rhs = -(err * sw[:, None]).reshape(-1)
    step = np.linalg.lstsq(A, rhs, rcond=1e-6)[0]
    cov = np.asarray(sigma * sigma * np.linalg.pinv(A.T @ A, rcond=1e-9), dtype=np.float64)
    return beta + step, cov


def remove_odometry_bias(i: IntArray, j: IntArray, R: FloatArray, odometry: BoolArray,
                         beta: FloatArray) -> FloatArray:
    """``R`` with each odometry step corrected by ``Exp(-beta)`` in its first frame (the
    lower node index): ``S_k <- Exp(-beta) S_k`` for ``S_k`` oriented ``k -> k + 1``, its
    transpose for an edge given as ``(k + 1, k)``."""
    out = R.copy()
    fix = exp_map(-np.asarray(beta, float))
    oe = np.flatnonzero(odometry)
    fwd = oe[i[oe] < j[oe]]
    back = oe[i[oe] > j[oe]]
    out[fwd] = fix @ R[fwd]
    out[back] = R[back] @ fix.T
    return out
