"""Messages in, :class:`EdgeMeasurement` or :class:`Rejection` out (duck-typed, no ROS import).

Works on rclpy messages and on ``rosbags`` deserialised messages alike: only the attribute
names shared by both are used (``header.frame_id``, ``header.stamp.sec/nanosec``,
``child_frame_id``, ``transform.rotation.x..w``, ``pose.pose.orientation.x..w``,
``pose.covariance``).

Frame semantics
---------------
``R_i`` is the **world-to-node** rotation of node ``i``. A ``geometry_msgs/msg/TransformStamped``
with ``header.frame_id = i`` and ``child_frame_id = j`` whose ``transform.rotation`` is the
rotation of frame ``j`` expressed in frame ``i`` (the TF convention) is exactly the edge
``R_ij ~= R_i R_j^T``. ``nav_msgs/msg/Odometry`` is read the same way with
``pose.pose.orientation`` as ``R_ij``. Translations (and the twist) are ignored.

Validation, in this order (first failure wins; each reason is a stable diagnostics key)
----------------------------------------------------------------------------------------
``empty_frame_id``
    ``header.frame_id`` or ``child_frame_id`` is ``""``.
``invalid_frame_id``
    Longer than :attr:`AdapterConfig.max_frame_id_length` (256) characters, contains a space
    or any character that ``str.isprintable()`` refuses (control characters, tabs, newlines,
    Unicode separators), or starts with ``/`` (tf2 refuses such frame ids, and the outputs are
    published as TF frames).
``reserved_frame_id``
    Equals one of :attr:`AdapterConfig.reserved_frames` (the node passes its ``world_frame``:
    a node named like the output frame would publish ``world -> world``).
``self_loop``
    ``header.frame_id == child_frame_id``.
``non_finite_quaternion``
    A NaN or infinite component.
``zero_quaternion``
    Norm below ``1e-9``.
``non_unit_quaternion``
    ``abs(|q| - 1) > quaternion_tolerance`` (default ``1e-3``). Within the tolerance the
    quaternion is normalised and accepted: float32 round trips and hand-written
    quaternions with 4-6 significant digits pass, a non-normalised or corrupted one does not.

Odometry covariance to weight
-----------------------------
The rotation block is rows/cols 3..5 of the row-major 6x6 ``pose.covariance`` (rad^2).
``weight = 3 * reference_variance / trace(block)``: the mean information ``3 / trace``
normalised so that a per-axis variance of ``reference_variance`` (default ``(1 deg)^2 =
3.046e-4 rad^2``) gives weight 1. The weight is clamped to ``[min_weight, max_weight]``
(default ``[1e-3, 1e3]``, i.e. a per-axis standard deviation from about 0.03 deg to 31.6 deg
at the default reference) so that a single over-confident message cannot dominate the solve;
clamping adds the note ``clamped_weight``. A covariance that cannot be used (wrong size, any
non-finite entry in the block, any non-positive diagonal entry of the block, e.g. the
all-zero "unknown" covariance) gives ``default_weight`` (1.0) and the note
``default_weight_covariance``; it is not a rejection. ``TransformStamped`` has no covariance
and always gets ``default_weight``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rotavg_ros.core.measurement import EdgeMeasurement, Rejection
from rotavg_ros.core.so3 import quat_to_matrix

__all__ = [
    "ADAPTER_REASONS",
    "AdapterConfig",
    "DEFAULT_REFERENCE_VARIANCE",
    "EdgeMeasurement",
    "NOTE_KEYS",
    "Rejection",
    "edge_from_message",
    "edge_from_odometry",
    "edge_from_transform",
    "rotation_weight_from_covariance",
    "stamp_to_ns",
]

EMPTY_FRAME_ID = "empty_frame_id"
INVALID_FRAME_ID = "invalid_frame_id"
RESERVED_FRAME_ID = "reserved_frame_id"
SELF_LOOP = "self_loop"
NON_FINITE_QUATERNION = "non_finite_quaternion"
ZERO_QUATERNION = "zero_quaternion"
NON_UNIT_QUATERNION = "non_unit_quaternion"
UNSUPPORTED_MESSAGE = "unsupported_message"

ADAPTER_REASONS: tuple[str, ...] = (
    EMPTY_FRAME_ID,
    INVALID_FRAME_ID,
    RESERVED_FRAME_ID,
    SELF_LOOP,
    NON_FINITE_QUATERNION,
    ZERO_QUATERNION,
    NON_UNIT_QUATERNION,
)
"""Every reason the adapters produce for a message of a supported type."""

DEFAULT_WEIGHT_COVARIANCE = "default_weight_covariance"
CLAMPED_WEIGHT = "clamped_weight"
NOTE_KEYS: tuple[str, ...] = (DEFAULT_WEIGHT_COVARIANCE, CLAMPED_WEIGHT)

DEFAULT_REFERENCE_VARIANCE = math.radians(1.0) ** 2
"""(1 deg)^2 in rad^2: the per-axis rotation variance that maps to weight 1."""

ZERO_QUATERNION_NORM = 1e-9


@dataclass(frozen=True)
class AdapterConfig:
    """Tunables of the input adapters (see the module docstring for their meaning)."""

    quaternion_tolerance: float = 1e-3
    reference_variance: float = DEFAULT_REFERENCE_VARIANCE
    default_weight: float = 1.0
    min_weight: float = 1e-3
    max_weight: float = 1e3
    max_frame_id_length: int = 256
    reserved_frames: frozenset[str] = field(default_factory=frozenset)


DEFAULT_CONFIG = AdapterConfig()


def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` (``sec``, ``nanosec``) to integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _check_frame(frame: Any, config: AdapterConfig) -> str | None:
    if not isinstance(frame, str):
        return INVALID_FRAME_ID
    if frame == "":
        return EMPTY_FRAME_ID
    if (
        len(frame) > config.max_frame_id_length
        or not frame.isprintable()
        or " " in frame
        or frame.startswith("/")
    ):
        return INVALID_FRAME_ID
    if frame in config.reserved_frames:
        return RESERVED_FRAME_ID
    return None


def _edge(
    frame_i: Any,
    frame_j: Any,
    quat: Any,
    stamp: Any,
    weight: float,
    notes: tuple[str, ...],
    config: AdapterConfig,
) -> EdgeMeasurement | Rejection:
    for frame in (frame_i, frame_j):
        reason = _check_frame(frame, config)
        if reason is not None:
            return Rejection(reason, repr(frame)[:80])
    if frame_i == frame_j:
        return Rejection(SELF_LOOP, frame_i[:80])
    try:
        q = np.array([quat.x, quat.y, quat.z, quat.w], dtype=np.float64)
    except (TypeError, ValueError):
        return Rejection(NON_FINITE_QUATERNION, "quaternion is not numeric")
    if not np.all(np.isfinite(q)):
        return Rejection(NON_FINITE_QUATERNION, str(q.tolist()))
    norm = float(np.linalg.norm(q))
    if norm < ZERO_QUATERNION_NORM:
        return Rejection(ZERO_QUATERNION, str(q.tolist()))
    if abs(norm - 1.0) > config.quaternion_tolerance:
        return Rejection(NON_UNIT_QUATERNION, f"|q| = {norm:.6g}")
    return EdgeMeasurement(
        frame_i=frame_i,
        frame_j=frame_j,
        R=quat_to_matrix(q / norm),
        weight=weight,
        stamp_ns=stamp_to_ns(stamp),
        notes=notes,
    )


def edge_from_transform(
    msg: Any, config: AdapterConfig = DEFAULT_CONFIG
) -> EdgeMeasurement | Rejection:
    """``geometry_msgs/msg/TransformStamped`` (rclpy or rosbags) to an edge ``R_ij``.

    ``i = header.frame_id``, ``j = child_frame_id``, ``R_ij = transform.rotation``; weight is
    ``config.default_weight``.
    """
    return _edge(
        msg.header.frame_id,
        msg.child_frame_id,
        msg.transform.rotation,
        msg.header.stamp,
        config.default_weight,
        (),
        config,
    )


def rotation_weight_from_covariance(
    covariance: Sequence[float] | np.ndarray, config: AdapterConfig = DEFAULT_CONFIG
) -> tuple[float, tuple[str, ...]]:
    """Weight of a 6x6 row-major pose covariance's rotation block, plus notes.

    ``weight = 3 * reference_variance / trace(cov[3:6, 3:6])``, clamped to
    ``[min_weight, max_weight]``; an unusable covariance gives ``default_weight`` and the note
    ``default_weight_covariance``.
    """
    try:
        cov = np.asarray(covariance, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return config.default_weight, (DEFAULT_WEIGHT_COVARIANCE,)
    if cov.size != 36:
        return config.default_weight, (DEFAULT_WEIGHT_COVARIANCE,)
    block = cov.reshape(6, 6)[3:6, 3:6]
    diag = np.diag(block)
    if not np.all(np.isfinite(block)) or not np.all(diag > 0.0):
        return config.default_weight, (DEFAULT_WEIGHT_COVARIANCE,)
    weight = 3.0 * config.reference_variance / float(diag.sum())
    if not math.isfinite(weight) or weight <= 0.0:
        return config.default_weight, (DEFAULT_WEIGHT_COVARIANCE,)
    clamped = min(max(weight, config.min_weight), config.max_weight)
    if clamped != weight:
        return clamped, (CLAMPED_WEIGHT,)
    return weight, ()


def edge_from_odometry(
    msg: Any, config: AdapterConfig = DEFAULT_CONFIG
) -> EdgeMeasurement | Rejection:
    """``nav_msgs/msg/Odometry`` (rclpy or rosbags) to an edge ``R_ij`` with a weight.

    ``i = header.frame_id``, ``j = child_frame_id``, ``R_ij = pose.pose.orientation``; the
    weight comes from the rotation block of ``pose.covariance``
    (:func:`rotation_weight_from_covariance`). Notes are only attached to accepted edges, so
    a rejected message never counts as ``default_weight_covariance``.
    """
    weight, notes = rotation_weight_from_covariance(msg.pose.covariance, config)
    return _edge(
        msg.header.frame_id,
        msg.child_frame_id,
        msg.pose.pose.orientation,
        msg.header.stamp,
        weight,
        notes,
        config,
    )


def edge_from_message(
    msg: Any, config: AdapterConfig = DEFAULT_CONFIG
) -> EdgeMeasurement | Rejection:
    """Dispatch on the message shape: ``TransformStamped``-like or ``Odometry``-like.

    Anything else is ``Rejection("unsupported_message")``.
    """
    if hasattr(msg, "transform") and hasattr(msg, "child_frame_id"):
        return edge_from_transform(msg, config)
    pose = getattr(msg, "pose", None)
    if hasattr(msg, "child_frame_id") and hasattr(pose, "covariance"):
        return edge_from_odometry(msg, config)
    return Rejection(UNSUPPORTED_MESSAGE, type(msg).__name__)
