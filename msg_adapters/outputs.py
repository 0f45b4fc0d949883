"""Solve results out: the node's output messages, built once over a message factory.

Conventions: the solver returns world-to-node rotations ``R_i`` (``x_node = R_i x_world``);
outputs carry the node-to-world rotation ``R_i^T``, the orientation of node ``i``'s frame in
the world frame, as tf2 expects (``header.frame_id = world_frame``, ``child_frame_id = i``,
zero translation: the graph has none).

The builders here decide every field value once; a :class:`MessageFactory` back-end only
turns plain values into messages of its library:

* ``rotavg_ros.ros.messages``: rclpy messages (what ``rotavg_node`` publishes);
* ``rotavg_ros.io.bag_messages``: rosbags messages (what ``rotavg replay`` writes to a bag).

Both therefore serialize to the same CDR bytes. The outputs:

* :func:`orientation_transforms`: one ``geometry_msgs/TransformStamped`` per node;
* :func:`tf_message`: ``tf2_msgs/TFMessage`` with all of them (``/tf``);
* :func:`orientation_markers` / :func:`clear_markers`: ``visualization_msgs/MarkerArray``,
  ``DELETEALL`` then an axes triad and a label per node; components not connected to the
  anchor (solved on their own, not comparable with it) go to the ``detached_*`` namespaces
  in muted colours;
* :func:`diagnostic_status` / :func:`diagnostic_array`: ``diagnostic_msgs/DiagnosticArray``.

Stamps are integer nanoseconds. ROS-free: imports only ``rotavg_ros.core`` and numpy.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, Protocol

import numpy as np

from rotavg_ros.core.so3 import matrix_to_quat
from rotavg_ros.core.types import FloatArray, IntArray

Msg = Any
"""A message instance of the factory's library (rclpy or rosbags)."""
Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]
"""Quaternion ``(x, y, z, w)``."""
Rgba = tuple[float, float, float, float]

NS_AXES = "orientations"
NS_LABELS = "labels"
NS_DETACHED_AXES = "detached_orientations"
NS_DETACHED_LABELS = "detached_labels"

# visualization_msgs/msg/Marker constants
LINE_LIST = 5
TEXT_VIEW_FACING = 9
ADD = 0
DELETEALL = 3

_IDENTITY: Quat = (0.0, 0.0, 0.0, 1.0)
_ORIGIN: Vec3 = (0.0, 0.0, 0.0)
_AXIS_RGB: tuple[Vec3, ...] = ((1.0, 0.0, 0.0), (0.0, 0.8, 0.0), (0.0, 0.3, 1.0))
_WHITE: Rgba = (1.0, 1.0, 1.0, 1.0)
_ORANGE: Rgba = (1.0, 0.55, 0.0, 1.0)
AXES_LINE_WIDTH = 0.03
LABEL_HEIGHT = 0.15


class Level(IntEnum):
    """``diagnostic_msgs/DiagnosticStatus`` levels as ints (the message field is a byte)."""

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3


@dataclass(frozen=True)
class MarkerSpec:
    """Field values of one ``visualization_msgs/Marker`` (besides its header).

    Fields left out keep the message's zero default, except the pose's orientation, which is
    the identity (as in ``geometry_msgs/Quaternion``'s default).
    """

    action: int
    ns: str = ""
    id: int = 0
    type: int = 0
    position: Vec3 = _ORIGIN
    orientation: Quat = _IDENTITY
    scale: Vec3 = _ORIGIN
    color: Rgba = (0.0, 0.0, 0.0, 0.0)
    points: tuple[Vec3, ...] = ()
    colors: tuple[Rgba, ...] = ()
    text: str = ""


class MessageFactory(Protocol):
    """Makes the output messages of one message library from plain values.

    Fields not named keep their defaults. A back-end makes no decision of its own: every
    value comes from the builders of this module.
    """

    def header(self, frame_id: str, stamp_ns: int) -> Msg:
        """``std_msgs/Header`` stamped ``stamp_ns`` (split into ``sec``, ``nanosec``)."""
        ...

    def transform_stamped(self, header: Msg, child_frame_id: str, rotation: Quat) -> Msg:
        """``geometry_msgs/TransformStamped`` with ``rotation`` and zero translation."""
        ...

    def tf_message(self, transforms: Sequence[Msg]) -> Msg:
        """``tf2_msgs/TFMessage``."""
        ...

    def marker(self, header: Msg, spec: MarkerSpec) -> Msg:
        """``visualization_msgs/Marker``."""
        ...

    def marker_array(self, markers: Sequence[Msg]) -> Msg:
        """``visualization_msgs/MarkerArray``."""
        ...

    def diagnostic_status(self, level: int, name: str, message: str, hardware_id: str,
                          values: Sequence[tuple[str, str]]) -> Msg:
        """``diagnostic_msgs/DiagnosticStatus`` with one ``KeyValue`` per ``values`` pair."""
        ...

    def diagnostic_array(self, header: Msg, statuses: Sequence[Msg]) -> Msg:
        """``diagnostic_msgs/DiagnosticArray``."""
        ...


# ---------------------------------------------------------------------- helpers
def node_to_world_quaternions(rotations: FloatArray) -> FloatArray:
    """``(N, 4)`` quaternions (x, y, z, w) of ``R_i^T`` for world-to-node ``rotations``."""
    R = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    return matrix_to_quat(np.swapaxes(R, 1, 2))


def grid_layout(component: IntArray, spacing: float = 1.0) -> FloatArray:
    """``(N, 3)`` marker positions: each component on its own square grid in the z=0 plane.

    Component 0 (the anchor's) starts at the origin; the next components follow along +x with
    a gap of two ``spacing``. Inside a component, nodes keep their index order row by row.
    """
    comp = np.asarray(component, dtype=np.int64).reshape(-1)
    pos = np.zeros((comp.size, 3))
    x0 = 0.0
    for label in np.unique(comp):
        idx = np.flatnonzero(comp == label)
        cols = max(1, math.ceil(math.sqrt(idx.size)))
        k = np.arange(idx.size)
        pos[idx, 0] = x0 + (k % cols) * spacing
        pos[idx, 1] = -(k // cols) * spacing
        x0 += (cols + 1) * spacing
    return pos


def format_diagnostic_value(value: Any) -> str:
    """Floats with 6 significant digits, booleans ``true``/``false``, lists comma-separated."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(format_diagnostic_value(v) for v in value)
    return str(value)


def _quat(q: FloatArray) -> Quat:
    x, y, z, w = (float(v) for v in q)
    return (x, y, z, w)


# ---------------------------------------------------------------------- builders
def orientation_transforms(
    f: MessageFactory,
    node_ids: Sequence[Hashable],
    rotations: FloatArray,
    world_frame: str,
    stamp_ns: int,
) -> list[Msg]:
    """One ``TransformStamped`` per node: ``world_frame -> node id`` with rotation ``R_i^T``."""
    quats = node_to_world_quaternions(rotations)
    return [f.transform_stamped(f.header(world_frame, stamp_ns), str(node_id), _quat(q))
            for node_id, q in zip(node_ids, quats, strict=True)]


def tf_message(f: MessageFactory, transforms: Sequence[Msg]) -> Msg:
    """``TFMessage`` holding ``transforms`` (for ``/tf``)."""
    return f.tf_message(list(transforms))


def orientation_markers(
    f: MessageFactory,
    node_ids: Sequence[Hashable],
    rotations: FloatArray,
    component: IntArray,
    anchors: Sequence[Hashable],
    world_frame: str,
    stamp_ns: int,
    spacing: float = 1.0,
    axis_length: float = 0.35,
) -> Msg:
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
    markers = [f.marker(f.header(world_frame, stamp_ns), MarkerSpec(action=DELETEALL))]
    points: list[Vec3] = []
    for axis in range(3):
        tip = [0.0, 0.0, 0.0]
        tip[axis] = axis_length
        points += [_ORIGIN, (tip[0], tip[1], tip[2])]
    axes_points = tuple(points)
    for k, node_id in enumerate(node_ids):
        detached = bool(comp[k] != 0)
        name = str(node_id)
        alpha = 0.5 if detached else 1.0
        shade = 0.6 if detached else 1.0
        colors: list[Rgba] = []
        for r, g, b in _AXIS_RGB:
            c = (shade * r, shade * g, shade * b, alpha)
            colors += [c, c]
        x, y, z = (float(v) for v in pos[k])
        markers.append(f.marker(f.header(world_frame, stamp_ns), MarkerSpec(
            action=ADD, ns=NS_DETACHED_AXES if detached else NS_AXES, id=k, type=LINE_LIST,
            position=(x, y, z), orientation=_quat(quats[k]),
            scale=(AXES_LINE_WIDTH, 0.0, 0.0), color=(1.0, 1.0, 1.0, alpha),
            points=axes_points, colors=tuple(colors),
        )))
        markers.append(f.marker(f.header(world_frame, stamp_ns), MarkerSpec(
            action=ADD, ns=NS_DETACHED_LABELS if detached else NS_LABELS, id=k,
            type=TEXT_VIEW_FACING, position=(x, y, z + axis_length + LABEL_HEIGHT),
            orientation=_IDENTITY, scale=(0.0, 0.0, LABEL_HEIGHT),
            color=_ORANGE if detached else _WHITE,
            text=f"{name} (anchor)" if name in anchor_set else name,
        )))
    return f.marker_array(markers)


def clear_markers(f: MessageFactory, world_frame: str, stamp_ns: int) -> Msg:
    """A ``MarkerArray`` holding only ``DELETEALL`` (after a reset, or with no edges)."""
    return f.marker_array([f.marker(f.header(world_frame, stamp_ns),
                                    MarkerSpec(action=DELETEALL))])


def diagnostic_status(
    f: MessageFactory,
    name: str,
    level: Level | int,
    message: str,
    values: Mapping[str, Any],
    hardware_id: str = "",
) -> Msg:
    """One ``DiagnosticStatus``; every entry of ``values`` becomes a ``KeyValue`` (in order),
    formatted by :func:`format_diagnostic_value`."""
    return f.diagnostic_status(
        int(level), name, message, hardware_id,
        [(str(k), format_diagnostic_value(v)) for k, v in values.items()])


def diagnostic_array(f: MessageFactory, statuses: Sequence[Msg], stamp_ns: int) -> Msg:
    """Stamped ``DiagnosticArray`` (empty ``frame_id``) holding ``statuses``."""
    return f.diagnostic_array(f.header("", stamp_ns), list(statuses))
