"""One relative-rotation measurement as it enters the view graph, or why a message was not one.

Convention: ``R_i`` is world-to-node (``x_node = R_i x_world``); a measurement
``(frame_i, frame_j, R)`` carries ``R ~= R_i R_j^T``, the orientation of frame ``j`` in frame
``i`` (the TF rotation of a transform with ``header.frame_id = i``, ``child_frame_id = j``).
"""

from __future__ import annotations

from dataclasses import dataclass

from rotavg_ros.core.types import FloatArray


@dataclass(frozen=True)
class EdgeMeasurement:
    """One validated relative rotation ``R ~= R_i R_j^T`` (world-to-node ``R_i``).

    ``R`` is a proper 3x3 rotation (the adapter normalises the quaternion). ``weight`` is a
    positive confidence (1.0 = reference accuracy). ``stamp_ns`` is the message stamp in
    nanoseconds (0 when unknown). ``notes`` are remarks that are counted but do not reject the
    measurement, e.g. ``("default_weight_covariance",)``.
    """

    frame_i: str
    frame_j: str
    R: FloatArray
    weight: float = 1.0
    stamp_ns: int = 0
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class Rejection:
    """A message that was not turned into an edge; ``reason`` is a stable snake_case key."""

    reason: str
    detail: str = ""
