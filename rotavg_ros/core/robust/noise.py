"""The noise scale and the inlier threshold, estimated from residual angles.

Residual angles ``r`` (radians) of edges against a solution are modelled as a mixture:

* inliers: isotropic Gaussian noise of standard deviation ``s`` per axis of the rotation
  vector, so ``r`` follows a Maxwell (chi, 3 degrees of freedom) distribution of scale ``s``;
* outliers: rotations uniform on SO(3), whose angle has density ``(1 - cos r) / pi`` on
  ``[0, pi]``.

On a planar problem (every measurement turns about one common axis: a 2D front end's
headings, :func:`noise_axes`) both have one axis: the inliers' angles are half-normal (chi,
1 degree of freedom) of scale ``s``, and a wrong heading is uniform on the circle, its angle
uniform on ``[0, pi]``. The solver sets :data:`NOISE_AXES` per component (one axis only
where the graph is no odometry chain with sparse loop closures: see
``RotationAverager.solve_component``).

An EM fit gives ``s`` and the inlier fraction; the inlier threshold is the angle where an
edge becomes more likely an outlier than an inlier. With no outliers the threshold moves far
into the inlier tail, so clean graphs lose no edges; with high noise it grows with ``s``.
"""

from __future__ import annotations

import math
from contextvars import ContextVar
from dataclasses import dataclass

import numpy as np

from rotavg_ros.core.so3 import log_map
from rotavg_ros.core.types import BoolArray, FloatArray

NOISE_AXES: ContextVar[int] = ContextVar("NOISE_AXES", default=3)
"""Axes of the rotation vector the noise acts on: 3, or 1 on a planar problem
(:func:`noise_axes`). Read by :func:`fit_noise` and :func:`looks_gaussian`, by the closure
tests for their chi-square quantiles (:mod:`.closure_consistency`, :mod:`.closure_runs`) and
by the solver for its cross-validation (``l1_from_fold``)."""

PLANAR_TOLERANCE = 1e-12
"""A problem is planar where the measurements' rotation vectors have a second moment
``sum v v^T`` whose two smaller eigenvalues sum to at most this fraction of the largest:
exactly planar input (a 2D g2o file lifted to 3D, a planar robot's headings) gives rounding
only (0 to rounding); a ground robot measured in 3D with 0.1 deg of roll and pitch noise on
headings of up to a radian about 2e-5, and stays three-axis."""

_MEDIAN_OF_CHI = {1: 0.6745, 3: 1.538}
"""Median of the unit-scale chi distribution with 1 and 3 degrees of freedom."""


def noise_axes(R: FloatArray) -> int:
    """1 where every rotation in ``R`` (E, 3, 3) turns about one common axis (a planar
    problem: its noise and its residuals have one axis), else 3."""
    v = log_map(np.asarray(R, dtype=np.float64).reshape(-1, 3, 3))
    moments = np.linalg.eigvalsh(v.T @ v)  # ascending
    if not moments[2] > 0.0:
        return 3
    return 1 if moments[0] + moments[1] <= PLANAR_TOLERANCE * moments[2] else 3


@dataclass(frozen=True)
class NoiseModel:
    """Fitted mixture: per-axis noise ``sigma`` (rad), inlier fraction, threshold (rad), and
    the axes the noise acts on (3, or 1 on a planar problem)."""

    sigma: float
    inlier_fraction: float
    threshold: float
    axes: int = 3

    @property
    def sigma_deg(self) -> float:
        return math.degrees(self.sigma)


def _log_maxwell(r: FloatArray, s: float) -> FloatArray:
    return 0.5 * math.log(2.0 / math.pi) + 2.0 * np.log(np.maximum(r, 1e-300)) \
        - 3.0 * math.log(s) - r * r / (2.0 * s * s)


def _log_uniform(r: FloatArray) -> FloatArray:
    return np.log(np.maximum(1.0 - np.cos(r), 1e-300) / math.pi)


def _log_inlier(r: FloatArray, s: float, axes: int) -> FloatArray:
    """Log density of an inlier's residual angle: Maxwell (3 axes) or half-normal (1)."""
    if axes == 3:
        return _log_maxwell(r, s)
    return 0.5 * math.log(2.0 / math.pi) - math.log(s) - r * r / (2.0 * s * s)


def _log_outlier(r: FloatArray, axes: int) -> FloatArray:
    """Log density of an outlier's residual angle: a rotation uniform on SO(3) (3 axes) or
    a heading uniform on the circle (1: uniform on ``[0, pi]``)."""
    if axes == 3:
        return _log_uniform(r)
    return np.full(np.shape(r), -math.log(math.pi))


def fit_noise(
    r: FloatArray, min_sigma: float = math.radians(0.05), max_threshold: float = math.radians(60),
    iterations: int = 50, scale: FloatArray | None = None,
) -> NoiseModel:
    """EM fit of the inlier/outlier mixture to residual angles ``r`` (radians).

    The inlier and outlier models are those of :data:`NOISE_AXES` (Maxwell and a uniform
    rotation; on a planar problem half-normal and a uniform heading). With ``scale``, ``r``
    are standardized residuals (raw angle / ``scale``, per edge): the inlier model stays
    as it is, and an outlier's raw angle keeps its distribution ``g``, so its density in
    standardized units is ``scale g(r scale)``.
    ``min_sigma`` keeps the scale away from zero (exact data); the threshold is capped at
    ``max_threshold``. Returns a wide threshold when there are too few residuals to fit.
    """
    axes = NOISE_AXES.get()
    r = np.asarray(r, dtype=np.float64)
    ok = np.isfinite(r)
    sc = np.ones(r.shape) if scale is None else np.asarray(scale, dtype=np.float64)
    r, sc = r[ok], sc[ok]
    if r.size < 5:
        return NoiseModel(math.radians(5.0), 1.0, max_threshold, axes)
    r = np.maximum(r, 1e-9)
    if scale is None:
        r = np.minimum(r, math.pi)
    s = max(float(np.median(r)) / _MEDIAN_OF_CHI[axes], min_sigma)
    p = 0.8
    log_out = np.log(sc) + _log_outlier(np.minimum(r * sc, math.pi), axes)
    for _ in range(iterations):
        a = math.log(p) + _log_inlier(r, s, axes)
        b = math.log(1.0 - p) + log_out
        gamma = 1.0 / (1.0 + np.exp(np.clip(b - a, -700, 700)))
        total = float(gamma.sum())
        if total <= 0:
            break
        s_new = max(math.sqrt(float((gamma * r * r).sum()) / (axes * total)), min_sigma)
        p_new = min(max(total / r.size, 1e-3), 1.0 - 1e-6)
        done = abs(s_new - s) < 1e-6 * s and abs(p_new - p) < 1e-6
        s, p = s_new, p_new
        if done:
            break
    return NoiseModel(s, p, _crossing(s, p, max_threshold, axes), axes)


def is_inlier(r: FloatArray, model: NoiseModel, scale: FloatArray | None = None,
              max_threshold: float = math.pi) -> BoolArray:
    """Per residual: more likely an inlier than an outlier under ``model`` (and at most
    ``max_threshold``). With ``scale``, ``r`` are standardized residuals and each outlier
    density is taken at its own scale, as in :func:`fit_noise`."""
    r = np.maximum(np.asarray(r, dtype=np.float64), 1e-9)
    sc = np.ones(r.shape) if scale is None else np.asarray(scale, dtype=np.float64)
    p = model.inlier_fraction
    if p >= 1.0:
        return r <= max_threshold
    log_in = math.log(p) + _log_inlier(r, model.sigma, model.axes)
    log_out = math.log(1.0 - p) + np.log(sc) + _log_outlier(np.minimum(r * sc, math.pi),
                                                            model.axes)
    return (log_in >= log_out) & (r <= max_threshold)


def log_likelihood(r: FloatArray, model: NoiseModel) -> float:
    """Log-likelihood of residual angles ``r`` (radians) under the fitted mixture."""
    r = np.clip(np.asarray(r, dtype=np.float64), 1e-9, math.pi)
    p = model.inlier_fraction
    a = math.log(p) + _log_inlier(r, model.sigma, model.axes)
    b = (math.log(1.0 - p) + _log_outlier(r, model.axes) if p < 1.0
         else np.full(r.shape, -np.inf))
    return float(np.sum(np.logaddexp(a, b)))


def _crossing(s: float, p: float, cap: float, axes: int = 3) -> float:
    """Smallest angle above the inlier mode (half-normal: above one scale) where outliers
    become more likely; <= cap."""
    mode = s * math.sqrt(2.0) if axes == 3 else s
    grid = np.linspace(mode, max(cap, mode), 2000)
    more_out = (math.log(1.0 - p) + _log_outlier(grid, axes)
                > math.log(p) + _log_inlier(grid, s, axes))
    hit = np.flatnonzero(more_out)
    return min(float(grid[hit[0]]), cap) if hit.size else cap


GAUSSIAN_SHAPE = 0.90
"""Residual angles whose :func:`residual_shape` is at least this look Gaussian: within 0.02
of a Maxwell distribution's 0.921 (isotropic Gaussian noise per axis; the sampling spread
of the ratio is about 0.097 / sqrt(n): 0.02 is four standard errors at 400 residuals). Lower:
residuals peaked at zero or heavy-tailed, where an L1 fit beats least squares (an angle
``|N(0, s)|`` about a random axis: 0.798; the re-solves' standardized residuals on the
regime benchmark: 0.84-0.87 under that noise, 0.920-0.923 under Gaussian tangent noise;
Ellis Island's raw residuals: 0.73)."""

RANK_TOLERANCE = 1e-9
"""An axis of the residual vectors' second-moment matrix with an eigenvalue below this times
the largest carries no noise (a planar robot's roll and pitch: rounding only)."""


def residual_shape(t: FloatArray, inlier: BoolArray, vectors: FloatArray | None = None,
                   ) -> float:
    """``mean / RMS`` of the finite residual angles ``t`` of the ``inlier`` edges (NaN when
    fewer than 20): 0.921 for Maxwell-distributed residuals, lower for residuals peaked at
    zero or heavy-tailed, where an L1 fit beats least squares.

    ``vectors``: the ``(E, 3)`` residual rotation vectors whose angles ``t`` standardizes.
    Where noise shows on all three axes, the shape is then that of the standardized vectors
    (``t`` along each vector's axis) whitened by their second moment: Gaussian noise larger
    about one axis (a SLAM front end's heading) then reads 0.921 as isotropic noise does,
    where its angles read peaked (three times larger: 0.87). Noise on fewer axes (a planar
    robot's headings) keeps the angles' shape (one axis: 0.798, peaked; see
    docs/method.md)."""
    keep = np.asarray(inlier, bool) & np.isfinite(t)
    r = np.abs(np.asarray(t, dtype=np.float64)[keep])
    if r.size < 20 or not np.any(r > 0):
        return math.nan
    if vectors is not None:
        v = np.asarray(vectors, dtype=np.float64)[keep]
        angle = np.linalg.norm(v, axis=1)
        v = v * (r / np.where(angle > 0, angle, 1.0))[:, None]  # t along each axis
        values, axes = np.linalg.eigh(v.T @ v / r.size)
        if values[0] > RANK_TOLERANCE * values[-1]:
            r = np.linalg.norm((v @ axes) / np.sqrt(values), axis=1)
    return float(np.mean(r) / math.sqrt(float(np.mean(r * r))))


GAUSSIAN_SHAPE_PLANAR = 0.78
""":data:`GAUSSIAN_SHAPE` on a planar problem (:data:`NOISE_AXES` 1): within 0.02 of a
half-normal distribution's ``sqrt(2 / pi)`` = 0.798, Gaussian noise on one axis. The
half-normal's ratio spreads more (about 0.21 / sqrt(n)): 0.02 is two standard errors at
400 residuals, not four: Gaussian heading noise reads peaked 4.5% of the time there, 17% at
100 (simulated). The bound was measured as it is (docs/benchmarks.md, "Planar robots: a
one-axis noise model")."""


def looks_gaussian(t: FloatArray, inlier: BoolArray, vectors: FloatArray | None = None,
                   ) -> bool:
    """Whether the residual angles ``t`` of the ``inlier`` edges (with their residual
    rotation ``vectors``, whitened) look Gaussian (:func:`residual_shape` at least
    :data:`GAUSSIAN_SHAPE`, or :data:`GAUSSIAN_SHAPE_PLANAR` on a planar problem; False where
    it is undefined): least squares is then the better estimator on those edges."""
    shape = residual_shape(t, inlier, vectors)
    bound = GAUSSIAN_SHAPE if NOISE_AXES.get() == 3 else GAUSSIAN_SHAPE_PLANAR
    return math.isfinite(shape) and shape >= bound


def redundancy(num_nodes: int, inlier: BoolArray) -> float:
    """Mean redundancy of a connected graph's ``inlier`` edges, ``(m - n + 1) / m``: one
    minus the mean leverage of its least-squares fit, at any weights (the hat matrix's trace
    is the rank, 3 (n - 1), over 3 m residuals). Near 0 on an odometry chain with sparse
    loop closures, where almost every edge is needed to connect the nodes; near 1 on a dense
    view graph."""
    m = int(np.count_nonzero(inlier))
    return (m - num_nodes + 1) / m if m else 0.0
