"""Graduated non-convexity with a truncated least-squares loss (GNC-TLS) on SO(3).

Yang, Antonante, Tzoumas and Carlone, "Graduated Non-Convexity for Robust Spatial Perception"
(RA-L 2020), on the geodesic residuals of :mod:`.gauss_newton`: the TLS loss
``min(r^2, c^2)`` is approached through a sequence of surrogates indexed by ``mu``, from a
nearly convex one (small ``mu``) to TLS itself (large ``mu``). Each step solves a weighted
least-squares problem (a few Gauss-Newton steps) with the closed-form weights

    w = 1                                  if r^2 <= mu / (mu + 1) c^2
    w = c / r sqrt(mu (mu + 1)) - mu       in between
    w = 0                                  if r^2 >= (mu + 1) / mu c^2

Known inliers (e.g. odometry edges) keep weight 1 throughout. Conventions as in
:mod:`.gauss_newton`: world-to-node rotations, ``R_ij ~= R_i R_j^T``, node 0 fixed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rotavg_ros.core.robust.gauss_newton import Factor, edge_residuals, gauss_newton_step
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray


@dataclass(frozen=True)
class GncResult:
    rotations: FloatArray
    weights: FloatArray
    """Final GNC weight of each edge in [0, 1] (binary once converged)."""
    steps: int


def tls_weights(r: FloatArray, c: float, mu: float) -> FloatArray:
    """The GNC-TLS weights for residual angles ``r`` at threshold ``c`` and stage ``mu``."""
    r2 = r * r
    c2 = c * c
    lo = mu / (mu + 1.0) * c2
    hi = (mu + 1.0) / mu * c2
    mid = c / np.maximum(r, 1e-300) * np.sqrt(mu * (mu + 1.0)) - mu
    return np.where(r2 <= lo, 1.0, np.where(r2 >= hi, 0.0, np.clip(mid, 0.0, 1.0)))


def gnc_tls(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    c: float | FloatArray,
    known_inlier: BoolArray | None = None, mu_factor: float = 2.0, max_steps: int = 40,
    gn_iterations: int = 1, mu_min: float = 0.0,
) -> GncResult:
    """GNC-TLS from ``rot`` with inlier threshold ``c`` (radians) on the residual angle: one
    for every edge, or one per edge.

    ``w`` are the edges' own weights (the TLS weights multiply them). Stops when every
    weight is binary or after ``max_steps`` surrogate stages. The first stage's ``mu`` makes
    every residual of ``rot`` fall in the surrogate's convex part (Yang et al.'s rule),
    floored at 1e-6 and at ``mu_min`` (a start already near a robust solution needs no
    flatter surrogate than that).
    """
    known = np.zeros(i.size, bool) if known_inlier is None else np.asarray(known_inlier, bool)
    c = np.broadcast_to(np.asarray(c, float), (i.size,))
    # The weights depend on r / c only: GNC runs on residuals in units of their threshold.
    e = edge_residuals(rot, i, j, R)
    r = np.linalg.norm(e, axis=-1) / c
    r_max2 = float(np.max(r[~known] ** 2)) if np.any(~known) else 0.0
    if r_max2 <= 1.0:  # every residual already within the threshold: plain LS
        mu = np.inf
    else:
        mu = max(1.0 / max(2.0 * r_max2 - 1.0, 1e-12), 1e-6, mu_min)
    gw = np.ones(i.size)
    steps = 0
    while True:
        gw = np.ones(i.size) if not np.isfinite(mu) else tls_weights(r, 1.0, mu)
        gw[known] = 1.0
        laplacian: Factor | None = None  # one per stage: the stage's weights
        for k in range(gn_iterations):  # the residuals of ``rot`` are known at first
            rot, laplacian = gauss_newton_step(rot, i, j, R, w * gw, laplacian,
                                               residuals=e if k == 0 else None)
        e = edge_residuals(rot, i, j, R)
        r = np.linalg.norm(e, axis=-1) / c
        steps += 1
        binary = bool(np.all((gw == 0.0) | (gw == 1.0)))
        if not np.isfinite(mu) or steps >= max_steps or (binary and steps > 1):
            break
        mu *= mu_factor
    final = np.where(r <= 1.0, 1.0, 0.0)
    final[known] = 1.0
    return GncResult(rot, final, steps)
