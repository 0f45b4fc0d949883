"""Gauge-aligned absolute-rotation errors (the evaluation protocol of the paper).

Conventions
-----------
* Rotations are world-to-node, ``(M, 3, 3)``. Relative rotations ``R_i R_j^T`` are invariant
  under ``R_i -> R_i Q``, so the gauge acts on the **right**: an estimate is compared with
  ``R_gt_i Q`` for the best ``Q``.
* ``Q`` minimises ``sum_i d(R_est_i, R_gt_i Q)`` with ``d`` the geodesic angle (L1): start
  from the chordal L2 solution ``Q0 = proj_SO3(sum_i R_gt_i^T R_est_i)`` and refine with
  Weiszfeld iterations for the geodesic median of the candidates ``C_i = R_gt_i^T R_est_i``.
* Angles are computed with ``atan2`` (:func:`~rotavg_ros.core.so3.rotation_angle`), accurate
  down to ~1e-15 rad.
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from rotavg_ros.core.so3 import exp_map, log_map, project_to_so3, rotation_angle
from rotavg_ros.core.types import FloatArray


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
        V = log_map(Q.T @ C)
        w = 1.0 / np.maximum(np.linalg.norm(V, axis=-1), 1e-12)
        step = (w[:, None] * V).sum(axis=0) / w.sum()
        Q = _project(Q @ exp_map(step))
        if float(np.linalg.norm(step)) < tol:
            break
    return Q


def angular_errors_deg(R_est: ArrayLike, R_gt: ArrayLike, R_align: ArrayLike) -> FloatArray:
    """Per-node ``d(R_est_i, R_gt_i R_align)`` in degrees."""
    est = _as_stack(R_est, "R_est")
    gt = _as_stack(R_gt, "R_gt")
    Q = np.asarray(R_align, dtype=np.float64)
    diff = est @ np.swapaxes(gt @ Q, -1, -2)
    return np.degrees(rotation_angle(diff))


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
