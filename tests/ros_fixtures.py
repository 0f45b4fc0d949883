"""Launch-free rclpy test helpers (imported by test modules; not a conftest).

* Importing this module sets ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (no multicast leaves
  the machine) and a ``ROS_DOMAIN_ID`` unique to this pytest(-xdist) worker process, derived
  from ``PYTEST_XDIST_WORKER`` and the pid; subprocesses inherit both.
* :class:`RosHarness`: one ``Context`` per test (``rclpy.init(context=..., domain_id=...)``),
  an executor spun in a background thread with a stop flag (never ``executor.shutdown()``
  from another thread while it spins), and a unique namespace per test so that even two
  processes that happen to share a domain do not cross-talk.
* :class:`EdgeClient`: the "other side" of ``rotavg_node``: publishers for both edge topics,
  collectors for orientations / markers / diagnostics, and ``~/solve`` / ``~/reset`` clients.
* :func:`spanning_tree_solve`: a tiny exact solver (BFS composition over consolidated edges)
  with the ``SolveFn`` signature, for tests that exercise the node rather than the solver.
"""

from __future__ import annotations

import itertools
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Hashable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"


def worker_domain_id() -> int:
    """A ROS domain id in 1..100 for this worker process (PYTEST_XDIST_WORKER + pid)."""
    match = re.search(r"(\d+)$", os.environ.get("PYTEST_XDIST_WORKER", ""))
    worker = int(match.group(1)) if match else 0
    return 1 + (os.getpid() * 7 + worker * 13) % 100


DOMAIN_ID = worker_domain_id()
os.environ["ROS_DOMAIN_ID"] = str(DOMAIN_ID)

import rclpy  # noqa: E402 - after the environment is set
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import TransformStamped  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import Executor, SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

from rotavg_ros.core.options import SolverOptions  # noqa: E402
from rotavg_ros.core.result import SolveResult  # noqa: E402
from rotavg_ros.core.so3 import (  # noqa: E402
    geodesic_distance,
    matrix_to_quat,
    project_to_so3,
    quat_to_matrix,
)
from rotavg_ros.core.view_graph import ViewGraph  # noqa: E402

_NS_COUNTER = itertools.count()


def unique_namespace() -> str:
    return f"/t{os.getpid()}_{next(_NS_COUNTER)}"


def wait_until(
    predicate: Callable[[], bool], timeout: float = 10.0, interval: float = 0.01
) -> bool:
    """Poll ``predicate`` until it is true (returns True) or ``timeout`` s pass (False)."""
    deadline = time.monotonic() + timeout
    while True:
        if predicate():
            return True
        if time.monotonic() > deadline:
            return False
        time.sleep(interval)


class RosHarness:
    """A Context, an executor spinning in a background thread, and the nodes on it."""

    def __init__(
        self,
        executor_factory: Callable[..., Executor] = SingleThreadedExecutor,
        args: Sequence[str] | None = None,
    ) -> None:
        self.context = Context()
        rclpy.init(args=list(args) if args is not None else None, context=self.context,
                   domain_id=DOMAIN_ID)
        self.executor = executor_factory(context=self.context)
        self.namespace = unique_namespace()
        self._nodes: list[Node] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def add(self, node: Node) -> Any:
        self._nodes.append(node)
        self.executor.add_node(node)
        return node

    def start(self) -> None:
        self._thread = threading.Thread(target=self._spin, name="ros_spin", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
        for node in reversed(self._nodes):
            self.executor.remove_node(node)
            node.destroy_node()
        self.executor.shutdown(timeout_sec=1.0)
        self.context.try_shutdown()

    def __enter__(self) -> RosHarness:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@pytest.fixture
def ros() -> Iterator[RosHarness]:
    """A started-later :class:`RosHarness` on a SingleThreadedExecutor."""
    harness = RosHarness()
    try:
        yield harness
    finally:
        harness.close()


RELIABLE_DEEP = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=10000, reliability=ReliabilityPolicy.RELIABLE
)


class EdgeClient(Node):
    """Publishes edges to a ``rotavg_node`` and records everything it publishes."""

    def __init__(self, target: str, *, context: Context, namespace: str = "") -> None:
        """``target`` is the fully qualified name of the node under test, e.g. ``/ns/rotavg``."""
        super().__init__("edge_client", namespace=namespace, context=context)
        self.target = target
        self.lock = threading.Lock()
        self.orientations: list[TransformStamped] = []
        self.markers: list[MarkerArray] = []
        self.diagnostics: list[DiagnosticArray] = []
        self.pub_tf = self.create_publisher(TransformStamped, f"{target}/edges", RELIABLE_DEEP)
        self.pub_odom = self.create_publisher(
            Odometry, f"{target}/edges_with_covariance", RELIABLE_DEEP
        )
        self.create_subscription(
            TransformStamped, f"{target}/orientations", self._keep(self.orientations),
            RELIABLE_DEEP,
        )
        self.create_subscription(MarkerArray, f"{target}/markers", self._keep(self.markers), 10)
        self.create_subscription(
            DiagnosticArray, "/diagnostics", self._keep(self.diagnostics), 100
        )
        self.solve_client = self.create_client(Trigger, f"{target}/solve")
        self.reset_client = self.create_client(Trigger, f"{target}/reset")

    def _keep(self, store: list[Any]) -> Callable[[Any], None]:
        def callback(msg: Any) -> None:
            with self.lock:
                store.append(msg)
        return callback

    # ------------------------------------------------------------------ setup
    def wait_connected(self, timeout: float = 10.0) -> bool:
        """Both edge topics matched, all outputs matched and both services available."""
        return wait_until(
            lambda: self.pub_tf.get_subscription_count() > 0
            and self.pub_odom.get_subscription_count() > 0
            and all(s.get_publisher_count() > 0 for s in self.subscriptions)
            and self.solve_client.service_is_ready()
            and self.reset_client.service_is_ready(),
            timeout,
        )

    # ------------------------------------------------------------------ inputs
    def send_transform(
        self, frame_i: str, frame_j: str, q: Iterable[float], stamp_sec: int = 0
    ) -> None:
        msg = TransformStamped()
        msg.header.frame_id = frame_i
        msg.header.stamp.sec = stamp_sec
        msg.child_frame_id = frame_j
        r = msg.transform.rotation
        r.x, r.y, r.z, r.w = (float(v) for v in q)
        self.pub_tf.publish(msg)

    def send_odometry(
        self, frame_i: str, frame_j: str, q: Iterable[float], rot_variance: float = 0.0
    ) -> None:
        msg = Odometry()
        msg.header.frame_id = frame_i
        msg.child_frame_id = frame_j
        o = msg.pose.pose.orientation
        o.x, o.y, o.z, o.w = (float(v) for v in q)
        cov = np.zeros((6, 6))
        cov[3, 3] = cov[4, 4] = cov[5, 5] = rot_variance
        msg.pose.covariance = cov.reshape(-1)
        self.pub_odom.publish(msg)

    def send_edge(self, frame_i: str, frame_j: str, R_ij: np.ndarray, odometry: bool = False,
                  rot_variance: float = 0.0) -> None:
        q = matrix_to_quat(R_ij)
        if odometry:
            self.send_odometry(frame_i, frame_j, q, rot_variance)
        else:
            self.send_transform(frame_i, frame_j, q)

    # ------------------------------------------------------------------ services
    def call(self, client: Any, timeout: float = 30.0) -> Trigger.Response:
        future = client.call_async(Trigger.Request())
        if not wait_until(future.done, timeout):
            raise TimeoutError(f"no answer from {client.srv_name} within {timeout} s")
        return future.result()

    def solve(self, timeout: float = 30.0) -> Trigger.Response:
        return self.call(self.solve_client, timeout)

    def reset(self, timeout: float = 10.0) -> Trigger.Response:
        return self.call(self.reset_client, timeout)

    # ------------------------------------------------------------------ outputs
    def latest_orientations(self) -> dict[str, np.ndarray]:
        """World-to-node rotations ``R_i`` from the most recent stamp's TransformStamped."""
        with self.lock:
            msgs = list(self.orientations)
        if not msgs:
            return {}
        def key(m: TransformStamped) -> tuple[int, int]:
            return (m.header.stamp.sec, m.header.stamp.nanosec)
        last = max(key(m) for m in msgs)
        out: dict[str, np.ndarray] = {}
        for m in msgs:
            if key(m) == last:
                r = m.transform.rotation
                out[m.child_frame_id] = quat_to_matrix([r.x, r.y, r.z, r.w]).T
        return out

    def latest_diagnostics(self) -> tuple[int, str, dict[str, str]] | None:
        """``(level, message, values)`` of the newest status of the node under test."""
        with self.lock:
            arrays = list(self.diagnostics)
        for array in reversed(arrays):
            for status in array.status:
                if status.hardware_id == self.target:
                    values = {kv.key: kv.value for kv in status.values}
                    return status.level[0], status.message, values
        return None

    def clear(self) -> None:
        with self.lock:
            self.orientations.clear()
            self.markers.clear()
            self.diagnostics.clear()


# ---------------------------------------------------------------------- node process
REPO = Path(__file__).resolve().parents[1]


def node_command(namespace: str, name: str, params: Sequence[str] = ()) -> list[str]:
    """``rotavg_node --ros-args -r __node:=name -r __ns:=namespace -p ...`` (the console
    script of this venv, else ``python -m rotavg_ros.ros.node``)."""
    exe = shutil.which("rotavg_node", path=str(Path(sys.executable).parent))
    cmd = [exe] if exe else [sys.executable, "-m", "rotavg_ros.ros.node"]
    cmd += ["--ros-args", "-r", f"__node:={name}", "-r", f"__ns:={namespace}"]
    for p in params:
        cmd += ["-p", p]
    return cmd


def process_env() -> dict[str, str]:
    """This worker's domain, localhost discovery, unbuffered output, the repo importable."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    return env


class NodeProcess:
    """``rotavg_node`` in a child process, stdout and stderr in files (no pipe to fill)."""

    def __init__(self, cmd: Sequence[str], log_dir: Path) -> None:
        self.out_path = log_dir / "node.out"
        self.err_path = log_dir / "node.err"
        with open(self.out_path, "w") as out, open(self.err_path, "w") as err:
            self.proc = subprocess.Popen(list(cmd), cwd=REPO, env=process_env(),
                                         stdout=out, stderr=err, text=True)

    @property
    def stderr(self) -> str:
        return self.err_path.read_text()

    @property
    def output(self) -> str:
        return self.out_path.read_text() + self.err_path.read_text()

    def descendants(self) -> list[int]:
        """Pids of the process's children and their children (from /proc)."""
        parents: dict[int, int] = {}
        for entry in os.listdir("/proc"):
            if entry.isdigit():
                try:
                    stat = Path(f"/proc/{entry}/stat").read_text()
                except OSError:
                    continue
                parents[int(entry)] = int(stat.rsplit(")", 1)[1].split()[1])
        found, frontier = [], [self.proc.pid]
        while frontier:
            parent = frontier.pop()
            kids = [pid for pid, pp in parents.items() if pp == parent]
            found += kids
            frontier += kids
        return found

    def stop(self) -> None:
        """Kill it if still running (test teardown)."""
        if self.proc.poll() is None:
            for pid in self.descendants():
                try:
                    os.kill(pid, 9)
                except OSError:
                    pass
            self.proc.kill()
            self.proc.wait(10.0)


def pid_alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie counts as gone)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


# ---------------------------------------------------------------------- exact solver
def spanning_tree_solve(
    graph: ViewGraph, anchor: Hashable | None, options: SolverOptions
) -> SolveResult:
    """Exact for noise-free graphs: BFS from each component's anchor, ``R_j = R_ij^T R_i``.

    Follows the solver's contract: component 0 is the anchor's, every component's anchor
    (first node by index for the others) is identity.
    """
    t0 = time.perf_counter()
    edges = graph.edge_arrays()
    n = graph.num_nodes
    adjacency: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(n)]
    for a, b, R in zip(edges.i, edges.j, edges.R, strict=True):
        adjacency[a].append((b, R.T))  # R_b = R_ab^T R_a
        adjacency[b].append((a, R))  # R_a = R_ab R_b
    rotations = np.zeros((n, 3, 3))
    component = np.full(n, -1, dtype=np.int64)
    start = graph.index_of(anchor) if anchor is not None else 0
    roots = [start] + [k for k in range(n) if k != start]
    anchors: list[Hashable] = []
    ids = graph.node_ids
    for root in roots:
        if component[root] >= 0:
            continue
        label = len(anchors)
        anchors.append(ids[root])
        component[root] = label
        rotations[root] = np.eye(3)
        queue = [root]
        while queue:
            a = queue.pop()
            for b, M in adjacency[a]:
                if component[b] < 0:
                    component[b] = label
                    rotations[b] = M @ rotations[a]
                    queue.append(b)
    predicted = rotations[edges.i] @ np.swapaxes(rotations[edges.j], 1, 2)
    residuals = np.degrees(geodesic_distance(edges.R, predicted))
    return SolveResult(
        node_ids=list(ids),
        rotations=rotations,
        component=component,
        anchors=anchors,
        depth=0,
        residuals_deg=residuals,
        edge_inlier=np.ones(edges.num_edges, dtype=bool),
        num_filtered=0,
        cost_by_depth={},
        duration_s=time.perf_counter() - t0,
    )


def aligned_errors_deg(est: Mapping[Any, np.ndarray], gt: Mapping[Any, np.ndarray]) -> np.ndarray:
    """Errors (deg) after the right gauge R_est ~= R_gt Q, Q = project(sum R_gt^T R_est)."""
    keys = sorted(gt)
    G = np.stack([gt[k] for k in keys])
    E = np.stack([est[k] for k in keys])
    Q = project_to_so3(np.einsum("kji,kjl->il", G, E))
    return np.degrees(geodesic_distance(E, G @ Q))
