"""Gauge-aligned absolute-rotation errors (the evaluation protocol of the paper).

Conventions
-----------
* Rotations are world-to-node, ``(M, 3, 3)``. Relative rotations ``R_i R_j^T`` are invariant
  under ``R_i -> R_i Q``, so the gauge acts on the **right**: an estimate is compared with
  ``R_gt_i Q`` for the best ``Q``.
* ``Q`` minimises ``sum_i d(R_est_i, R_gt_i Q)`` with ``d`` the geodesic angle (L1): start
  from the chordal L2 solution ``Q0 = proj_SO3(sum_i R_gt_i^T R_est_i)`` and refine with
  Weiszfeld iterations for the geodesic median of the candidates ``C_i = R_gt_i^T R_est_i``.
* Angles are computed with ``atan2`` on the log map, accurate down to ~1e-15 rad.
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rotavg_ros.core.so3 import project_to_so3

FloatArray = NDArray[np.float64]

_NEAR_PI = 2.5  # above this angle the axis comes from the symmetric part of R


# ------------------------------------------------------------ local SO(3) helpers
def _vee_skew(R: FloatArray) -> FloatArray:
    """``vee(R - R^T)`` = ``2 sin(theta) * axis``."""
    return np.stack([R[..., 2, 1] - R[..., 1, 2],
                     R[..., 0, 2] - R[..., 2, 0],
                     R[..., 1, 0] - R[..., 0, 1]], axis=-1)


def _rotation_angle(R: FloatArray) -> FloatArray:
    """Angle of each rotation in ``[0, pi]`` via ``atan2`` (accurate near 0 and pi)."""
    s = np.linalg.norm(_vee_skew(R), axis=-1) / 2.0
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arctan2(s, c)


def _so3_log(R: FloatArray) -> FloatArray:
    """Rotation vectors ``(..., 3)`` with ``exp(hat(v)) = R``, ``|v| <= pi``."""
    R = np.asarray(R, dtype=np.float64)
    v = _vee_skew(R)
    theta = _rotation_angle(R)
    s = np.sin(theta)
    small = theta < 1e-6
    # theta / (2 sin theta), with its Taylor series near 0.
    scale = np.where(small, 0.5 + theta**2 / 12.0, theta / (2.0 * np.where(small, 1.0, s)))
    out = scale[..., None] * v
    near_pi = theta > _NEAR_PI
    if np.any(near_pi):
        Rp = R[near_pi]
        th = theta[near_pi]
        cos = np.cos(th)
        # (R + R^T)/2 = cos I + (1 - cos) a a^T
        S = (Rp + np.swapaxes(Rp, -1, -2)) / 2.0 - cos[:, None, None] * np.eye(3)
        S /= (1.0 - cos)[:, None, None]
        k = np.argmax(np.diagonal(S, axis1=-2, axis2=-1), axis=-1)
        axis = S[np.arange(k.size), :, k]
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        sign = np.where(np.einsum("ka,ka->k", axis, v[near_pi]) < 0, -1.0, 1.0)
        out[near_pi] = (sign * th)[:, None] * axis
    return out


def _so3_exp(v: FloatArray) -> FloatArray:
    """Rodrigues' formula for rotation vectors ``(..., 3)``."""
    v = np.asarray(v, dtype=np.float64)
    theta = np.linalg.norm(v, axis=-1)
    small = theta < 1e-6
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    K = np.zeros((*v.shape[:-1], 3, 3))
    K[..., 0, 1], K[..., 0, 2] = -v[..., 2], v[..., 1]
    K[..., 1, 0], K[..., 1, 2] = v[..., 2], -v[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -v[..., 1], v[..., 0]
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def _project(M: FloatArray) -> FloatArray:
    """:func:`project_to_so3` of one 3x3 matrix (it expects a stack)."""
    return project_to_so3(M[None])[0]


# --------------------------------------------------------------------- public API
def _as_stack(R: ArrayLike, name: str) -> FloatArray:
    A = np.asarray(R, dtype=np.float64)
    if A.ndim != 3 or A.shape[1:] != (3, 3):
        raise ValueError(f"{name} must have shape (M, 3, 3), got {A.shape}")
    return A


def align_gauge(
    R_est: ArrayLike, R_gt: ArrayLike, max_iters: int = 50, tol: float = 1e-12
) -> FloatArray:
    """Rotation ``Q`` minimising ``sum_i d(R_est_i, R_gt_i Q)`` (geodesic L1).

    Chordal L2 start ``proj_SO3(sum_i R_gt_i^T R_est_i)``, then Weiszfeld steps
    ``Q <- Q exp(sum_i w_i v_i / sum_i w_i)`` with ``v_i = log(Q^T C_i)`` and
    ``w_i = 1 / max(|v_i|, 1e-12)``, until the step is below ``tol`` or ``max_iters``.
    """
    est = _as_stack(R_est, "R_est")
    gt = _as_stack(R_gt, "R_gt")
    if est.shape != gt.shape or est.shape[0] == 0:
        raise ValueError(f"R_est {est.shape} and R_gt {gt.shape} must match and be non-empty")
    C = np.swapaxes(gt, -1, -2) @ est  # R_est_i ~= R_gt_i C_i
    Q = _project(C.sum(axis=0))
    for _ in range(max_iters):
        V = _so3_log(Q.T @ C)
        w = 1.0 / np.maximum(np.linalg.norm(V, axis=-1), 1e-12)
        step = (w[:, None] * V).sum(axis=0) / w.sum()
        Q = _project(Q @ _so3_exp(step))
        if float(np.linalg.norm(step)) < tol:
            break
    return Q


def angular_errors_deg(R_est: ArrayLike, R_gt: ArrayLike, R_align: ArrayLike) -> FloatArray:
    """Per-node ``d(R_est_i, R_gt_i R_align)`` in degrees."""
    est = _as_stack(R_est, "R_est")
    gt = _as_stack(R_gt, "R_gt")
    Q = np.asarray(R_align, dtype=np.float64)
    diff = est @ np.swapaxes(gt @ Q, -1, -2)
    return np.degrees(_rotation_angle(diff))


@dataclass
class ErrorStats:
    """Gauge-aligned absolute-rotation errors, in degrees, over the common nodes."""

    num_nodes: int
    mean_deg: float
    median_deg: float
    max_deg: float
    errors: FloatArray
    """Per-node errors in degrees, in the order of ``ids``."""
    ids: Sequence[Hashable] = field(default_factory=list)
    R_align: FloatArray = field(default_factory=lambda: np.eye(3))
    """The right gauge ``Q``: ``R_est_i ~= R_gt_i Q``."""


def evaluate(est: Mapping[Any, ArrayLike], gt: Mapping[Any, ArrayLike]) -> ErrorStats:
    """L1-align ``est`` to ``gt`` (node id -> world-to-node rotation) over their common ids
    and summarise the errors."""
    ids = [k for k in est if k in gt]
    if not ids:
        raise ValueError("no common node ids between the estimate and the ground truth")
    E = np.stack([np.asarray(est[k], dtype=np.float64) for k in ids])
    G = np.stack([np.asarray(gt[k], dtype=np.float64) for k in ids])
    Q = align_gauge(E, G)
    err = angular_errors_deg(E, G, Q)
    return ErrorStats(len(ids), float(err.mean()), float(np.median(err)), float(err.max()),
                      err, ids, Q)
