"""One output builder, two back-ends: rclpy and rosbags outputs are the same CDR bytes.

Each output kind is built by :mod:`rotavg_ros.msg_adapters.outputs` once with the rclpy
back-end (serialized by ``rclpy.serialization.serialize_message``, as the node publishes it)
and once with the rosbags back-end (serialized by its typestore's ``serialize_cdr``, as the
bag writer stores it); the bytes must be equal.

Except for alignment padding: Fast-CDR (rclpy) leaves the padding bytes uninitialised (they
vary with what the buffer held before), rosbags writes zeros. :func:`assert_same_cdr` hence
compares rosbags' bytes with rclpy's after a rosbags decode/encode round trip, which keeps
every value and zeroes the padding, and checks that the raw bytes differ nowhere else.
"""

from __future__ import annotations

import importlib.util
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from rclpy.serialization import serialize_message
from rotavg_ros.msg_adapters import outputs
from rotavg_ros.msg_adapters.outputs import Level, MarkerSpec

from rotavg_ros.core.so3 import random_rotations
from rotavg_ros.io.bag_messages import TF_MESSAGE, TRANSFORM_STAMPED
from rotavg_ros.io.bag_messages import MessageFactory as BagFactory
from rotavg_ros.ros.messages import FACTORY as RCLPY

BAGS = BagFactory()
STAMP_NS = 1_700_000_123_456_789_012
NODE_IDS: list[Any] = ["a", "b", 7, "d", "e", "f"]
COMPONENT = np.array([0, 0, 1, 1, 0, 2])  # "d", "7" detached; "f" alone
ANCHORS: list[Any] = ["a", 7, "f"]
ROTATIONS = random_rotations(len(NODE_IDS), np.random.default_rng(3))


def rclpy_bytes(msg: Any) -> bytes:
    return bytes(serialize_message(msg))


def bag_bytes(msg: Any) -> bytes:
    return bytes(BAGS.typestore.serialize_cdr(msg, msg.__msgtype__))


def assert_same_cdr(rclpy_msg: Any, bag_msg: Any, what: str = "") -> None:
    raw, ref = rclpy_bytes(rclpy_msg), bag_bytes(bag_msg)
    assert len(raw) == len(ref), what
    store = BAGS.typestore
    canonical = bag_bytes(store.deserialize_cdr(raw, bag_msg.__msgtype__))
    assert canonical == ref, what
    differ = np.flatnonzero(np.frombuffer(raw, np.uint8) != np.frombuffer(ref, np.uint8))
    assert not any(ref[i] for i in differ), what  # only (zero) padding may differ


def transforms(f: outputs.MessageFactory) -> list[Any]:
    return outputs.orientation_transforms(f, NODE_IDS, ROTATIONS, "map", STAMP_NS)


def markers(f: outputs.MessageFactory) -> Any:
    return outputs.orientation_markers(f, NODE_IDS, ROTATIONS, COMPONENT, ANCHORS, "map",
                                       STAMP_NS, spacing=1.5, axis_length=0.4)


def diagnostics(f: outputs.MessageFactory) -> Any:
    values = {"nodes": 6, "ratio": 0.123456789, "ok": True, "anchors": ["a", 7, "f"],
              "note": "", "detached": 2}
    status = outputs.diagnostic_status(f, "rotavg: test", Level.WARN, "3 components",
                                       values, "/rotavg")
    other = outputs.diagnostic_status(f, "second", Level.ERROR, "", {"x": 1.5})
    return outputs.diagnostic_array(f, [status, other], STAMP_NS)


def test_orientations_same_bytes() -> None:
    ours, theirs = transforms(RCLPY), transforms(BAGS)
    assert len(ours) == len(theirs) == len(NODE_IDS)
    for a, b in zip(ours, theirs, strict=True):
        assert_same_cdr(a, b)


def test_tf_same_bytes() -> None:
    bag_tf = outputs.tf_message(BAGS, transforms(BAGS))
    if importlib.util.find_spec("tf2_msgs") is not None:
        assert_same_cdr(outputs.tf_message(RCLPY, transforms(RCLPY)), bag_tf)
    # tf2_msgs is not in the pinned environment: /tf must hold exactly rclpy's transforms.
    store = BAGS.typestore
    decoded: list[Any] = [store.deserialize_cdr(rclpy_bytes(m), TRANSFORM_STAMPED)
                          for m in transforms(RCLPY)]
    rebuilt = store.types[TF_MESSAGE](transforms=decoded)
    assert bag_bytes(bag_tf) == bag_bytes(rebuilt)


def test_markers_same_bytes_with_detached_components() -> None:
    ours, theirs = markers(RCLPY), markers(BAGS)
    namespaces = {m.ns for m in theirs.markers}
    assert {outputs.NS_DETACHED_AXES, outputs.NS_DETACHED_LABELS} <= namespaces
    assert len(ours.markers) == len(theirs.markers) == 1 + 2 * len(NODE_IDS)
    for a, b in zip(ours.markers, theirs.markers, strict=True):  # to name the first culprit
        assert_same_cdr(a, b, f"marker {b.ns}/{b.id}")
    assert_same_cdr(ours, theirs)


def test_clear_markers_same_bytes() -> None:
    ours = outputs.clear_markers(RCLPY, "map", STAMP_NS)
    theirs = outputs.clear_markers(BAGS, "map", STAMP_NS)
    assert theirs.markers[0].action == outputs.DELETEALL
    assert_same_cdr(ours, theirs)


def test_diagnostics_same_bytes() -> None:
    ours, theirs = diagnostics(RCLPY), diagnostics(BAGS)
    assert [len(s.values) for s in theirs.status] == [6, 1]
    assert_same_cdr(ours, theirs)


@pytest.mark.parametrize("change", [
    {"color": (1.0, 0.55, 0.0, 0.5)},
    {"ns": outputs.NS_AXES + "_"},
    {"id": 99},
    {"orientation": (0.0, 0.0, 0.0, -1.0)},
    {"text": "x"},
])
def test_comparison_catches_a_differing_field(change: dict[str, Any]) -> None:
    """The byte comparison is sharp: one back-end given one other field value differs."""
    spec = MarkerSpec(action=outputs.ADD, ns=outputs.NS_AXES, id=3, type=outputs.LINE_LIST,
                      position=(1.0, -2.0, 0.0), orientation=(0.0, 0.6, 0.0, 0.8),
                      scale=(0.03, 0.0, 0.0), color=(0.6, 0.6, 0.6, 0.5),
                      points=((0.0, 0.0, 0.0), (0.35, 0.0, 0.0)),
                      colors=((0.6, 0.0, 0.0, 0.5),) * 2)
    ours = RCLPY.marker(RCLPY.header("map", STAMP_NS), spec)
    same = BAGS.marker(BAGS.header("map", STAMP_NS), spec)
    other = BAGS.marker(BAGS.header("map", STAMP_NS), replace(spec, **change))
    assert_same_cdr(ours, same)
    with pytest.raises(AssertionError):
        assert_same_cdr(ours, other)


def test_comparison_catches_a_differing_diagnostic_value() -> None:
    ours = RCLPY.diagnostic_status(1, "n", "m", "hw", [("k", "1"), ("j", "2")])
    other = BAGS.diagnostic_status(1, "n", "m", "hw", [("k", "1"), ("j", "3")])
    with pytest.raises(AssertionError):
        assert_same_cdr(ours, other)
