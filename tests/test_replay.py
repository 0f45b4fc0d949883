"""``rotavg replay``: bag reading (good, damaged, recorded by rclpy), scheduling, outputs,
reports, and equality with the live node fed the same messages.

Bags are written to ``tmp_path`` with rosbags (rosbag2 directories) or the ``mcap`` writer
(lone ``.mcap`` files, small chunks so that damage leaves some chunks intact). Tests that
exercise scheduling and reporting use the exact spanning-tree solver from ``ros_fixtures``;
the command-line, equivalence and committed-bag tests run the real solver with few
iterations.
"""

from __future__ import annotations

import io
import math
from collections import Counter
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ros_fixtures import (
    RosHarness,
    aligned_errors_deg,
    spanning_tree_solve,
    wait_until,
)
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from rotavg_ros import cli
from rotavg_ros.app.parameters import settings_from_parameters
from rotavg_ros.app.session import default_solve
from rotavg_ros.core.so3 import (
    matrix_to_quat,
    quat_to_matrix,
    random_rotations,
    rotation_about_axis,
)
from rotavg_ros.errors import InputError
from rotavg_ros.io.bag_messages import TRANSFORM_STAMPED, MessageFactory
from rotavg_ros.io.g2o import g2o_id_mapping, read_g2o_vertices, write_g2o_with_mapping
from rotavg_ros.replay import EXIT_INPUT, EXIT_NOTHING_USABLE, EXIT_OK, ReplayConfig, run_replay
from rotavg_ros.replay.config import ODOMETRY
from rotavg_ros.replay.progress import ProgressBar

REPO = Path(__file__).resolve().parents[1]
T0 = 1_000 * 1_000_000_000
MS = 1_000_000
FACTORY = MessageFactory()
STORE = FACTORY.typestore

Msg = tuple[str, int, Any]  # topic, log time ns, rosbags message


# ---------------------------------------------------------------------- bag helpers
def transform(parent: str, child: str, R: np.ndarray, t: int) -> Any:
    return FACTORY.transform(parent, child, matrix_to_quat(R), t)


def odometry(parent: str, child: str, R: np.ndarray, t: int, rot_var: float = 0.0) -> Any:
    msg = FACTORY.new(ODOMETRY, header=FACTORY.header(parent, t), child_frame_id=child)
    x, y, z, w = (float(v) for v in matrix_to_quat(R))
    msg.pose.pose.orientation = FACTORY.new("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w)
    cov = np.zeros((6, 6))
    cov[3, 3] = cov[4, 4] = cov[5, 5] = rot_var
    msg.pose.covariance = cov.reshape(-1)
    return msg


def write_bag(path: Path, msgs: Iterable[Msg], types: dict[str, str] | None = None,
              raw: dict[str, list[tuple[int, bytes]]] | None = None) -> Path:
    """rosbag2 directory (rosbags, MCAP); ``raw`` adds pre-serialised messages per topic."""
    msgs = sorted(msgs, key=lambda m: m[1])
    types = dict(types or {})
    for topic, _, msg in msgs:
        types.setdefault(topic, msg.__msgtype__)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {t: writer.add_connection(t, typ, typestore=STORE) for t, typ in types.items()}
        items = [(t, c, FACTORY.serialize(m)) for c, t, m in msgs]
        for topic, entries in (raw or {}).items():
            items += [(t, topic, data) for t, data in entries]
        for t, topic, data in sorted(items, key=lambda x: x[0]):
            writer.write(conns[topic], t, data)
    return path


def write_mcap(path: Path, msgs: Iterable[tuple[str, int, str, bytes]],
               chunk_size: int = 2048, profile: str = "ros2",
               schemas: dict[str, str] | None = None) -> Path:
    """Lone .mcap with the mcap writer: ``(topic, log time, type, cdr bytes)`` records."""
    from mcap.writer import CompressionType
    from mcap.writer import Writer as McapWriter

    with open(path, "wb") as fh:
        w = McapWriter(fh, chunk_size=chunk_size, compression=CompressionType.NONE)
        w.start(profile=profile, library="test")
        channels: dict[str, int] = {}
        for topic, t, typ, data in msgs:
            if topic not in channels:
                text = (schemas or {}).get(typ)
                if text is None:
                    text = STORE.generate_msgdef(typ, ros_version=2)[0]
                sid = w.register_schema(typ, "ros2msg", text.encode()) if text else 0
                channels[topic] = w.register_channel(topic, "cdr", sid)
            w.add_message(channels[topic], log_time=t, data=data, publish_time=t)
        w.finish()
    return path


def read_bag(path: Path) -> dict[str, list[tuple[int, Any]]]:
    out: dict[str, list[tuple[int, Any]]] = {}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
        for conn, t, raw in r.messages():
            out.setdefault(conn.topic, []).append((t, r.deserialize(raw, conn.msgtype)))
    return out


def ground_truth(n: int, seed: int, prefix: str = "n") -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {f"{prefix}{k}": R for k, R in enumerate(random_rotations(n, rng))}


def gt_messages(gt: dict[str, np.ndarray], t: int = T0) -> list[Msg]:
    return [("/ground_truth", t, transform("world", k, R.T, t)) for k, R in gt.items()]


def noisy(R: np.ndarray, deg: float, rng: np.random.Generator) -> np.ndarray:
    if deg == 0.0:
        return R
    return rotation_about_axis(rng.normal(size=3), np.radians(abs(rng.normal(scale=deg)))) @ R


def mixed_bag_messages(gt: dict[str, np.ndarray], seed: int, noise_deg: float = 1.0,
                       outliers: float = 0.0, tf_message: bool = True) -> list[Msg]:
    """Edges over ~half the pairs as TransformStamped (/edges, some reversed), Odometry
    (/odom) and, optionally, TFMessage (/tf_edges, two transforms each); 5 ms apart."""
    rng = np.random.default_rng(seed)
    names = list(gt)
    n = len(names)
    pairs = [(a, b) for a in range(n) for b in range(a + 1, n) if b == a + 1 or rng.random() < 0.4]
    msgs: list[Msg] = []
    pending_tf: list[Any] = []
    t = T0 + 10 * MS
    for a, b in pairs:
        i, j = names[a], names[b]
        R = gt[i] @ gt[j].T
        R = random_rotations(1, rng)[0] if rng.random() < outliers else noisy(R, noise_deg, rng)
        kind = rng.integers(4 if tf_message else 3)
        if kind == 0:
            msgs.append(("/edges", t, transform(i, j, R, t)))
        elif kind == 1:
            msgs.append(("/edges", t, transform(j, i, R.T, t)))
        elif kind == 2:
            msgs.append(("/odom", t, odometry(i, j, R, t, np.radians(noise_deg) ** 2)))
        else:
            pending_tf.append(transform(i, j, R, t))
            if len(pending_tf) == 2:
                msgs.append(("/tf_edges", t, FACTORY.tf_message(pending_tf)))
                pending_tf = []
        t += 5 * MS
    return msgs


def config(bag: Path, **kwargs: Any) -> ReplayConfig:
    params = kwargs.pop("params", {})
    return ReplayConfig(bag=bag, settings=settings_from_parameters(params), quiet=True,
                        **kwargs)


def replay(bag: Path, solve_fn: Any = spanning_tree_solve, **kwargs: Any) -> Any:
    out = io.StringIO()
    report = run_replay(config(bag, **kwargs), solve_fn=solve_fn, out=out, err=io.StringIO())
    report.text = out.getvalue()  # type: ignore[attr-defined]
    return report


# ---------------------------------------------------------------------- command line
def test_cli_solve_once_recovers_ground_truth_and_writes_outputs(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """All three edge types + GT + an unrelated topic through ``rotavg replay`` with the real
    solver: accurate, every output topic written at the last message's time, g2o ids from
    the frame ids, exit 0."""
    gt = ground_truth(20, seed=1)
    msgs = mixed_bag_messages(gt, seed=2, noise_deg=1.0)
    msgs += gt_messages(gt)
    chatter = FACTORY.new("std_msgs/msg/String", data="hello")
    msgs += [("/chatter", T0 + k * MS, chatter) for k in range(3)]
    bag = write_bag(tmp_path / "in", msgs)
    out, g2o = tmp_path / "out", tmp_path / "final.g2o"
    code = cli.main(["replay", str(bag), "--output", str(out), "--output-g2o", str(g2o),
                     "--depths", "2", "--iterations", "300", "--seed", "3"])
    text = capsys.readouterr().out
    assert code == EXIT_OK, text
    assert "solve 1 at bag time" in text and "vs ground truth (20 nodes)" in text
    for topic in ("/edges", "/odom", "/tf_edges", "/ground_truth"):
        assert topic in text
    assert "/chatter (std_msgs/msg/String, 3 msgs): not an edge message type" in text
    assert "(edges = transforms)" in text and "solves: 1 (1 ok, 0 failed)" in text

    written = read_bag(out)
    last_t = max(t for _, t, _ in msgs if _ != "/ground_truth" and _ != "/chatter")
    assert set(written) == {"/rotavg_node/orientations", "/tf", "/rotavg_node/markers",
                            "/diagnostics"}
    orient = written["/rotavg_node/orientations"]
    assert len(orient) == 20 and {t for t, _ in orient} == {last_t}
    est = {m.child_frame_id: quat_to_matrix([m.transform.rotation.x, m.transform.rotation.y,
                                             m.transform.rotation.z, m.transform.rotation.w]).T
           for _, m in orient}
    assert all(m.header.frame_id == "world" for _, m in orient)
    errors = aligned_errors_deg(est, gt)
    assert errors.mean() < 1.5 and errors.max() < 4.0, errors
    (t_tf, tf), = written["/tf"]
    assert t_tf == last_t and len(tf.transforms) == 20
    (_, markers), = written["/rotavg_node/markers"]
    assert len(markers.markers) == 1 + 2 * 20 and markers.markers[0].action == 3
    (_, diag), = written["/diagnostics"]
    values = {kv.key: kv.value for kv in diag.status[0].values}
    assert diag.status[0].name == "rotavg_node: rotation averaging"
    assert values["solved_nodes"] == "20" and values["solves_completed"] == "1"
    first_frame = msgs[0][2].header.frame_id if msgs[0][0] == "/edges" else None
    if first_frame is not None:
        np.testing.assert_allclose(est[first_frame], np.eye(3), atol=1e-9)  # the anchor

    ids, rots = read_g2o_vertices(g2o)
    assert sorted(ids) == list(range(20))
    assert g2o.read_text().startswith("# rotavg replay:")
    for vid, R in zip(ids, rots, strict=True):
        np.testing.assert_allclose(R, est[f"n{vid}"], atol=1e-9)


def test_cli_argument_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        cli.main(["replay", "x", "--solve-once", "--solve-period", "1"])
    assert cli.main(["replay", str(tmp_path / "missing")]) == EXIT_INPUT
    assert "no such file" in capsys.readouterr().err
    assert cli.main(["replay", str(tmp_path), "--solve-period", "0"]) == EXIT_INPUT
    assert "--solve-period" in capsys.readouterr().err
    assert cli.main(["replay", str(tmp_path), "--depths", "3"]) == EXIT_INPUT


# ---------------------------------------------------------------------- scheduling
def chain_messages(gt: dict[str, np.ndarray], times_s: list[float]) -> list[Msg]:
    names = list(gt)
    return [("/edges", T0 + int(s * 1e9),
             transform(names[k], names[k + 1], gt[names[k]] @ gt[names[k + 1]].T,
                       T0 + int(s * 1e9)))
            for k, s in enumerate(times_s)]


def test_solve_period_follows_the_timer_in_bag_time(tmp_path: Path) -> None:
    gt = ground_truth(6, seed=4)
    msgs = chain_messages(gt, [0.0, 0.4, 1.0, 1.2, 7.3])
    bad = transform("x", "x", np.eye(3), T0 + int(5.5e9))  # rejected: counters move only
    msgs.append(("/edges", T0 + int(5.5e9), bad))
    bag = write_bag(tmp_path / "in", msgs)
    report = replay(bag, solve_period=1.0, output=tmp_path / "out")
    # ticks at 1 s (message at exactly 1 s counts before it), 2 s, 6 s (diagnostics only:
    # the rejection), 8 s (after the last message).
    assert [(s.bag_time_ns - T0) / 1e9 for s in report.solves] == [1.0, 2.0, 8.0]
    assert [len(s.attempt.result.node_ids) for s in report.solves] == [4, 5, 6]
    assert report.diagnostics_only_ticks == 1
    written = read_bag(tmp_path / "out")
    assert [(t - T0) / 1e9 for t, _ in written["/tf"]] == [1.0, 2.0, 8.0]
    assert [(t - T0) / 1e9 for t, _ in written["/diagnostics"]] == [1.0, 2.0, 6.0, 8.0]
    _, diag = written["/diagnostics"][2]
    assert {kv.key: kv.value for kv in diag.status[0].values}["self_loop"] == "1"
    assert report.topics["/edges"].rejected == Counter({"self_loop": 1})
    errors = aligned_errors_deg(report.final_orientations, gt)
    assert errors.max() < 1e-4

    once = replay(bag)
    assert len(once.solves) == 1 and once.solves[0].bag_time_ns == T0 + int(7.3e9)


# ---------------------------------------------------------------------- reports
def test_rejections_topics_and_exit_status(tmp_path: Path) -> None:
    gt = ground_truth(4, seed=5)
    msgs = chain_messages(gt, [0.1, 0.2, 0.3])
    t = T0 + int(1e9)
    bad_q = transform("a", "b", np.eye(3), t)
    bad_q.transform.rotation.w = 2.0
    msgs += [
        ("/edges", t, bad_q),
        ("/edges", t + 1, transform("", "b", np.eye(3), t + 1)),
        ("/odom", t + 2, odometry("world", "b", np.eye(3), t + 2)),  # the output frame
        ("/odom", t + 3, odometry("a", "a", np.eye(3), t + 3)),
        ("/tf", t + 4, FACTORY.tf_message([transform("base", "laser", np.eye(3), t + 4)])),
        ("/empty_tf", t + 5, FACTORY.tf_message([])),
    ]
    bag = write_bag(tmp_path / "in", msgs)
    report = replay(bag)
    assert report.exit_code == EXIT_OK
    assert report.topics["/edges"].used == 3
    assert report.topics["/edges"].rejected == Counter(
        {"non_unit_quaternion": 1, "empty_frame_id": 1})
    assert report.topics["/odom"].rejected == Counter(
        {"reserved_frame_id": 1, "self_loop": 1})
    assert report.topics["/tf"].role == "ignored"  # not an edge topic by default
    assert report.topics["/empty_tf"].rejected == Counter({"empty_tf_message": 1})
    text = report.text
    assert "rejected: empty_frame_id 1, non_unit_quaternion 1" in text
    assert "/tf (tf2_msgs/msg/TFMessage, 1 msgs): not an edge topic by default" in text

    explicit = replay(bag, edge_topics=["/tf", "/nope"])
    assert explicit.topics["/tf"].used == 1 and explicit.topics["/edges"].role == "ignored"
    assert any("/nope: not in the bag" in p for p in explicit.problems)

    nothing = replay(bag, edge_topics=["/odom"])
    assert nothing.exit_code == EXIT_NOTHING_USABLE and nothing.final is None


def test_g2o_id_mapping(tmp_path: Path) -> None:
    assert g2o_id_mapping(["cam_3", "cam_10", "cam_0"]) == (
        [3, 10, 0], "g2o id = the integer in frame id 'cam_<id>'")
    assert g2o_id_mapping(["7", "2"])[0] == [7, 2]
    for names in (["cam_007", "cam_8"], ["a1", "b2"], ["x", "y"], ["c1", "c01"]):
        ids, how = g2o_id_mapping(names)
        assert ids == list(range(len(names))) and how.startswith("sequential"), names
    from rotavg_ros.core.result import SolveResult

    rots = random_rotations(3, np.random.default_rng(0))
    result = SolveResult(["left", "right", "up"], rots, np.zeros(3, np.int64), ["left"], 0,
                         np.zeros(0), np.zeros(0, bool), 0, {}, 0.0)
    path = tmp_path / "out.g2o"
    how = write_g2o_with_mapping(path, result)
    sidecar = tmp_path / "out.frames.tsv"
    assert str(sidecar) in how
    assert sidecar.read_text().splitlines() == ["g2o_id\tframe_id", "0\tleft", "1\tright",
                                                "2\tup"]
    ids, back = read_g2o_vertices(path)
    assert ids == [0, 1, 2]
    np.testing.assert_allclose(back, rots, atol=1e-12)


def test_progress_bar_format_and_tty_detection(tmp_path: Path) -> None:
    stream = io.StringIO()
    bar = ProgressBar(20000, stream, enabled=True, width=10)
    bar.update(10400, force=True)
    assert stream.getvalue().startswith("\r[#####     ]  52% 10400/20000 msgs")
    bar.clear()
    bar.finish()
    assert stream.getvalue().endswith("\n")
    quiet = io.StringIO()
    ProgressBar(10, quiet, enabled=False).update(5, force=True)
    assert quiet.getvalue() == ""

    gt = ground_truth(3, seed=6)
    bag = write_bag(tmp_path / "in", chain_messages(gt, [0.1, 0.2]))
    err, out = io.StringIO(), io.StringIO()  # StringIO is not a TTY: no bar, summary printed
    run_replay(ReplayConfig(bag=bag, settings=settings_from_parameters({})),
               solve_fn=spanning_tree_solve, out=out, err=err)
    assert err.getvalue() == "" and "replay summary" in out.getvalue()
    assert "solve 1 at bag time" in out.getvalue()


def test_failing_solver_is_reported(tmp_path: Path) -> None:
    gt = ground_truth(4, seed=14)
    bag = write_bag(tmp_path / "in", chain_messages(gt, [0.1, 0.2, 0.3]))

    def broken(*_: Any) -> Any:
        raise RuntimeError("out of memory")

    report = replay(bag, solve_fn=broken, output=tmp_path / "out")
    assert report.exit_code == 3 and report.final is None
    assert "solves: 1 (0 ok, 1 failed)" in report.text
    assert "failed: RuntimeError: out of memory" in report.text  # the reason, not just a count
    (_, diag), = read_bag(tmp_path / "out")["/diagnostics"]
    assert diag.status[0].level == 2 and "out of memory" in diag.status[0].message
    with pytest.raises(InputError, match="must not be the input bag"):
        replay(bag, output=bag, overwrite=True)
    assert (bag / "metadata.yaml").is_file()


def test_ignored_ground_truth_topic_is_not_taken_for_edges(tmp_path: Path) -> None:
    gt = ground_truth(5, seed=15)
    bag = write_bag(tmp_path / "in", chain_messages(gt, [0.1, 0.2, 0.3, 0.4]) + gt_messages(gt))
    report = replay(bag, gt_topic="")
    stats = report.topics["/ground_truth"]
    assert stats.role == "ignored" and stats.used == 0 and not stats.rejected
    assert "--edge-topics" in stats.note
    assert report.final_errors is None and report.exit_code == 0
    named = replay(bag, gt_topic="", edge_topics=["/edges", "/ground_truth"])
    assert named.topics["/ground_truth"].role == "edges"  # still possible when asked for


# ---------------------------------------------------------------------- damaged bags
def cdr(msg: Any) -> bytes:
    return FACTORY.serialize(msg)


def chain_records(gt: dict[str, np.ndarray], start_ms: int = 0) -> list[tuple[str, int, str,
                                                                             bytes]]:
    names = list(gt)
    out = []
    for k in range(len(names) - 1):
        t = T0 + (start_ms + k) * MS
        msg = transform(names[k], names[k + 1], gt[names[k]] @ gt[names[k + 1]].T, t)
        out.append(("/edges", t, TRANSFORM_STAMPED, cdr(msg)))
    return out


def test_truncated_mcap_uses_every_complete_chunk(tmp_path: Path) -> None:
    gt = ground_truth(120, seed=7)
    path = write_mcap(tmp_path / "run.mcap", chain_records(gt), chunk_size=2048)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * 0.6)])
    report = replay(path)
    assert report.exit_code == EXIT_OK
    assert report.reader == "mcap stream reader"
    used = report.topics["/edges"].used
    assert 30 < used < 119
    assert any("rosbags could not open" in p for p in report.problems)
    assert any("stopped at byte" in p for p in report.problems)
    # the chain's first `used` edges were read, in order: n0..n{used}
    assert len(report.final.node_ids) == used + 1
    assert aligned_errors_deg(report.final_orientations,
                              {k: gt[k] for k in list(gt)[: used + 1]}).max() < 1e-4
    assert "problems:" in report.text


def test_corrupt_chunk_in_rosbag2_directory(tmp_path: Path) -> None:
    """rosbags stops at the damaged chunk; the stream reader cannot get past it either, so
    the chunks before it are used and the report says what was lost."""
    gt = ground_truth(120, seed=8)
    bag = tmp_path / "bag"
    bag.mkdir()
    mcap = write_mcap(bag / "bag_0.mcap", chain_records(gt), chunk_size=2048)
    # a rosbag2 directory around it: metadata.yaml listing the file
    meta_src = write_bag(tmp_path / "tmpl", chain_messages(ground_truth(2, seed=0), [0.0]))
    meta = (meta_src / "metadata.yaml").read_text()
    meta = meta.replace("tmpl.mcap", "bag_0.mcap").replace("message_count: 1",
                                                           "message_count: 119")
    (bag / "metadata.yaml").write_text(meta)
    from mcap.reader import make_reader

    with open(mcap, "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    chunks = summary.chunk_indexes
    assert len(chunks) > 4
    bad = chunks[len(chunks) // 2]
    data = bytearray(mcap.read_bytes())
    middle = bad.chunk_start_offset + bad.chunk_length // 2
    data[middle:middle + 64] = bytes(64)  # inside one chunk: its CRC no longer matches
    mcap.write_bytes(bytes(data))
    report = replay(bag)
    assert report.exit_code == EXIT_OK, report.text
    used = report.topics["/edges"].used
    assert 20 < used < 119
    assert any("Chunk checksum mismatch" in p for p in report.problems), report.text
    assert len(report.final.node_ids) == used + 1


def test_unknown_types_and_malformed_messages_are_skipped(tmp_path: Path) -> None:
    gt = ground_truth(6, seed=9)
    records = chain_records(gt)
    custom = "my_pkg/msg/Weird"
    records.append(("/weird", T0 + 50 * MS, custom, b"\x00\x01\x00\x00\x05\x00\x00\x00"))
    records.append(("/noschema", T0 + 51 * MS, "other_pkg/msg/Thing", b"\x00\x01\x00\x00"))
    # malformed: a TransformStamped whose CDR stops short, and garbage bytes
    good = records[0][3]
    records.append(("/edges", T0 + 60 * MS, TRANSFORM_STAMPED, good[:20]))
    records.append(("/edges", T0 + 61 * MS, TRANSFORM_STAMPED, b"\xff" * 7))
    records.sort(key=lambda r: r[1])
    path = write_mcap(tmp_path / "odd.mcap", records,
                      schemas={custom: "int32 value\n", "other_pkg/msg/Thing": ""})
    report = replay(path, edge_topics=["/edges", "/weird"])
    assert report.exit_code == EXIT_OK, report.text
    edges = report.topics["/edges"]
    assert edges.used == 5 and edges.rejected["undecodable_message"] == 2
    assert report.topics["/weird"].role == "ignored"
    assert any("/weird: type my_pkg/msg/Weird cannot carry edges" in p
               for p in report.problems)
    assert "/noschema" in report.text
    assert "undecodable_message 2" in report.text
    assert aligned_errors_deg(report.final_orientations, gt).max() < 1e-4


def test_unreadable_inputs(tmp_path: Path) -> None:
    not_a_bag = tmp_path / "notes.mcap"
    not_a_bag.write_text("hello, not an mcap file\n" * 10)
    with pytest.raises(InputError, match="notes.mcap"):
        replay(not_a_bag)
    empty_dir = tmp_path / "empty"
    empty_dir.mkdir()
    with pytest.raises(InputError, match="no .mcap file"):
        replay(empty_dir)
    # a bag without a single usable message: truncated inside its only chunk
    gt = ground_truth(5, seed=10)
    bag = write_bag(tmp_path / "bag", chain_messages(gt, [0.1, 0.2, 0.3, 0.4]))
    mcap = next(bag.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:300])
    report = replay(bag)
    assert report.exit_code == EXIT_NOTHING_USABLE
    assert report.problems and "solves: 0" in report.text


# ---------------------------------------------------------------------- recorded by rclpy
def test_lone_mcap_recorded_with_rclpy_serialization(tmp_path: Path) -> None:
    """Messages built and serialised by rclpy (as ``ros2 bag record`` stores them), written
    with the mcap writer into a lone .mcap, replay like the rosbags-written bag."""
    from geometry_msgs.msg import TransformStamped
    from nav_msgs.msg import Odometry
    from rclpy.serialization import serialize_message

    gt = ground_truth(8, seed=11)
    names = list(gt)
    records = []
    for k in range(len(names) - 1):
        i, j = names[k], names[k + 1]
        q = matrix_to_quat(gt[i] @ gt[j].T)
        t = T0 + k * 10 * MS
        if k % 2:
            msg = TransformStamped()
            msg.header.frame_id, msg.child_frame_id = i, j
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t, 1_000_000_000)
            r = msg.transform.rotation
            r.x, r.y, r.z, r.w = (float(v) for v in q)
            records.append(("/edges", t, TRANSFORM_STAMPED, serialize_message(msg)))
        else:
            msg = Odometry()
            msg.header.frame_id, msg.child_frame_id = i, j
            o = msg.pose.pose.orientation
            o.x, o.y, o.z, o.w = (float(v) for v in q)
            cov = np.zeros(36)
            cov[[21, 28, 35]] = 1e-4
            msg.pose.covariance = cov
            records.append(("/odom", t, ODOMETRY, serialize_message(msg)))
    for k, name in enumerate(names):
        msg = TransformStamped()
        msg.header.frame_id, msg.child_frame_id = "world", name
        r = msg.transform.rotation
        r.x, r.y, r.z, r.w = (float(v) for v in matrix_to_quat(gt[name].T))
        records.append(("/ground_truth", T0 + 500 * MS + k, TRANSFORM_STAMPED,
                        serialize_message(msg)))
    path = write_mcap(tmp_path / "recorded.mcap", records, chunk_size=1 << 20)
    report = replay(path)
    assert report.exit_code == EXIT_OK and report.reader == "rosbags"
    assert report.topics["/edges"].used == 3 and report.topics["/odom"].used == 4
    assert report.final_errors is not None and report.final_errors.max_deg < 1e-4
    assert math.isclose(report.final_errors.num_nodes, 8)


# ---------------------------------------------------------------------- committed bag
@pytest.mark.skipif(not (REPO / "bags/ellis_island/metadata.yaml").is_file(),
                    reason="bags/ellis_island not generated (scripts/make_sample_bags.py)")
def test_committed_ellis_island_bag(capsys: pytest.CaptureFixture[str]) -> None:
    """Paper protocol through the bag: 227 cameras, 20,010 edges; depth 2 and 500 iterations
    give mean 2.63 deg / median 0.41 deg (the full default: 2.22 / 0.40)."""
    code = cli.main(["replay", str(REPO / "bags/ellis_island"), "--depths", "2",
                     "--iterations", "500", "--quiet"])
    text = capsys.readouterr().out
    assert code == EXIT_OK, text
    assert "/edges" in text and " 20010 " in text
    line = next(x for x in text.splitlines() if "accuracy vs ground truth" in x)
    assert "(227 nodes)" in line
    mean = float(line.split("mean ")[1].split(" deg")[0])
    median = float(line.split("median ")[1].split(" deg")[0])
    assert mean < 3.5 and median < 0.6, line


# ---------------------------------------------------------------------- equals the node
def test_replay_equals_the_live_node(tmp_path: Path) -> None:
    """The node fed the bag's messages over DDS and ``replay --solve-once`` give the same
    orientations (same seed, same parameters) to 1e-6, and the same counters."""
    from geometry_msgs.msg import TransformStamped
    from nav_msgs.msg import Odometry
    from rclpy.parameter import Parameter
    from rclpy.serialization import deserialize_message
    from ros_fixtures import EdgeClient

    from rotavg_ros.io.bag_reader import open_bag
    from rotavg_ros.ros.node import RotavgNode

    gt = ground_truth(16, seed=12)
    msgs = mixed_bag_messages(gt, seed=13, noise_deg=2.0, outliers=0.1, tf_message=False)
    msgs.append(("/edges", T0 + 5 * MS, transform("z", "z", np.eye(3), T0 + 5 * MS)))
    bag = write_bag(tmp_path / "in", msgs + gt_messages(gt))
    # dense mode: its random start makes the result depend on the seed (a seed change moves
    # rotations by ~0.04), so equality to 1e-6 really checks that both ran the same solve
    params = {"seed": 5, "depths": [2], "iterations": 200, "mode": "dense"}

    report = replay(bag, solve_fn=None, params=params, output=tmp_path / "out")
    assert report.exit_code == EXIT_OK and report.final is not None

    overrides = [Parameter("solve_period", value=3600.0)] + [
        Parameter(k, value=v) for k, v in params.items()]
    with RosHarness() as h:
        node = h.add(RotavgNode(solve_fn=default_solve, context=h.context,
                                namespace=h.namespace, parameter_overrides=overrides))
        client = h.add(EdgeClient(node.get_fully_qualified_name(), context=h.context,
                                  namespace=h.namespace))
        h.start()
        assert client.wait_connected(15.0)
        node_settings = getattr(node, "_settings", None)
        if node_settings is not None:
            assert node_settings.solver == settings_from_parameters(params).solver
        sent = 0
        with open_bag(bag) as source:
            for rec in source.read(["/edges", "/odom"]):
                if rec.topic == "/edges":
                    client.pub_tf.publish(deserialize_message(rec.data, TransformStamped))
                else:
                    client.pub_odom.publish(deserialize_message(rec.data, Odometry))
                sent += 1
                # one at a time: across two topics DDS/the executor may reorder messages, and
                # the arrival order sets the anchor and breaks the node order's ties
                assert wait_until(
                    lambda n=sent: node.accumulator.stats().received >= n, 15.0)  # type: ignore[misc]
        response = client.solve(timeout=120.0)
        assert response.success, response.message
        assert wait_until(lambda: len(client.latest_orientations()) == 16, 10.0)
        live = client.latest_orientations()
        stats = node.accumulator.stats()
        assert wait_until(lambda: (d := client.latest_diagnostics()) is not None
                          and d[2].get("solves_completed") == "1", 10.0)
        live_level, live_message, live_values = client.latest_diagnostics()  # type: ignore[misc]

    replayed = {str(k): R for k, R in report.final_orientations.items()}
    assert set(live) == set(replayed)
    for name in live:
        np.testing.assert_allclose(live[name], replayed[name], atol=1e-6, err_msg=name)
    assert stats.accepted == sum(t.used for t in report.topics.values() if t.role == "edges")
    assert dict(stats.rejected)["self_loop"] == 1
    # the output bag holds the same diagnostics (but for timing) and orientations
    out = read_bag(tmp_path / "out")
    (_, diag), = out["/diagnostics"]
    status = diag.status[0]
    values = {kv.key: kv.value for kv in status.values}
    for timing in ("last_solve_duration_s",):
        values.pop(timing), live_values.pop(timing)
    assert values == live_values
    assert (status.level, status.message) == (live_level, live_message)
    written = out["/rotavg_node/orientations"]
    for _, m in written:
        r = m.transform.rotation
        np.testing.assert_allclose(quat_to_matrix([r.x, r.y, r.z, r.w]).T,
                                   live[m.child_frame_id], atol=1e-6)
