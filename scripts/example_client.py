"""Example client of ``rotavg_node``: send a graph, ask for a solve, print the result.

Publishes the relative rotations of a small graph on the node's ``~/edges`` topic
(``geometry_msgs/msg/TransformStamped``, ``header.frame_id = i``, ``child_frame_id = j``,
rotation ``R_ij``), waits until the node's ``/diagnostics`` count them, calls ``~/solve``
(``std_srvs/srv/Trigger``) and prints the orientations it publishes on ``~/orientations``
(node-to-world quaternions x y z w) and its diagnostics. Exit status 0 when the solve
succeeded.

    rotavg_node &                                         # in another terminal
    .venv/bin/python scripts/example_client.py            # built-in graph: 12 nodes
    .venv/bin/python scripts/example_client.py graph.g2o  # the EDGE_SE3:QUAT lines of a file
    .venv/bin/python scripts/example_client.py --node /robot/rotavg_node
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger

from rotavg_ros.core.so3 import matrix_to_quat, random_rotations, rotation_about_axis
from rotavg_ros.io.g2o import read_g2o

Edge = tuple[str, str, np.ndarray]


def synthetic_graph(n: int, seed: int = 0) -> list[Edge]:
    """A ring of ``n`` frames ``cam_<k>`` with chords to the frame after next, 1 deg noise."""
    rng = np.random.default_rng(seed)
    R = random_rotations(n, rng)
    edges = []
    for k in range(n):
        for step in (1, 2):
            a, b = k, (k + step) % n
            noise = rotation_about_axis(rng.normal(size=3), np.radians(rng.normal(0.0, 1.0)))
            edges.append((f"cam_{a}", f"cam_{b}", noise @ R[a] @ R[b].T))
    return edges


def g2o_graph(path: Path) -> list[Edge]:
    """The ``EDGE_SE3:QUAT`` rotations of a g2o file; frame ids are the vertex ids."""
    graph = read_g2o(path).graph
    i, j, R, _ = graph.measurement_arrays()
    ids = [str(v) for v in graph.node_ids]
    return [(ids[a], ids[b], Rk) for a, b, Rk in zip(i, j, R, strict=True)]


class ExampleClient(Node):
    """Publisher for the edges, ``~/solve`` client, orientation and diagnostics listeners."""

    def __init__(self, target: str, depth: int) -> None:
        super().__init__("rotavg_example_client")
        self.target = target
        self.edges_pub = self.create_publisher(TransformStamped, f"{target}/edges", QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=depth,
            reliability=ReliabilityPolicy.RELIABLE))
        self.solve_client = self.create_client(Trigger, f"{target}/solve")
        self.orientations: dict[str, TransformStamped] = {}
        self.create_subscription(
            TransformStamped, f"{target}/orientations", self._on_orientation, QoSProfile(
                history=HistoryPolicy.KEEP_LAST, depth=max(depth, 1000),
                reliability=ReliabilityPolicy.RELIABLE,
                durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.status: dict[str, str] = {}
        self.level = -1
        self.message = ""
        self.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)

    def _on_orientation(self, msg: TransformStamped) -> None:
        self.orientations[msg.child_frame_id] = msg  # the newest per frame

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.hardware_id == self.target:
                self.level = status.level[0] if isinstance(status.level, bytes) else \
                    int(status.level)
                self.message = status.message
                self.status = {kv.key: kv.value for kv in status.values}

    def spin_until(self, done: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not done():
            if time.monotonic() > deadline:
                raise TimeoutError(f"timed out after {timeout:g} s waiting for {what}")
            rclpy.spin_once(self, timeout_sec=0.05)

    def send(self, edges: list[Edge]) -> None:
        for i, j, R in edges:
            msg = TransformStamped()
            msg.header.stamp = self.get_clock().now().to_msg()
            msg.header.frame_id = i
            msg.child_frame_id = j
            r = msg.transform.rotation
            r.x, r.y, r.z, r.w = (float(v) for v in matrix_to_quat(R))
            self.edges_pub.publish(msg)


def run(args: argparse.Namespace) -> int:
    edges = g2o_graph(args.graph) if args.graph else synthetic_graph(args.nodes, args.seed)
    frames = list(dict.fromkeys(f for e in edges for f in e[:2]))  # in order of appearance
    client = ExampleClient(args.node, depth=len(edges))
    t = args.timeout
    # Edges published before the node's subscription has matched are lost: wait for it.
    client.spin_until(lambda: client.edges_pub.get_subscription_count() > 0, t,
                      f"{args.node}/edges to match (is rotavg_node running?)")
    client.spin_until(client.solve_client.service_is_ready, t, f"{args.node}/solve")
    client.spin_until(lambda: bool(client.status), t, "the node's /diagnostics")
    before = int(client.status["edges_received"])
    client.send(edges)
    print(f"sent {len(edges)} edges between {len(frames)} frames to {args.node}/edges")
    # Topics and services are not ordered: ask for the solve once the node has the edges.
    client.spin_until(lambda: int(client.status["edges_received"]) >= before + len(edges), t,
                      "the node to receive the edges")
    future = client.solve_client.call_async(Trigger.Request())
    client.spin_until(future.done, t, "the ~/solve answer")
    answer = future.result()
    assert answer is not None
    print(f"~/solve: success={answer.success} ({answer.message})")
    if answer.success:
        client.spin_until(lambda: set(frames) <= set(client.orientations), t,
                          "the orientations")
        print("orientations (node-to-world quaternion x y z w):")
        for frame in frames:
            r = client.orientations[frame].transform.rotation
            print(f"  {frame}: {r.x:+.6f} {r.y:+.6f} {r.z:+.6f} {r.w:+.6f}")
    levels = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}
    print(f"diagnostics: {levels.get(client.level, client.level)}: {client.message}")
    for key in ("edges_received", "edges_accepted", "edges_rejected", "solved_nodes",
                "filtered_outliers", "depth", "residual_median_deg", "last_solve_duration_s"):
        if key in client.status:
            print(f"  {key}: {client.status[key]}")
    client.destroy_node()
    return 0 if answer.success else 1


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("graph", nargs="?", type=Path, help="g2o file (default: a synthetic graph)")
    p.add_argument("--node", default="/rotavg_node",
                   help="fully qualified name of the node (default /rotavg_node)")
    p.add_argument("--nodes", type=int, default=12, help="frames of the synthetic graph")
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic graph")
    p.add_argument("--timeout", type=float, default=30.0, help="seconds per wait")
    args = p.parse_args(argv)
    rclpy.init()
    try:
        return run(args)
    except TimeoutError as exc:
        print(f"example_client: {exc}", file=sys.stderr)
        return 1
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
