"""rclpy back-end of the output builder: what ``rotavg_node`` publishes.

:class:`RclpyMessageFactory` implements :class:`rotavg_ros.msg_adapters.outputs.MessageFactory`
with rclpy messages; the builders of :mod:`rotavg_ros.msg_adapters.outputs` decide every
field, so these messages serialize to the same CDR bytes as the rosbags ones that
``rotavg replay`` writes (:mod:`rotavg_ros.io.bag_messages`). The functions below are those
builders bound to this back-end, stamped with an rclpy ``builtin_interfaces/Time`` (what the
node's clock gives).

Conventions: the solver returns world-to-node rotations ``R_i``; the outputs carry the
node-to-world rotation ``R_i^T`` (``header.frame_id = world_frame``,
``child_frame_id = <node id>``), the orientation of the node's frame in the world frame, as
tf2 expects. Components not connected to the anchor are solved on their own (their anchor is
the identity): still published under ``world_frame`` (consumers must check the diagnostics),
drawn in the ``detached_*`` marker namespaces.

``tf2_msgs`` is imported only by :meth:`RclpyMessageFactory.tf_message` (the node publishes
no ``/tf``, and the pinned environment does not install it).
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping, Sequence
from typing import Any

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, Quaternion, Transform, TransformStamped, Vector3
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from rotavg_ros.core.types import FloatArray, IntArray
from rotavg_ros.msg_adapters import outputs
from rotavg_ros.msg_adapters.outputs import (
    NS_AXES,
    NS_DETACHED_AXES,
    NS_DETACHED_LABELS,
    NS_LABELS,
    Level,
    MarkerSpec,
    Quat,
    Rgba,
    Vec3,
    format_diagnostic_value,
    grid_layout,
    node_to_world_quaternions,
)

__all__ = [
    "FACTORY",
    "NS_AXES",
    "NS_DETACHED_AXES",
    "NS_DETACHED_LABELS",
    "NS_LABELS",
    "Level",
    "RclpyMessageFactory",
    "clear_markers",
    "diagnostic_array",
    "diagnostic_status",
    "diagnostic_values",
    "format_diagnostic_value",
    "grid_layout",
    "node_to_world_quaternions",
    "orientation_markers",
    "orientation_transforms",
    "stamp_ns",
]


def _quaternion(q: Quat) -> Quaternion:
    return Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])


def _point(p: Vec3) -> Point:
    return Point(x=p[0], y=p[1], z=p[2])


def _color(c: Rgba) -> ColorRGBA:
    return ColorRGBA(r=c[0], g=c[1], b=c[2], a=c[3])


class RclpyMessageFactory:
    """The output builder's rclpy back-end (stateless; use :data:`FACTORY`)."""

    def header(self, frame_id: str, stamp_ns: int) -> Header:
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        return Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id)

    def transform_stamped(self, header: Header, child_frame_id: str,
                          rotation: Quat) -> TransformStamped:
        return TransformStamped(header=header, child_frame_id=child_frame_id,
                                transform=Transform(rotation=_quaternion(rotation)))

    def tf_message(self, transforms: Sequence[TransformStamped]) -> Any:
        from tf2_msgs.msg import TFMessage  # not in the pinned environment; see the docstring

        return TFMessage(transforms=list(transforms))

    def marker(self, header: Header, spec: MarkerSpec) -> Marker:
        return Marker(
            header=header, ns=spec.ns, id=spec.id, type=spec.type, action=spec.action,
            pose=Pose(position=_point(spec.position),
                      orientation=_quaternion(spec.orientation)),
            scale=Vector3(x=spec.scale[0], y=spec.scale[1], z=spec.scale[2]),
            color=_color(spec.color),
            points=[_point(p) for p in spec.points],
            colors=[_color(c) for c in spec.colors],
            text=spec.text,
        )

    def marker_array(self, markers: Sequence[Marker]) -> MarkerArray:
        return MarkerArray(markers=list(markers))

    def diagnostic_status(self, level: int, name: str, message: str, hardware_id: str,
                          values: Sequence[tuple[str, str]]) -> DiagnosticStatus:
        return DiagnosticStatus(
            level=bytes([level]), name=name, message=message, hardware_id=hardware_id,
            values=[KeyValue(key=k, value=v) for k, v in values],
        )

    def diagnostic_array(self, header: Header,
                         statuses: Sequence[DiagnosticStatus]) -> DiagnosticArray:
        return DiagnosticArray(header=header, status=list(statuses))


FACTORY = RclpyMessageFactory()


def stamp_ns(stamp: Time) -> int:
    """Nanoseconds of an rclpy ``Time`` message (the builders' stamp)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


# ---------------------------------------------------------------------- bound builders
def orientation_transforms(node_ids: Sequence[Hashable], rotations: FloatArray,
                           world_frame: str, stamp: Time) -> list[TransformStamped]:
    """:func:`rotavg_ros.msg_adapters.outputs.orientation_transforms` as rclpy messages."""
    return outputs.orientation_transforms(FACTORY, node_ids, rotations, world_frame,
                                          stamp_ns(stamp))


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
    """:func:`rotavg_ros.msg_adapters.outputs.orientation_markers` as rclpy messages."""
    return outputs.orientation_markers(FACTORY, node_ids, rotations, component, anchors,
                                       world_frame, stamp_ns(stamp), spacing, axis_length)


def clear_markers(world_frame: str, stamp: Time) -> MarkerArray:
    """:func:`rotavg_ros.msg_adapters.outputs.clear_markers` as rclpy messages."""
    return outputs.clear_markers(FACTORY, world_frame, stamp_ns(stamp))


def diagnostic_status(name: str, level: Level | int, message: str, values: Mapping[str, Any],
                      hardware_id: str = "") -> DiagnosticStatus:
    """:func:`rotavg_ros.msg_adapters.outputs.diagnostic_status` as an rclpy message."""
    return outputs.diagnostic_status(FACTORY, name, level, message, values, hardware_id)


def diagnostic_array(statuses: Sequence[DiagnosticStatus], stamp: Time) -> DiagnosticArray:
    """:func:`rotavg_ros.msg_adapters.outputs.diagnostic_array` as an rclpy message."""
    return outputs.diagnostic_array(FACTORY, statuses, stamp_ns(stamp))


def diagnostic_values(array: DiagnosticArray, name: str | None = None) -> dict[str, str]:
    """Key/value dict of the first status (or the one called ``name``); handy in tests/tools."""
    for status in array.status:
        if name is None or status.name == name:
            return {kv.key: kv.value for kv in status.values}
    return {}
