"""Write the sample rosbag2 MCAP bags in ``bags/`` (reproducible: fixed seeds and stamps).

Bags (rosbag2 version 9, MCAP storage with zstd-compressed chunks, Jazzy message types,
written with rosbags, no ROS needed):

``bags/ellis_island/``
    1DSfM Ellis Island, the paper's protocol (227 cameras with ground truth, 20,010 edges):
    ``/edges`` ``geometry_msgs/msg/TransformStamped`` with ``header.frame_id = cam_<i>``,
    ``child_frame_id = cam_<j>`` and rotation ``R_ij = R_i R_j^T`` (the dataset's relative
    rotation), one every 2 ms over 40 s in the dataset's order; ``/ground_truth``
    TransformStamped ``world -> cam_<i>`` with the node-to-world rotation ``R_i^T``, all at
    the start.
``bags/smallgrid3d_odom/``
    SE-Sync smallGrid3D (125 poses, 297 edges) as ``nav_msgs/msg/Odometry`` on ``/odom_edges``
    (``pose_<i> -> pose_<j>``, the g2o edge's relative pose; the covariance is block
    diagonal: each 3x3 block is the inverse of the g2o information block), over 30 s;
    ``/ground_truth`` holds the certified-optimal rotations (``shared/reference``).
``bags/slam_false_loops/``
    Synthetic SLAM run, seed 7: 300 keyframes ``kf_<k>`` at 5 Hz (60 s) driving three laps
    of a 30 m x 20 m loop with rounded corners and small pitch/roll wobble. Odometry
    ``k-1 -> k`` (0.3 deg per-axis noise) and short loops ``k-2 -> k`` (every keyframe),
    ``k-3 -> k`` (every other one, 0.4 deg) on ``/edges`` (TransformStamped); revisit loop
    closures (keyframes at least 20 back within 1.5 m, up to two per keyframe on every other
    keyframe, 0.6 deg) and false loop closures (15 % of all non-odometry edges, a random
    earlier keyframe and a uniformly random rotation) on ``/tf_edges``
    (``tf2_msgs/msg/TFMessage``, one message per keyframe with all its closures);
    ``/ground_truth`` ``world -> kf_<k>`` at each keyframe's time.

Every message's log time equals its header stamp (from 1,700,000,000 s, strictly
increasing). Reads ``../shared`` (or ``$ROTAVG_SHARED``) through
``benchmarks.datasets.find_shared_dir``; bags needing it are skipped with a message when it
is absent. Usage::

    python scripts/make_sample_bags.py            # all three, replacing existing ones
    python scripts/make_sample_bags.py --only slam_false_loops
"""

from __future__ import annotations

import argparse
import shutil
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer  # noqa: E402

from benchmarks.datasets import find_shared_dir, load_ellis_island, load_se_sync  # noqa: E402
from rotavg_ros.core.so3 import matrix_to_quat, quat_to_matrix, rotation_about_axis  # noqa: E402
from rotavg_ros.io.bag_messages import TF_MESSAGE, TRANSFORM_STAMPED, MessageFactory  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
BAGS = REPO / "bags"
T0_NS = 1_700_000_000 * 1_000_000_000
ODOMETRY = "nav_msgs/msg/Odometry"
MS = 1_000_000

Message = tuple[str, int, Any]  # topic, log time (ns), rosbags message


# ---------------------------------------------------------------------- writing
def write_bag(path: Path, topics: dict[str, str], messages: Iterable[Message],
              factory: MessageFactory) -> int:
    """Write ``messages`` (already in time order) to a new bag at ``path``; returns bytes."""
    if path.exists():
        if not (path / "metadata.yaml").is_file():
            raise SystemExit(f"{path} exists and is not a rosbag2 bag; not replacing it")
        shutil.rmtree(path)
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    last = -1
    with writer:
        conns = {t: writer.add_connection(t, typ, typestore=factory.typestore)
                 for t, typ in topics.items()}
        for topic, t_ns, msg in messages:
            if t_ns <= last:
                raise AssertionError("log times must increase")
            last = t_ns
            writer.write(conns[topic], t_ns, factory.serialize(msg))
    return sum(f.stat().st_size for f in path.iterdir())


def transform(f: MessageFactory, parent: str, child: str, R: np.ndarray, t_ns: int,
              translation: np.ndarray | None = None) -> Any:
    msg = f.transform(parent, child, matrix_to_quat(R).tolist(), t_ns)
    if translation is not None:
        x, y, z = (float(v) for v in translation)
        msg.transform.translation = f.new("geometry_msgs/msg/Vector3", x=x, y=y, z=z)
    return msg


def ground_truth(f: MessageFactory, frames: dict[str, np.ndarray], t_ns: int,
                 step_ns: int) -> list[Message]:
    """``world -> frame`` with the node-to-world rotation ``R^T`` of world-to-node ``R``."""
    return [("/ground_truth", t_ns + k * step_ns, transform(f, "world", name, R.T,
                                                            t_ns + k * step_ns))
            for k, (name, R) in enumerate(frames.items())]


# ---------------------------------------------------------------------- (a) Ellis Island
def ellis_island(shared: Path, f: MessageFactory) -> tuple[dict[str, str], list[Message]]:
    bench = load_ellis_island(shared)
    g = bench.graph
    ids = g.node_ids
    i, j, R, _ = g.measurement_arrays()
    gt = {f"cam_{n}": bench.reference[n] for n in ids}
    msgs = ground_truth(f, gt, T0_NS, 10_000)
    start = T0_NS + 10 * MS
    step = 2 * MS  # 20,010 edges over 40 s
    for k in range(len(i)):
        t = start + k * step
        msgs.append(("/edges", t, transform(f, f"cam_{ids[i[k]]}", f"cam_{ids[j[k]]}", R[k], t)))
    return {"/ground_truth": TRANSFORM_STAMPED, "/edges": TRANSFORM_STAMPED}, msgs


# ---------------------------------------------------------------------- (b) smallGrid3D
def _g2o_edges(path: Path) -> list[tuple[int, int, np.ndarray, np.ndarray, np.ndarray]]:
    """``(i, j, translation, quaternion xyzw, 6x6 information)`` of every EDGE_SE3:QUAT."""
    edges = []
    for line in path.read_text().splitlines():
        tok = line.split()
        if not tok or tok[0] != "EDGE_SE3:QUAT":
            continue
        vals = np.array([float(v) for v in tok[3:]])
        info = np.zeros((6, 6))
        info[np.triu_indices(6)] = vals[7:28]
        info = info + np.triu(info, 1).T
        edges.append((int(tok[1]), int(tok[2]), vals[0:3], vals[3:7], info))
    return edges


def smallgrid3d(shared: Path, f: MessageFactory) -> tuple[dict[str, str], list[Message]]:
    bench = load_se_sync(shared, "smallGrid3D")
    edges = _g2o_edges(shared / "data/se_sync_3d/smallGrid3D.g2o")
    gt = {f"pose_{n}": R for n, R in sorted(bench.reference.items())}
    msgs = ground_truth(f, gt, T0_NS, 10_000)
    start = T0_NS + 10 * MS
    step = 100 * MS  # 297 edges over ~30 s
    for k, (a, b, trans, quat, info) in enumerate(edges):
        t = start + k * step
        cov = np.zeros((6, 6))
        cov[:3, :3] = np.linalg.inv(info[:3, :3])
        cov[3:, 3:] = np.linalg.inv(info[3:, 3:])  # rotation block = inverse information
        q = quat / np.linalg.norm(quat)
        msg = f.new(
            ODOMETRY,
            header=f.header(f"pose_{a}", t),
            child_frame_id=f"pose_{b}",
            pose=f.new(
                "geometry_msgs/msg/PoseWithCovariance",
                pose=f.new(
                    "geometry_msgs/msg/Pose",
                    position=f.new("geometry_msgs/msg/Point", x=float(trans[0]),
                                   y=float(trans[1]), z=float(trans[2])),
                    orientation=f.new("geometry_msgs/msg/Quaternion", x=float(q[0]),
                                      y=float(q[1]), z=float(q[2]), w=float(q[3])),
                ),
                covariance=cov.reshape(-1).astype(np.float64),
            ),
        )
        msgs.append(("/odom_edges", t, msg))
    return {"/ground_truth": TRANSFORM_STAMPED, "/odom_edges": ODOMETRY}, msgs


# ---------------------------------------------------------------------- (c) synthetic SLAM
def _rz(a: float) -> np.ndarray:
    return rotation_about_axis([0.0, 0.0, 1.0], a)


def _noisy(R: np.ndarray, sigma_deg: float, rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(scale=np.radians(sigma_deg), size=3)
    angle = float(np.linalg.norm(v))
    return (rotation_about_axis(v, angle) if angle > 0 else np.eye(3)) @ R


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return quat_to_matrix(q / np.linalg.norm(q))


def slam_trajectory(n: int = 300, rng: np.random.Generator | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Positions ``(n, 3)`` and body-to-world rotations ``(n, 3, 3)``: 3 laps, 1 m steps."""
    rng = rng if rng is not None else np.random.default_rng(7)
    width, height, radius = 30.0, 20.0, 4.0
    straight_x, straight_y = width - 2 * radius, height - 2 * radius
    arc = np.pi * radius / 2
    perimeter = 2 * (straight_x + straight_y) + 4 * arc
    segments = [("line", straight_x), ("arc", arc), ("line", straight_y), ("arc", arc)] * 2
    pos = np.zeros((n, 3))
    rot = np.zeros((n, 3, 3))
    for k in range(n):
        s = (k * perimeter * 3.0 / n) % perimeter  # 3 laps
        x, y, yaw = radius, 0.0, 0.0
        for kind, length in segments:
            step = min(s, length)
            if kind == "line":
                x, y = x + step * np.cos(yaw), y + step * np.sin(yaw)
            else:
                cx, cy = x - radius * np.sin(yaw), y + radius * np.cos(yaw)
                yaw2 = yaw + step / radius
                x, y = cx + radius * np.sin(yaw2), cy - radius * np.cos(yaw2)
                yaw = yaw2
            s -= step
            if s <= 0:
                break
        lap = k * 3 // n
        x += 0.3 * lap * np.sin(0.7 * k)  # the laps do not overlap exactly
        pitch = np.radians(3.0) * np.sin(0.21 * k) + np.radians(0.5) * rng.normal()
        roll = np.radians(2.0) * np.sin(0.13 * k + 1.0) + np.radians(0.5) * rng.normal()
        pos[k] = (x, y, 0.5 * np.sin(0.05 * k))
        rot[k] = (_rz(yaw) @ rotation_about_axis([0.0, 1.0, 0.0], pitch)
                  @ rotation_about_axis([1.0, 0.0, 0.0], roll))
    return pos, rot


def slam_false_loops(f: MessageFactory, seed: int = 7, false_fraction: float = 0.15
                     ) -> tuple[dict[str, str], list[Message], dict[str, int]]:
    """The synthetic SLAM bag; ``false_fraction`` of the non-odometry edges are false."""
    rng = np.random.default_rng(seed)
    n = 300
    pos, body = slam_trajectory(n, rng)
    R = np.swapaxes(body, 1, 2)  # world-to-node
    name = [f"kf_{k}" for k in range(n)]

    def rel(a: int, b: int) -> np.ndarray:
        return R[a] @ R[b].T

    def rel_t(a: int, b: int) -> np.ndarray:
        return body[a].T @ (pos[b] - pos[a])

    msgs: list[Message] = []
    counts = {"odometry": 0, "short_loops": 0, "revisits": 0, "false_loops": 0}
    closures: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(n)]
    short: list[list[int]] = [[] for _ in range(n)]
    for k in range(n):
        if k >= 2:
            short[k].append(k - 2)
        if k >= 3 and k % 2 == 0:
            short[k].append(k - 3)
        if k % 2 == 0:
            d = np.linalg.norm(pos[: max(0, k - 19)] - pos[k], axis=1)
            for m in np.argsort(d)[:2]:
                if d[m] < 1.5:
                    closures[k].append((int(m), _noisy(rel(int(m), k), 0.6, rng)))
    num_true = sum(len(s) for s in short) + sum(len(c) for c in closures)
    num_false = int(round(false_fraction / (1.0 - false_fraction) * num_true))
    for _ in range(num_false):
        k = int(rng.integers(20, n))
        m = int(rng.integers(0, k - 10))
        closures[k].append((m, _random_rotation(rng)))
        counts["false_loops"] += 1
    counts["revisits"] = sum(len(c) for c in closures) - counts["false_loops"]
    counts["short_loops"] = sum(len(s) for s in short)

    period = 200 * MS  # 5 Hz keyframes
    for k in range(n):
        t = T0_NS + k * period
        msgs.append(("/ground_truth", t, transform(f, "world", name[k], body[k], t,
                                                    translation=pos[k])))
        t += MS
        if k >= 1:
            msgs.append(("/edges", t, transform(f, name[k - 1], name[k],
                                                _noisy(rel(k - 1, k), 0.3, rng), t,
                                                translation=rel_t(k - 1, k))))
            counts["odometry"] += 1
            t += MS
        for m in short[k]:
            msgs.append(("/edges", t, transform(f, name[m], name[k], _noisy(rel(m, k), 0.4, rng),
                                                t, translation=rel_t(m, k))))
            t += MS
        if closures[k]:
            tfs = [transform(f, name[m], name[k], Rmk, t) for m, Rmk in closures[k]]
            msgs.append(("/tf_edges", t, f.tf_message(tfs)))
    topics = {"/ground_truth": TRANSFORM_STAMPED, "/edges": TRANSFORM_STAMPED,
              "/tf_edges": TF_MESSAGE}
    return topics, msgs, counts


# ---------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", nargs="+", choices=("ellis_island", "smallgrid3d_odom",
                                                      "slam_false_loops"))
    parser.add_argument("--out", type=Path, default=BAGS, help="folder (default bags/)")
    args = parser.parse_args(argv)
    wanted = set(args.only or ("ellis_island", "smallgrid3d_odom", "slam_false_loops"))
    factory = MessageFactory()
    shared = find_shared_dir()
    args.out.mkdir(parents=True, exist_ok=True)
    jobs: list[tuple[str, Callable[[], tuple[dict[str, str], list[Message]]]]] = []
    if shared is None:
        for bag in sorted(wanted & {"ellis_island", "smallgrid3d_odom"}):
            print(f"skipping {bag}: shared benchmark data not found (expected ../shared next "
                  "to the repository or a folder in $ROTAVG_SHARED containing data/)")
    else:
        if "ellis_island" in wanted:
            jobs.append(("ellis_island", lambda: ellis_island(shared, factory)))
        if "smallgrid3d_odom" in wanted:
            jobs.append(("smallgrid3d_odom", lambda: smallgrid3d(shared, factory)))
    if "slam_false_loops" in wanted:
        def slam() -> tuple[dict[str, str], list[Message]]:
            topics, msgs, counts = slam_false_loops(factory)
            print("  slam_false_loops edges: " + ", ".join(f"{k} {v}" for k, v in counts.items()))
            return topics, msgs
        jobs.append(("slam_false_loops", slam))
    total = 0
    for name, make in jobs:
        topics, msgs = make()
        size = write_bag(args.out / name, topics, msgs, factory)
        total += size
        per_topic = {t: sum(1 for m in msgs if m[0] == t) for t in topics}
        print(f"{args.out / name}: {size / 1e6:.2f} MB, {len(msgs)} messages ("
              + ", ".join(f"{t} {c}" for t, c in per_topic.items()) + ")")
    print(f"total {total / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
