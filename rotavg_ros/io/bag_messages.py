"""The node's output messages built with a rosbags typestore (no rclpy needed).

Mirrors ``rotavg_ros.ros.messages`` (which builds rclpy messages) field for field, so that a bag
written by ``rotavg replay`` holds what ``rotavg_node`` would have published:

* ``geometry_msgs/msg/TransformStamped`` per node: ``header.frame_id = world_frame``,
  ``child_frame_id = <node id>``, rotation = node-to-world ``R_i^T``, zero translation;
* ``tf2_msgs/msg/TFMessage`` with all of them (for ``/tf``);
* ``visualization_msgs/msg/MarkerArray``: ``DELETEALL``, then an axes triad and a label per
  node (namespaces ``orientations``/``labels``, ``detached_*`` for components not connected
  to the anchor);
* ``diagnostic_msgs/msg/DiagnosticArray`` with one status.
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from rotavg_ros.core.types import FloatArray, IntArray
from rotavg_ros.msg_adapters.outputs import (
    Level,
    format_diagnostic_value,
    grid_layout,
    node_to_world_quaternions,
)

TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"

NS_AXES = "orientations"
NS_LABELS = "labels"
NS_DETACHED_AXES = "detached_orientations"
NS_DETACHED_LABELS = "detached_labels"

# visualization_msgs/msg/Marker constants
LINE_LIST = 5
TEXT_VIEW_FACING = 9
ADD = 0
DELETEALL = 3

_AXIS_RGB = ((1.0, 0.0, 0.0), (0.0, 0.8, 0.0), (0.0, 0.3, 1.0))

_BASE_DTYPES = {
    "bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8,
    "uint8": np.uint8, "int16": np.int16, "uint16": np.uint16, "int32": np.int32,
    "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64, "float32": np.float32,
    "float64": np.float64,
}


class MessageFactory:
    """Builds rosbags message instances (default-filled) and the node's outputs."""

    def __init__(self, typestore: Typestore | None = None) -> None:
        self.typestore = typestore if typestore is not None else get_typestore(
            Stores.ROS2_JAZZY)

    # ------------------------------------------------------------------ generic
    def new(self, typename: str, **fields: Any) -> Any:
        """An instance of ``typename`` with every field defaulted, then ``fields`` set."""
        _, defs = self.typestore.fielddefs[typename]
        values = {name: self._default(desc) for name, desc in defs if name not in fields}
        values.update(fields)
        return self.typestore.types[typename](**values)

    def _default(self, desc: Any) -> Any:
        kind, arg = desc
        if kind == Nodetype.BASE:
            base = arg[0]
            if base == "string":
                return ""
            if base == "bool":
                return False
            if base in ("float32", "float64"):
                return 0.0
            return 0
        if kind == Nodetype.NAME:
            return self.new(arg)
        sub, length = arg
        if kind == Nodetype.SEQUENCE:
            length = 0
        if sub[0] == Nodetype.BASE and sub[1][0] in _BASE_DTYPES:
            return np.zeros(length, dtype=_BASE_DTYPES[sub[1][0]])
        return [self._default(sub) for _ in range(length)]

    def time(self, stamp_ns: int) -> Any:
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        return self.new("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)

    def header(self, frame_id: str, stamp_ns: int) -> Any:
        return self.new("std_msgs/msg/Header", stamp=self.time(stamp_ns), frame_id=frame_id)

    def serialize(self, msg: Any) -> bytes:
        return bytes(self.typestore.serialize_cdr(msg, msg.__msgtype__))

    # ------------------------------------------------------------------ outputs
    def transform(self, parent: str, child: str, quat_xyzw: Iterable[float],
                  stamp_ns: int) -> Any:
        x, y, z, w = (float(v) for v in quat_xyzw)
        return self.new(
            TRANSFORM_STAMPED,
            header=self.header(parent, stamp_ns),
            child_frame_id=child,
            transform=self.new(
                "geometry_msgs/msg/Transform",
                rotation=self.new("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w),
            ),
        )

    def orientation_transforms(self, node_ids: Sequence[Hashable], rotations: FloatArray,
                               world_frame: str, stamp_ns: int) -> list[Any]:
        """One ``TransformStamped`` per node: ``world_frame -> id`` with rotation ``R_i^T``."""
        quats = node_to_world_quaternions(rotations)
        return [self.transform(world_frame, str(node_id), q, stamp_ns)
                for node_id, q in zip(node_ids, quats, strict=True)]

    def tf_message(self, transforms: Sequence[Any]) -> Any:
        return self.new(TF_MESSAGE, transforms=list(transforms))

    def _color(self, r: float, g: float, b: float, a: float = 1.0) -> Any:
        return self.new("std_msgs/msg/ColorRGBA", r=float(r), g=float(g), b=float(b),
                        a=float(a))

    def _marker(self, world_frame: str, stamp_ns: int, **fields: Any) -> Any:
        return self.new("visualization_msgs/msg/Marker",
                        header=self.header(world_frame, stamp_ns), **fields)

    def clear_markers(self, world_frame: str, stamp_ns: int) -> Any:
        """A ``MarkerArray`` holding only ``DELETEALL``."""
        return self.new(MARKER_ARRAY,
                        markers=[self._marker(world_frame, stamp_ns, action=DELETEALL)])

    def orientation_markers(
        self,
        node_ids: Sequence[Hashable],
        rotations: FloatArray,
        component: IntArray,
        anchors: Sequence[Hashable],
        world_frame: str,
        stamp_ns: int,
        spacing: float = 1.0,
        axis_length: float = 0.35,
    ) -> Any:
        """Same markers as ``rotavg_ros.ros.messages.orientation_markers``."""
        comp = np.asarray(component, dtype=np.int64).reshape(-1)
        quats = node_to_world_quaternions(rotations)
        pos = grid_layout(comp, spacing)
        anchor_set = {str(a) for a in anchors}
        markers = [self._marker(world_frame, stamp_ns, action=DELETEALL)]
        point = "geometry_msgs/msg/Point"
        origin = self.new(point, x=0.0, y=0.0, z=0.0)
        for k, node_id in enumerate(node_ids):
            detached = bool(comp[k] != 0)
            name = str(node_id)
            alpha = 0.5 if detached else 1.0
            shade = 0.6 if detached else 1.0
            points: list[Any] = []
            colors: list[Any] = []
            for axis, rgb in enumerate(_AXIS_RGB):
                tip = [0.0, 0.0, 0.0]
                tip[axis] = axis_length
                points += [origin, self.new(point, x=tip[0], y=tip[1], z=tip[2])]
                c = self._color(shade * rgb[0], shade * rgb[1], shade * rgb[2], alpha)
                colors += [c, c]
            qx, qy, qz, qw = (float(v) for v in quats[k])
            markers.append(self._marker(
                world_frame, stamp_ns,
                ns=NS_DETACHED_AXES if detached else NS_AXES, id=k, type=LINE_LIST,
                action=ADD,
                pose=self.new(
                    "geometry_msgs/msg/Pose",
                    position=self.new(point, x=float(pos[k, 0]), y=float(pos[k, 1]),
                                      z=float(pos[k, 2])),
                    orientation=self.new("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz,
                                         w=qw),
                ),
                scale=self.new("geometry_msgs/msg/Vector3", x=0.03, y=0.0, z=0.0),
                color=self._color(1.0, 1.0, 1.0, alpha),
                points=points, colors=colors,
            ))
            markers.append(self._marker(
                world_frame, stamp_ns,
                ns=NS_DETACHED_LABELS if detached else NS_LABELS, id=k,
                type=TEXT_VIEW_FACING, action=ADD,
                pose=self.new(
                    "geometry_msgs/msg/Pose",
                    position=self.new(point, x=float(pos[k, 0]), y=float(pos[k, 1]),
                                      z=float(pos[k, 2]) + axis_length + 0.15),
                    orientation=self.new("geometry_msgs/msg/Quaternion", x=0.0, y=0.0,
                                         z=0.0, w=1.0),
                ),
                scale=self.new("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.15),
                color=self._color(1.0, 0.55, 0.0) if detached else self._color(1.0, 1.0, 1.0),
                text=f"{name} (anchor)" if name in anchor_set else name,
            ))
        return self.new(MARKER_ARRAY, markers=markers)

    def diagnostic_array(self, name: str, level: Level | int, message: str,
                         values: Mapping[str, Any], hardware_id: str, stamp_ns: int) -> Any:
        """A ``DiagnosticArray`` with one status (values formatted like the node's)."""
        status = self.new(
            "diagnostic_msgs/msg/DiagnosticStatus",
            level=int(level), name=name, message=message, hardware_id=hardware_id,
            values=[self.new("diagnostic_msgs/msg/KeyValue", key=str(k),
                             value=format_diagnostic_value(v)) for k, v in values.items()],
        )
        return self.new(DIAGNOSTIC_ARRAY, header=self.header("", stamp_ns), status=[status])
