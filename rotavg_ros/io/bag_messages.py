"""rosbags back-end of the output builder, and rosbags messages for bags (no rclpy needed).

:class:`MessageFactory` implements :class:`rotavg_ros.msg_adapters.outputs.MessageFactory`
over a rosbags typestore (ROS 2 Jazzy by default): the builders of
:mod:`rotavg_ros.msg_adapters.outputs` decide the field values, this module only makes the
messages, so a bag written by ``rotavg replay`` holds what ``rotavg_node`` would have
published, byte for byte. It also makes any other message (:meth:`MessageFactory.new`, for
the sample bags and tests) and serializes to CDR for :mod:`rotavg_ros.io.bag_writer`.

Conventions: ``R_i`` is world-to-node; the outputs carry node-to-world ``R_i^T``. Stamps are
integer nanoseconds.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from rotavg_ros.msg_adapters.outputs import MarkerSpec, Msg, Quat, Rgba, Vec3

TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"

_BASE_DTYPES = {
    "bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8,
    "uint8": np.uint8, "int16": np.int16, "uint16": np.uint16, "int32": np.int32,
    "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64, "float32": np.float32,
    "float64": np.float64,
}


class MessageFactory:
    """rosbags message instances (default-filled); the output builder's rosbags back-end."""

    def __init__(self, typestore: Typestore | None = None) -> None:
        self.typestore = typestore if typestore is not None else get_typestore(
            Stores.ROS2_JAZZY)

    # ------------------------------------------------------------------ generic
    def new(self, typename: str, **fields: Any) -> Any:
        """An instance of ``typename`` with every field defaulted, then ``fields`` set.

        Defaults are zeros and empty strings/sequences (the typestore knows no ``.msg``
        default values: a ``Quaternion`` defaults to ``w = 0`` here, ``w = 1`` in rclpy).
        """
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

    def serialize(self, msg: Any) -> bytes:
        """CDR bytes of ``msg`` (what the bag writer stores)."""
        return bytes(self.typestore.serialize_cdr(msg, msg.__msgtype__))

    def time(self, stamp_ns: int) -> Msg:
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        return self.new("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)

    def transform(self, parent: str, child: str, quat_xyzw: Iterable[float],
                  stamp_ns: int) -> Msg:
        """``TransformStamped`` ``parent -> child`` with rotation ``quat_xyzw`` (an edge)."""
        x, y, z, w = (float(v) for v in quat_xyzw)
        return self.transform_stamped(self.header(parent, stamp_ns), child, (x, y, z, w))

    # ------------------------------------------------------------------ back-end
    def header(self, frame_id: str, stamp_ns: int) -> Msg:
        return self.new("std_msgs/msg/Header", stamp=self.time(stamp_ns), frame_id=frame_id)

    def _quaternion(self, q: Quat) -> Msg:
        return self.new("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3])

    def _point(self, p: Vec3) -> Msg:
        return self.new("geometry_msgs/msg/Point", x=p[0], y=p[1], z=p[2])

    def _color(self, c: Rgba) -> Msg:
        return self.new("std_msgs/msg/ColorRGBA", r=c[0], g=c[1], b=c[2], a=c[3])

    def transform_stamped(self, header: Msg, child_frame_id: str, rotation: Quat) -> Msg:
        return self.new(
            TRANSFORM_STAMPED, header=header, child_frame_id=child_frame_id,
            transform=self.new("geometry_msgs/msg/Transform",
                               rotation=self._quaternion(rotation)),
        )

    def tf_message(self, transforms: Sequence[Msg]) -> Msg:
        return self.new(TF_MESSAGE, transforms=list(transforms))

    def marker(self, header: Msg, spec: MarkerSpec) -> Msg:
        return self.new(
            "visualization_msgs/msg/Marker", header=header, ns=spec.ns, id=spec.id,
            type=spec.type, action=spec.action,
            pose=self.new("geometry_msgs/msg/Pose", position=self._point(spec.position),
                          orientation=self._quaternion(spec.orientation)),
            scale=self.new("geometry_msgs/msg/Vector3", x=spec.scale[0], y=spec.scale[1],
                           z=spec.scale[2]),
            color=self._color(spec.color),
            points=[self._point(p) for p in spec.points],
            colors=[self._color(c) for c in spec.colors],
            text=spec.text,
        )

    def marker_array(self, markers: Sequence[Msg]) -> Msg:
        return self.new(MARKER_ARRAY, markers=list(markers))

    def diagnostic_status(self, level: int, name: str, message: str, hardware_id: str,
                          values: Sequence[tuple[str, str]]) -> Msg:
        return self.new(
            "diagnostic_msgs/msg/DiagnosticStatus", level=level, name=name, message=message,
            hardware_id=hardware_id,
            values=[self.new("diagnostic_msgs/msg/KeyValue", key=k, value=v)
                    for k, v in values],
        )

    def diagnostic_array(self, header: Msg, statuses: Sequence[Msg]) -> Msg:
        return self.new(DIAGNOSTIC_ARRAY, header=header, status=list(statuses))
