"""msg_adapters: rclpy and rosbags messages in, edges/rejections out; outputs built right."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import TransformStamped
from hypothesis import given, settings
from hypothesis import strategies as st
from nav_msgs.msg import Odometry
from rosbags.typesys import Stores, get_typestore
from rotavg_ros.msg_adapters.inputs import (
    ADAPTER_REASONS,
    CLAMPED_WEIGHT,
    DEFAULT_REFERENCE_VARIANCE,
    DEFAULT_WEIGHT_COVARIANCE,
    AdapterConfig,
    EdgeMeasurement,
    Rejection,
    edge_from_message,
    edge_from_odometry,
    edge_from_transform,
    rotation_weight_from_covariance,
)
from visualization_msgs.msg import Marker

from rotavg_ros.core.so3 import matrix_to_quat, quat_to_matrix, random_rotations
from rotavg_ros.ros.messages import (
    NS_AXES,
    NS_DETACHED_AXES,
    NS_DETACHED_LABELS,
    NS_LABELS,
    Level,
    diagnostic_array,
    diagnostic_status,
    diagnostic_values,
    grid_layout,
    orientation_markers,
    orientation_transforms,
)

TS = get_typestore(Stores.ROS2_JAZZY)
REF = DEFAULT_REFERENCE_VARIANCE


# ---------------------------------------------------------------------- builders
def rclpy_transform(i: str, j: str, q: Any, sec: int = 0, nanosec: int = 0) -> TransformStamped:
    msg = TransformStamped()
    msg.header.frame_id = i
    msg.header.stamp.sec = sec
    msg.header.stamp.nanosec = nanosec
    msg.child_frame_id = j
    msg.transform.translation.x = 5.0  # ignored
    r = msg.transform.rotation
    r.x, r.y, r.z, r.w = (float(v) for v in q)
    return msg


def rosbags_transform(i: str, j: str, q: Any, sec: int = 0, nanosec: int = 0) -> Any:
    t = TS.types
    return t["geometry_msgs/msg/TransformStamped"](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=i
        ),
        child_frame_id=j,
        transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](x=5.0, y=0.0, z=0.0),
            rotation=t["geometry_msgs/msg/Quaternion"](*(float(v) for v in q)),
        ),
    )


def rclpy_odometry(i: str, j: str, q: Any, cov: Any, sec: int = 0) -> Odometry:
    msg = Odometry()
    msg.header.frame_id = i
    msg.header.stamp.sec = sec
    msg.child_frame_id = j
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = (float(v) for v in q)
    msg.pose.covariance = np.asarray(cov, dtype=np.float64).reshape(36)
    return msg


def rosbags_odometry(i: str, j: str, q: Any, cov: Any, sec: int = 0) -> Any:
    t = TS.types
    vec = t["geometry_msgs/msg/Vector3"]
    return t["nav_msgs/msg/Odometry"](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=0), frame_id=i
        ),
        child_frame_id=j,
        pose=t["geometry_msgs/msg/PoseWithCovariance"](
            pose=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=3.0),
                orientation=t["geometry_msgs/msg/Quaternion"](*(float(v) for v in q)),
            ),
            covariance=np.asarray(cov, dtype=np.float64).reshape(36),
        ),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](linear=vec(0.0, 0.0, 0.0),
                                               angular=vec(0.0, 0.0, 0.0)),
            covariance=np.zeros(36),
        ),
    )


def rot_cov(vx: float, vy: float | None = None, vz: float | None = None) -> np.ndarray:
    cov = np.zeros((6, 6))
    cov[0, 0] = cov[1, 1] = cov[2, 2] = 0.25  # translation block: ignored
    cov[3, 3] = vx
    cov[4, 4] = vx if vy is None else vy
    cov[5, 5] = vx if vz is None else vz
    return cov


TRANSFORM_BUILDERS: list[Callable[..., Any]] = [rclpy_transform, rosbags_transform]
ODOMETRY_BUILDERS: list[Callable[..., Any]] = [rclpy_odometry, rosbags_odometry]


# ---------------------------------------------------------------------- conventions
@pytest.mark.parametrize("build", TRANSFORM_BUILDERS)
def test_tf_convention_rotation_is_child_in_parent(build: Any) -> None:
    # Child frame j is the parent i rotated by +90 deg about z: j's x axis is i's y axis.
    s = math.sqrt(0.5)
    edge = edge_from_transform(build("i", "j", [0.0, 0.0, s, s], 12, 34))
    assert isinstance(edge, EdgeMeasurement)
    assert (edge.frame_i, edge.frame_j, edge.weight, edge.notes) == ("i", "j", 1.0, ())
    assert edge.stamp_ns == 12_000_000_034
    np.testing.assert_allclose(edge.R[:, 0], [0.0, 1.0, 0.0], atol=1e-12)
    # R_ij = R_i R_j^T for world-to-node R_i: a vector in j's coordinates maps to i's.
    rng = np.random.default_rng(3)
    Ri, Rj = random_rotations(2, rng)
    e = edge_from_transform(build("i", "j", matrix_to_quat(Ri @ Rj.T)))
    assert isinstance(e, EdgeMeasurement)
    np.testing.assert_allclose(e.R, Ri @ Rj.T, atol=1e-12)


def test_rclpy_and_rosbags_convert_identically() -> None:
    rng = np.random.default_rng(0)
    qs = rng.normal(size=(50, 4))
    qs /= np.linalg.norm(qs, axis=1, keepdims=True)
    qs *= 1.0 + rng.uniform(-9e-4, 9e-4, size=(50, 1))  # inside the default tolerance
    for k, q in enumerate(qs):
        a = edge_from_transform(rclpy_transform(f"a{k}", "b", q, k, 7 * k))
        b = edge_from_transform(rosbags_transform(f"a{k}", "b", q, k, 7 * k))
        assert isinstance(a, EdgeMeasurement) and isinstance(b, EdgeMeasurement)
        assert (a.frame_i, a.frame_j, a.weight, a.stamp_ns) == (
            b.frame_i, b.frame_j, b.weight, b.stamp_ns)
        np.testing.assert_array_equal(a.R, b.R)
        np.testing.assert_allclose(a.R @ a.R.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(a.R, quat_to_matrix(q), atol=1e-12)
        cov = rot_cov(rng.uniform(0.5, 2.0) * REF)
        c = edge_from_odometry(rclpy_odometry(f"a{k}", "b", q, cov, k))
        d = edge_from_odometry(rosbags_odometry(f"a{k}", "b", q, cov, k))
        assert isinstance(c, EdgeMeasurement) and isinstance(d, EdgeMeasurement)
        assert (c.weight, c.stamp_ns, c.notes) == (d.weight, d.stamp_ns, d.notes)
        np.testing.assert_array_equal(c.R, a.R)
        np.testing.assert_array_equal(d.R, a.R)


def test_dispatch_on_message_shape() -> None:
    q = [0.0, 0.0, 0.0, 1.0]
    for msg in (rclpy_transform("a", "b", q), rosbags_transform("a", "b", q),
                rclpy_odometry("a", "b", q, np.zeros(36)),
                rosbags_odometry("a", "b", q, np.zeros(36))):
        assert isinstance(edge_from_message(msg), EdgeMeasurement)
    assert edge_from_message(Time()) == Rejection("unsupported_message", "Time")


# ---------------------------------------------------------------------- rejections
GOOD_Q = [0.0, 0.0, 0.0, 1.0]
REJECTION_CASES = [
    ("", "b", GOOD_Q, "empty_frame_id"),
    ("a", "", GOOD_Q, "empty_frame_id"),
    ("a", "a", GOOD_Q, "self_loop"),
    ("a", "b\x00", GOOD_Q, "invalid_frame_id"),
    ("a\n", "b", GOOD_Q, "invalid_frame_id"),
    ("a\tb", "b", GOOD_Q, "invalid_frame_id"),
    ("with space", "b", GOOD_Q, "invalid_frame_id"),
    ("/leading_slash", "b", GOOD_Q, "invalid_frame_id"),
    ("x" * 257, "b", GOOD_Q, "invalid_frame_id"),
    ("world", "b", GOOD_Q, "reserved_frame_id"),
    ("a", "b", [math.nan, 0.0, 0.0, 1.0], "non_finite_quaternion"),
    ("a", "b", [0.0, math.inf, 0.0, 1.0], "non_finite_quaternion"),
    ("a", "b", [0.0, 0.0, 0.0, 0.0], "zero_quaternion"),
    ("a", "b", [0.0, 0.0, 0.0, 1.0011], "non_unit_quaternion"),
    ("a", "b", [0.0, 0.0, 0.0, 0.5], "non_unit_quaternion"),
    ("a", "b", [1.0, 1.0, 1.0, 1.0], "non_unit_quaternion"),
]
CONFIG = AdapterConfig(reserved_frames=frozenset({"world"}))


@pytest.mark.parametrize("build", TRANSFORM_BUILDERS + ODOMETRY_BUILDERS)
@pytest.mark.parametrize(("i", "j", "q", "reason"), REJECTION_CASES)
def test_each_rejection_reason(build: Any, i: str, j: str, q: list[float], reason: str) -> None:
    assert reason in ADAPTER_REASONS
    if build in ODOMETRY_BUILDERS:
        msg = build(i, j, q, np.zeros(36))
    else:
        msg = build(i, j, q)
    out = edge_from_message(msg, CONFIG)
    assert isinstance(out, Rejection)
    assert out.reason == reason


def test_frame_id_limits() -> None:
    ok = edge_from_transform(rclpy_transform("x" * 256, "ünïcode_frame", GOOD_Q))
    assert isinstance(ok, EdgeMeasurement)
    assert isinstance(edge_from_transform(rclpy_transform("world", "b", GOOD_Q)),
                      EdgeMeasurement)  # reserved only when configured


def test_quaternion_tolerance_is_a_parameter() -> None:
    near = [0.0, 0.0, 0.0, 1.0 + 0.9e-3]
    edge = edge_from_transform(rclpy_transform("a", "b", near))
    assert isinstance(edge, EdgeMeasurement)
    np.testing.assert_allclose(edge.R, np.eye(3), atol=1e-15)  # normalised
    strict = AdapterConfig(quaternion_tolerance=1e-6)
    assert edge_from_transform(rclpy_transform("a", "b", near), strict) == Rejection(
        "non_unit_quaternion", "|q| = 1.0009")
    loose = AdapterConfig(quaternion_tolerance=0.6)
    assert isinstance(edge_from_transform(rclpy_transform("a", "b", [0, 0, 0, 0.5]), loose),
                      EdgeMeasurement)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-2.0, 2.0), min_size=4, max_size=4))
def test_any_quaternion_is_accepted_iff_near_unit(q: list[float]) -> None:
    norm = float(np.linalg.norm(q))
    out = edge_from_transform(rclpy_transform("a", "b", q))
    if norm < 1e-9:
        assert out == Rejection("zero_quaternion", str([float(v) for v in q]))
    elif abs(norm - 1.0) > 1e-3:
        assert isinstance(out, Rejection) and out.reason == "non_unit_quaternion"
    else:
        assert isinstance(out, EdgeMeasurement)
        np.testing.assert_allclose(out.R @ out.R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(out.R) == pytest.approx(1.0, abs=1e-12)


# ---------------------------------------------------------------------- weights
@pytest.mark.parametrize(
    ("cov", "weight", "notes"),
    [
        (rot_cov(REF), 1.0, ()),
        (rot_cov(4 * REF), 0.25, ()),
        (rot_cov(REF / 10), 10.0, ()),
        (rot_cov(REF, 2 * REF, 3 * REF), 0.5, ()),  # 3 ref / (6 ref)
        (rot_cov(1e-12), 1e3, (CLAMPED_WEIGHT,)),
        (rot_cov(10.0), 1e-3, (CLAMPED_WEIGHT,)),
        (np.zeros((6, 6)), 1.0, (DEFAULT_WEIGHT_COVARIANCE,)),
        (rot_cov(REF, 0.0, REF), 1.0, (DEFAULT_WEIGHT_COVARIANCE,)),
        (rot_cov(REF, -REF, REF), 1.0, (DEFAULT_WEIGHT_COVARIANCE,)),
        (rot_cov(math.nan), 1.0, (DEFAULT_WEIGHT_COVARIANCE,)),
        (rot_cov(math.inf), 1.0, (DEFAULT_WEIGHT_COVARIANCE,)),
        (np.full(36, REF), 1.0, ()),  # off-diagonal terms do not enter the trace
    ],
)
def test_covariance_to_weight(cov: np.ndarray, weight: float, notes: tuple[str, ...]) -> None:
    for build in ODOMETRY_BUILDERS:
        edge = edge_from_odometry(build("a", "b", GOOD_Q, cov))
        assert isinstance(edge, EdgeMeasurement)
        assert edge.weight == pytest.approx(weight, rel=1e-12)
        assert edge.notes == notes


def test_covariance_mapping_details() -> None:
    # Only rows/cols 3..5 count; translation variances do not.
    cov = np.zeros((6, 6))
    cov[0, 0] = cov[1, 1] = cov[2, 2] = 1e6
    cov[3, 3] = cov[4, 4] = cov[5, 5] = REF
    assert rotation_weight_from_covariance(cov.reshape(-1)) == (pytest.approx(1.0), ())
    assert rotation_weight_from_covariance(list(cov.reshape(-1))) == (pytest.approx(1.0), ())
    assert rotation_weight_from_covariance([1.0] * 35) == (1.0, (DEFAULT_WEIGHT_COVARIANCE,))
    # reference_variance sets the unit: (2 deg)^2 reference -> a (1 deg)^2 edge weighs 4.
    cfg = AdapterConfig(reference_variance=math.radians(2.0) ** 2)
    assert rotation_weight_from_covariance(rot_cov(REF), cfg)[0] == pytest.approx(4.0)
    cfg = AdapterConfig(min_weight=0.5, max_weight=2.0)
    assert rotation_weight_from_covariance(rot_cov(REF / 100), cfg) == (2.0, (CLAMPED_WEIGHT,))
    # A rejected Odometry carries no default-weight note (it is not an edge at all).
    assert isinstance(edge_from_odometry(rclpy_odometry("a", "a", GOOD_Q, np.zeros(36))),
                      Rejection)


# ---------------------------------------------------------------------- outputs
def test_orientation_transforms_are_node_to_world() -> None:
    rng = np.random.default_rng(1)
    R = random_rotations(4, rng)  # world-to-node
    stamp = Time(sec=5, nanosec=6)
    msgs = orientation_transforms(["a", "b", 3, "d"], R, "map", stamp)
    assert [m.child_frame_id for m in msgs] == ["a", "b", "3", "d"]
    for m, Ri in zip(msgs, R, strict=True):
        assert m.header.frame_id == "map" and m.header.stamp == stamp
        r = m.transform.rotation
        # TF: orientation of the node frame in the world frame = R_i^T.
        np.testing.assert_allclose(quat_to_matrix([r.x, r.y, r.z, r.w]), Ri.T, atol=1e-12)
        t = m.transform.translation
        assert (t.x, t.y, t.z) == (0.0, 0.0, 0.0)
    # Feeding a published transform back in as an edge world -> node gives R_world,i with
    # R_world = I: R_wi = R_i^T, i.e. the conventions close.
    back = edge_from_transform(msgs[0])
    assert isinstance(back, EdgeMeasurement)
    np.testing.assert_allclose(back.R, R[0].T, atol=1e-12)


def test_grid_layout_separates_components() -> None:
    comp = np.array([0, 0, 1, 0, 1, 2, 0])
    pos = grid_layout(comp, spacing=2.0)
    assert pos.shape == (7, 3)
    assert len({tuple(p) for p in pos}) == 7
    assert pos[comp == 0, 0].max() < pos[comp == 1, 0].min() < pos[comp == 2, 0].min()
    np.testing.assert_allclose(pos[0], [0.0, 0.0, 0.0])


def test_markers_namespaces_and_contents() -> None:
    rng = np.random.default_rng(2)
    R = random_rotations(5, rng)
    comp = np.array([0, 0, 1, 1, 0])
    stamp = Time(sec=1)
    arr = orientation_markers(["a", "b", "c", "d", "e"], R, comp, ["a", "c"], "world", stamp)
    assert arr.markers[0].action == Marker.DELETEALL
    markers = arr.markers[1:]
    assert len(markers) == 10
    by_ns: dict[str, list[Marker]] = {}
    for m in markers:
        assert m.header.frame_id == "world" and m.header.stamp == stamp
        by_ns.setdefault(m.ns, []).append(m)
    assert sorted(m.id for m in by_ns[NS_AXES]) == [0, 1, 4]
    assert sorted(m.id for m in by_ns[NS_DETACHED_AXES]) == [2, 3]
    assert {m.text for m in by_ns[NS_LABELS]} == {"a (anchor)", "b", "e"}
    assert {m.text for m in by_ns[NS_DETACHED_LABELS]} == {"c (anchor)", "d"}
    for m in by_ns[NS_AXES] + by_ns[NS_DETACHED_AXES]:
        assert m.type == Marker.LINE_LIST and len(m.points) == 6 and len(m.colors) == 6
        o = m.pose.orientation
        np.testing.assert_allclose(quat_to_matrix([o.x, o.y, o.z, o.w]), R[m.id].T, atol=1e-12)
    for m in by_ns[NS_LABELS] + by_ns[NS_DETACHED_LABELS]:
        assert m.type == Marker.TEXT_VIEW_FACING
    assert by_ns[NS_DETACHED_LABELS][0].color != by_ns[NS_LABELS][0].color


def test_diagnostics_from_stats() -> None:
    status = diagnostic_status(
        "rotavg: test", Level.WARN, "2 components",
        {"nodes": 3, "ratio": 0.123456789, "ok": True, "anchors": ["a", "b"]}, "hw",
    )
    assert status.level == DiagnosticStatus.WARN
    arr = diagnostic_array([status], Time(sec=9))
    assert arr.header.stamp.sec == 9
    assert diagnostic_values(arr) == {
        "nodes": "3", "ratio": "0.123457", "ok": "true", "anchors": "a, b"}
    assert diagnostic_values(arr, "other") == {}
    for level, expected in [(Level.OK, DiagnosticStatus.OK), (Level.ERROR, DiagnosticStatus.ERROR)]:
        assert diagnostic_status("x", level, "", {}).level == expected
