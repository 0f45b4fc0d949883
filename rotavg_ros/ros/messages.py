"""Solve results out: TF-ready transforms, RViz markers and diagnostics (rclpy messages).

Conventions
-----------
The solver returns **world-to-node** rotations ``R_i`` (``x_node = R_i x_world``). The node
publishes the **node-to-world** rotation ``R_i^T`` as a ``geometry_msgs/msg/TransformStamped``
with ``header.frame_id = world_frame`` and ``child_frame_id = <node id>``, i.e. the orientation
of the node's frame expressed in the world frame, which is what tf2 expects. Translations are
zero (the graph has none).

Components not connected to the anchor are solved on their own and have their own anchor set
to identity; their rotations are *not* comparable with the anchor component's. They are still
published under ``world_frame`` (tf2 consumers must check the diagnostics); in the markers they
are drawn in the ``detached_*`` namespaces with muted colours, laid out to the right of the
anchor component.

Only this package (``msg_adapters``) imports ROS message modules; ``rotavg_ros``' solver
modules stay ROS-free. The message-independent helpers (:func:`grid_layout`,
:func:`node_to_world_quaternions`, :func:`format_diagnostic_value`, :class:`Level`) live in
:mod:`rotavg_ros.pipeline`, shared with the rosbags builders of :mod:`rotavg_ros.io.bag_messages`,
and are re-exported here.
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping, Sequence
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, TransformStamped
from numpy.typing import NDArray
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from rotavg_ros.msg_adapters.outputs import (
    Level,
    format_diagnostic_value,
    grid_layout,
    node_to_world_quaternions,
)

__all__ = [
    "NS_AXES",
    "NS_DETACHED_AXES",
    "NS_DETACHED_LABELS",
    "NS_LABELS",
    "Level",
    "clear_markers",
    "diagnostic_array",
    "diagnostic_status",
    "diagnostic_values",
    "format_diagnostic_value",
    "grid_layout",
    "node_to_world_quaternions",
    "orientation_markers",
    "orientation_transforms",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

NS_AXES = "orientations"
NS_LABELS = "labels"
NS_DETACHED_AXES = "detached_orientations"
NS_DETACHED_LABELS = "detached_labels"


def orientation_transforms(
    node_ids: Sequence[Hashable],
    rotations: FloatArray,
    world_frame: str,
    stamp: Time,
) -> list[TransformStamped]:
    """One ``TransformStamped`` per node: ``world_frame -> node id`` with rotation ``R_i^T``."""
    quats = node_to_world_quaternions(rotations)
    out: list[TransformStamped] = []
    for node_id, q in zip(node_ids, quats, strict=True):
        msg = TransformStamped()
        msg.header.stamp = stamp
        msg.header.frame_id = world_frame
        msg.child_frame_id = str(node_id)
        rot = msg.transform.rotation
        rot.x, rot.y, rot.z, rot.w = (float(v) for v in q)
        out.append(msg)
    return out


def _color(r: float, g: float, b: float, a: float = 1.0) -> ColorRGBA:
    return ColorRGBA(r=float(r), g=float(g), b=float(b), a=float(a))


_AXIS_RGB = ((1.0, 0.0, 0.0), (0.0, 0.8, 0.0), (0.0, 0.3, 1.0))


def orientation_markers(
    node_ids: Sequence[Hashable],
    rotations: FloatArray,
    component: IntArray,
    anchors: Sequence[Hashable],
    world_frame: str,
    stamp: Time,
    spacing: float = 1.0,
    axis_length: float = 0.35,
) -> MarkerArray:
    """RViz markers: a ``DELETEALL`` first, then per node an axes triad and a text label.

    * The triad is a ``LINE_LIST`` marker whose pose has the node-to-world orientation
      ``R_i^T``, with its x/y/z axes red/green/blue; it sits at :func:`grid_layout`'s position
      (there are no translations to show).
    * The label is a ``TEXT_VIEW_FACING`` marker with the node id, above the triad; the anchor
      of each component is labelled ``"<id> (anchor)"``.
    * Anchor component: namespaces ``orientations`` / ``labels``, white labels, opaque axes.
      Other components: ``detached_orientations`` / ``detached_labels``, orange labels,
      half-transparent muted axes.

    Marker ids are the dense node indices, unique inside each namespace.
    """
    comp = np.asarray(component, dtype=np.int64).reshape(-1)
    quats = node_to_world_quaternions(rotations)
    pos = grid_layout(comp, spacing)
    anchor_set = {str(a) for a in anchors}
    array = MarkerArray()
    clear = Marker()
    clear.header.stamp = stamp
    clear.header.frame_id = world_frame
    clear.action = Marker.DELETEALL
    array.markers.append(clear)
    for k, node_id in enumerate(node_ids):
        detached = bool(comp[k] != 0)
        name = str(node_id)
        axes = Marker()
        axes.header.stamp = stamp
        axes.header.frame_id = world_frame
        axes.ns = NS_DETACHED_AXES if detached else NS_AXES
        axes.id = k
        axes.type = Marker.LINE_LIST
        axes.action = Marker.ADD
        axes.pose.position.x, axes.pose.position.y, axes.pose.position.z = (
            float(v) for v in pos[k]
        )
        o = axes.pose.orientation
        o.x, o.y, o.z, o.w = (float(v) for v in quats[k])
        axes.scale.x = 0.03  # line width
        alpha = 0.5 if detached else 1.0
        shade = 0.6 if detached else 1.0
        for axis, rgb in enumerate(_AXIS_RGB):
            tip = [0.0, 0.0, 0.0]
            tip[axis] = axis_length
            axes.points.append(Point(x=0.0, y=0.0, z=0.0))
            axes.points.append(Point(x=tip[0], y=tip[1], z=tip[2]))
            c = _color(shade * rgb[0], shade * rgb[1], shade * rgb[2], alpha)
            axes.colors.extend([c, c])
        axes.color = _color(1.0, 1.0, 1.0, alpha)
        array.markers.append(axes)

        label = Marker()
        label.header.stamp = stamp
        label.header.frame_id = world_frame
        label.ns = NS_DETACHED_LABELS if detached else NS_LABELS
        label.id = k
        label.type = Marker.TEXT_VIEW_FACING
        label.action = Marker.ADD
        label.pose.position.x = float(pos[k, 0])
        label.pose.position.y = float(pos[k, 1])
        label.pose.position.z = float(pos[k, 2]) + axis_length + 0.15
        label.pose.orientation.w = 1.0
        label.scale.z = 0.15  # text height
        label.color = _color(1.0, 0.55, 0.0) if detached else _color(1.0, 1.0, 1.0)
        label.text = f"{name} (anchor)" if name in anchor_set else name
        array.markers.append(label)
    return array


def clear_markers(world_frame: str, stamp: Time) -> MarkerArray:
    """A ``MarkerArray`` holding only ``DELETEALL`` (after a reset)."""
    clear = Marker()
    clear.header.stamp = stamp
    clear.header.frame_id = world_frame
    clear.action = Marker.DELETEALL
    return MarkerArray(markers=[clear])


def diagnostic_status(
    name: str,
    level: Level | int,
    message: str,
    values: Mapping[str, Any],
    hardware_id: str = "",
) -> DiagnosticStatus:
    """One ``DiagnosticStatus``; every entry of ``values`` becomes a ``KeyValue`` (in order).

    Floats are formatted with 6 significant digits, booleans as ``true``/``false``, lists as
    comma-separated values.
    """
    status = DiagnosticStatus()
    status.level = bytes([int(level)])
    status.name = name
    status.message = message
    status.hardware_id = hardware_id
    status.values = [
        KeyValue(key=str(k), value=format_diagnostic_value(v)) for k, v in values.items()
    ]
    return status


def diagnostic_array(statuses: Sequence[DiagnosticStatus], stamp: Time) -> DiagnosticArray:
    """Wrap statuses into a stamped ``DiagnosticArray``."""
    array = DiagnosticArray()
    array.header.stamp = stamp
    array.status = list(statuses)
    return array


def diagnostic_values(array: DiagnosticArray, name: str | None = None) -> dict[str, str]:
    """Key/value dict of the first status (or the one called ``name``); handy in tests/tools."""
    for status in array.status:
        if name is None or status.name == name:
            return {kv.key: kv.value for kv in status.values}
    return {}
