#!/usr/bin/env python3
"""Streaming benchmark of the live ``rotavg_node`` (a benchmark that prints figures, not a test).

What it does
------------
1. Builds a synthetic graph: ``--nodes`` random world-to-node rotations ``R_i`` (Haar), a
   sequential chain ``i -> i+1`` (so it is connected) plus random extra pairs up to
   ``--edges`` measurements ``R_ij = R_i R_j^T`` perturbed by Gaussian noise
   (``--noise-deg`` per axis, i.e. a mean angle of about 1.6x that), a fraction
   ``--outliers`` of the non-chain edges replaced by uniformly random rotations. Stream
   order (``--order``): the chain first, then the extra edges shuffled (default), or
   everything shuffled.
2. Starts ``.venv/bin/rotavg_node`` as a separate process with
   ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` and its own ``ROS_DOMAIN_ID``.
3. This process publishes the edges on ``/rotavg_node/edges`` (``TransformStamped``,
   reliable, KEEP_LAST depth >= number of edges) at ``--rate`` edges/s, paced on the
   monotonic clock, after waiting for the subscription to match.
4. Reads ``/diagnostics`` until the node reports ``edges_received == sent`` and checks
   ``accepted + rejected == sent`` (no edge lost).
5. End-to-end latency: from the publication of the LAST edge to the reception of the first
   complete set of ``~/orientations`` (every node) of a solve that includes that edge. A
   solve includes it when its stamp (the node's clock when it took the graph snapshot;
   orientations and diagnostics of a solve share it) is not earlier than the last send and
   its diagnostics say ``solved_version == graph_version`` with ``edges_received == sent``.
   Compared with ``solve_period + last_solve_duration_s`` plus ``--tolerance`` (DDS
   transport, the node's publication of one message per node and this process's executor).
   If edges were lost, it is measured to the first solve of the whole graph as received.
6. Accuracy of those orientations against the synthetic ground truth, gauge-aligned with
   :func:`rotavg_ros.core.metrics.evaluate`, and the node's CPU time and RSS (``/proc/<pid>``).

Usage (from the repository root)::

    .venv/bin/python -m benchmarks.bench_node_stream --nodes 1000 --rate 2000 --edges 20000 \\
        --solve-period 1.0 --seed 0 --extra-node-args='-p iterations:=300'

``--extra-node-args`` is one string, split like a shell command line and appended after the
script's own ``--ros-args -p ...`` (give it with ``=`` because it starts with ``-``).
"""

from __future__ import annotations

import argparse
import math
import os
import shlex
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]

from rotavg_ros.core.metrics import evaluate  # noqa: E402
from rotavg_ros.core.so3 import matrix_to_quat, quat_to_matrix, random_rotations  # noqa: E402

NODE_NAME = "rotavg_node"
DIAG_NAME = f"{NODE_NAME}: rotation averaging"
# Node parameters this benchmark passes unless --extra-node-args overrides them (later -p
# wins). Measured in process on an idle 2-core machine with the default graph (1000 nodes,
# 20,000 edges, dense DMF), cold: the node's defaults (depths 2,4,6,8 x up to 1000 Adam
# iterations) took 6.8 s (depth 8, 0.49 deg mean error), depth 2 x 300 iterations 0.7 s
# (0.37 deg). The node warm-starts most re-solves (one depth, 100 iterations), but a cold
# solve runs whenever the previous solution covers under half of the nodes, and a 6.8 s
# solve on both cores mid-stream delays the final one (8 of 10 runs met the latency bound
# with the defaults, 10 of 10 with these settings). So the benchmark runs the dense DMF at
# depth 2 with 300 iterations by default; --extra-node-args='' runs the node's defaults.
DEFAULT_EXTRA_NODE_ARGS = "-p depths:=[2] -p iterations:=300"
CLK_TCK = os.sysconf("SC_CLK_TCK")


# ---------------------------------------------------------------------- synthetic graph
@dataclass
class SyntheticGraph:
    ids: list[str]
    gt: dict[Hashable, np.ndarray]  # world-to-node R_i
    i: np.ndarray
    j: np.ndarray
    R: np.ndarray  # (E, 3, 3) measured R_ij, in stream order
    outlier: np.ndarray  # (E,) bool
    num_pairs: int


def _small_rotations(rng: np.random.Generator, n: int, sigma_rad: float) -> np.ndarray:
    v = rng.normal(scale=sigma_rad, size=(n, 3))
    theta = np.linalg.norm(v, axis=1)
    axis = v / np.maximum(theta, 1e-300)[:, None]
    half = theta[:, None] / 2.0
    q = np.concatenate([axis * np.sin(half), np.cos(half)], axis=1)
    q[theta == 0] = (0.0, 0.0, 0.0, 1.0)
    return quat_to_matrix(q)


def make_graph(nodes: int, edges: int, seed: int, noise_deg: float,
               outlier_frac: float, order: str = "chain-first") -> SyntheticGraph:
    """Chain + random distinct extra pairs (repeats only when every pair is used).

    ``order``: ``chain-first`` streams the chain in order, then the extra edges shuffled
    (connected from the first ``nodes - 1`` edges on); ``shuffled`` shuffles everything
    (early snapshots are fragmented into many components).
    """
    if nodes < 2:
        raise ValueError("--nodes must be >= 2")
    if edges < nodes - 1:
        raise ValueError(f"--edges must be >= nodes - 1 = {nodes - 1} (the chain)")
    rng = np.random.default_rng(seed)
    Rw = random_rotations(nodes, rng)
    chain_i = np.arange(nodes - 1)
    pairs = {(int(a), int(a) + 1) for a in chain_i}
    ii, jj = chain_i.tolist(), (chain_i + 1).tolist()
    max_pairs = nodes * (nodes - 1) // 2
    extra = edges - (nodes - 1)
    while extra > 0 and len(pairs) < max_pairs:
        a, b = (int(x) for x in rng.integers(0, nodes, size=2))
        key = (min(a, b), max(a, b))
        if a == b or key in pairs:
            continue
        pairs.add(key)
        ii.append(a)
        jj.append(b)
        extra -= 1
    if extra > 0:  # more measurements than pairs: repeat random pairs (the node merges them)
        pick = rng.integers(0, len(ii), size=extra)
        ii += [ii[k] for k in pick]
        jj += [jj[k] for k in pick]
    i = np.asarray(ii, dtype=np.int64)
    j = np.asarray(jj, dtype=np.int64)
    E = i.size
    R = Rw[i] @ np.swapaxes(Rw[j], 1, 2)
    R = _small_rotations(rng, E, math.radians(noise_deg)) @ R
    outlier = np.zeros(E, dtype=bool)
    non_chain = np.arange(nodes - 1, E)
    n_out = int(round(outlier_frac * non_chain.size))
    if n_out:
        outlier[rng.choice(non_chain, size=n_out, replace=False)] = True
        R[outlier] = random_rotations(n_out, rng)
    perm = rng.permutation(E)
    if order == "chain-first":
        perm = np.concatenate([np.arange(nodes - 1), perm[perm >= nodes - 1]])
    elif order != "shuffled":
        raise ValueError(f"unknown order {order!r}")
    ids = [f"n{k:05d}" for k in range(nodes)]
    return SyntheticGraph(ids, {ids[k]: Rw[k] for k in range(nodes)}, i[perm], j[perm],
                          R[perm], outlier[perm], len(pairs))


# ---------------------------------------------------------------------- /proc readings
@dataclass
class ProcSample:
    t: float
    cpu_s: float
    rss_mb: float
    hwm_mb: float
    threads: int


def proc_sample(pid: int) -> ProcSample | None:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2:].split()  # fields from 3 (state) on
    cpu = (int(fields[11]) + int(fields[12])) / CLK_TCK  # utime, stime (fields 14, 15)
    kv = {}
    for line in status.splitlines():
        key, _, value = line.partition(":")
        kv[key] = value.split()
    return ProcSample(time.monotonic(), cpu, int(kv["VmRSS"][0]) / 1024.0,
                      int(kv["VmHWM"][0]) / 1024.0, int(kv["Threads"][0]))


# ---------------------------------------------------------------------- ROS side
@dataclass
class DiagRecord:
    t_recv: float
    stamp_ns: int
    level: int
    message: str
    values: dict[str, str]

    def num(self, key: str, default: float = math.nan) -> float:
        try:
            return float(self.values[key])
        except (KeyError, ValueError):
            return default


@dataclass
class OrientationSet:
    quats: dict[str, tuple[float, float, float, float]] = field(default_factory=dict)
    t_new: list[float] = field(default_factory=list)  # arrival of the k-th distinct frame

    @property
    def t_first(self) -> float:
        return self.t_new[0] if self.t_new else math.nan

    def t_complete(self, n: int) -> float:
        """When ``n`` distinct frames had arrived (NaN if not yet)."""
        return self.t_new[n - 1] if len(self.t_new) >= n else math.nan


class Observer:
    """Callbacks of this process's subscriptions (run on the spin thread)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.diags: list[DiagRecord] = []
        self.sets: dict[int, OrientationSet] = {}

    def on_orientation(self, msg: Any) -> None:
        now = time.monotonic()
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        r = msg.transform.rotation
        with self.lock:
            s = self.sets.get(stamp)
            if s is None:
                s = self.sets[stamp] = OrientationSet()
            if msg.child_frame_id not in s.quats:
                s.t_new.append(now)
            s.quats[msg.child_frame_id] = (r.x, r.y, r.z, r.w)

    def on_diagnostics(self, msg: Any) -> None:
        now = time.monotonic()
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        for st in msg.status:
            if st.name != DIAG_NAME:
                continue
            rec = DiagRecord(now, stamp, int.from_bytes(st.level, "little")
                             if isinstance(st.level, bytes) else int(st.level),
                             st.message, {kv.key: kv.value for kv in st.values})
            with self.lock:
                self.diags.append(rec)


def stop_process(proc: subprocess.Popen[bytes], timeout: float) -> str:
    if proc.poll() is not None:
        return f"already exited (rc {proc.returncode})"
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=timeout)
        return f"exited after SIGINT (rc {proc.returncode})"
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=10)
        return f"KILLED after {timeout:g} s without exiting on SIGINT"


def tail(path: Path, lines: int = 30) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"


def code_version() -> str:
    """``<commit>`` of the checkout, with the node's files that differ from it."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO_ROOT,
                              capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "rotavg_ros",
                                "msg_adapters"], cwd=REPO_ROOT, capture_output=True,
                               text=True, timeout=10).stdout.split("\n")
    except (OSError, subprocess.SubprocessError):
        return "unknown (no git)"
    changed = [line[3:] for line in dirty if line.strip()]
    return f"{head or '?'}" + (f" + uncommitted changes in {', '.join(changed)}"
                               if changed else "")


def fmt_pf(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def launch_node(node_cmd: list[str]) -> tuple[subprocess.Popen[bytes], Path]:
    """Start the node process (its own session; output to a temporary log file)."""
    log_fd, log_name = tempfile.mkstemp(prefix="bench_rotavg_node_", suffix=".log")
    env = dict(os.environ)
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)  # let the child bootstrap itself
    proc = subprocess.Popen(node_cmd, env=env, stdout=log_fd, stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL, start_new_session=True)
    os.close(log_fd)
    return proc, Path(log_name)


def start_watchdog(proc: subprocess.Popen[bytes], seconds: float) -> threading.Timer:
    """After ``seconds``, kill the node and exit this process (code 3); cancel it when done."""
    def watchdog() -> None:
        print(f"HARD TIMEOUT after {seconds:g} s: killing the node", flush=True)
        try:
            proc.kill()
        finally:
            os._exit(3)

    timer = threading.Timer(seconds, watchdog)
    timer.daemon = True
    timer.start()
    return timer


def start_node_and_client(
    node_cmd: list[str], hard_timeout: float, domain_id: int, client_name: str
) -> tuple[subprocess.Popen[bytes], Path, threading.Timer, Any, Any]:
    """Start the node process (with its watchdog) and this script's rclpy node.

    Returns ``(proc, log_path, watchdog, context, client_node)``; the client has its own
    ``Context`` on ``domain_id``. rclpy is imported before the node starts, so a failing
    import cannot leave an orphan node behind.
    """
    import rclpy
    from rclpy.context import Context

    proc, log_path = launch_node(node_cmd)
    timer = start_watchdog(proc, hard_timeout)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    return proc, log_path, timer, ctx, rclpy.create_node(client_name, context=ctx)


def start_spinner(node: Any, ctx: Any) -> tuple[Any, threading.Event, threading.Thread]:
    """Spin ``node`` in a daemon thread until the returned event is set or ``ctx`` ends.

    Returns ``(executor, stop, thread)``; the caller sets ``stop``, joins the thread and
    shuts the executor down.
    """
    from rclpy.executors import SingleThreadedExecutor

    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set() and ctx.ok():
            ex.spin_once(timeout_sec=0.05)

    thread = threading.Thread(target=spin, name="spin", daemon=True)
    thread.start()
    return ex, stop, thread


def wait_for_match(
    proc: subprocess.Popen[bytes], log_path: Path, until: float, timeout_s: float,
    matched: Callable[[], bool],
) -> None:
    """Poll ``matched()`` until true; ``RuntimeError`` if the node exits or ``until`` passes
    (``timeout_s`` is the limit named in that error)."""
    while time.monotonic() < until:
        if proc.poll() is not None:
            raise RuntimeError(f"node exited (rc {proc.returncode}):\n{tail(log_path)}")
        if matched():
            return
        time.sleep(0.05)
    raise RuntimeError(f"topics did not match within {timeout_s:g} s:\n{tail(log_path)}")


def wait_node_idle(proc: subprocess.Popen[bytes], log_path: Path, until: float) -> ProcSample:
    """Wait until the node uses < 10% of a core (its start-up imports are done) or ``until``.

    Raises ``RuntimeError`` if the process is gone.
    """
    prev = proc_sample(proc.pid)
    while True:
        time.sleep(0.5)
        cur = proc_sample(proc.pid)
        if prev is None or cur is None:
            raise RuntimeError(f"node process vanished:\n{tail(log_path)}")
        busy_frac = (cur.cpu_s - prev.cpu_s) / (cur.t - prev.t)
        prev = cur
        if busy_frac < 0.1 or time.monotonic() >= until:
            return prev


# ---------------------------------------------------------------------- main
def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--nodes", type=int, default=1000)
    p.add_argument("--rate", type=float, default=2000.0, help="edges per second")
    p.add_argument("--edges", type=int, default=20000, help="total measurements streamed")
    p.add_argument("--solve-period", type=float, default=1.0, help="node's solve_period (s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--noise-deg", type=float, default=1.0,
                   help="per-axis std of the edge noise (mean angle ~1.6x)")
    p.add_argument("--outliers", type=float, default=0.05,
                   help="fraction of non-chain edges replaced by random rotations")
    p.add_argument("--order", choices=("chain-first", "shuffled"), default="chain-first",
                   help="stream order: the chain first, then the extra edges shuffled; or "
                        "everything shuffled")
    p.add_argument("--tolerance", type=float, default=0.25,
                   help="latency allowance (s) for DDS transport, the node's publication of "
                        "the orientations and this process's executor")
    p.add_argument("--drain-timeout", type=float, default=15.0,
                   help="after the first final-looking diagnostics, wait this long for "
                        "received == sent")
    add_node_run_arguments(p, hard_timeout=900.0)
    return p.parse_args(argv)


def add_node_run_arguments(p: argparse.ArgumentParser, hard_timeout: float) -> None:
    """Options both node benchmarks share: node launch, discovery and time limits."""
    p.add_argument("--extra-node-args", default=DEFAULT_EXTRA_NODE_ARGS,
                   help="extra node arguments after '--ros-args' (one shell-quoted string; "
                        "pass it as --extra-node-args='...')")
    p.add_argument("--domain-id", type=int, default=None,
                   help="ROS_DOMAIN_ID (default: 100 + pid %% 100)")
    p.add_argument("--match-timeout", type=float, default=60.0,
                   help="wait this long for the node to start and the topics to match")
    p.add_argument("--hard-timeout", type=float, default=hard_timeout,
                   help="abort the whole run (and kill the node) after this many seconds")
    p.add_argument("--verbose", action="store_true",
                   help="print the timeline of the node's diagnostics")
    p.add_argument("--node-bin", default=str(REPO_ROOT / ".venv/bin/rotavg_node"))


def begin_run(args: argparse.Namespace) -> tuple[float, float, int]:
    """``(t_start, deadline, domain_id)``; sets localhost discovery and the domain id.

    Waiting stops at ``deadline``, early enough to report and shut the node down before the
    watchdog fires at ``--hard-timeout``.
    """
    t_start = time.monotonic()
    deadline = t_start + max(0.8 * args.hard_timeout, args.hard_timeout - 30.0)
    domain_id = args.domain_id if args.domain_id is not None else 100 + os.getpid() % 100
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ["ROS_DOMAIN_ID"] = str(domain_id)
    return t_start, deadline, domain_id


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    t_start, deadline, domain_id = begin_run(args)

    graph = make_graph(args.nodes, args.edges, args.seed, args.noise_deg, args.outliers,
                       args.order)
    E = graph.i.size
    mean_degree = 2.0 * graph.num_pairs / args.nodes
    print(f"graph: {args.nodes} nodes, {E} measurements on {graph.num_pairs} distinct pairs "
          f"(chain + random), mean degree {mean_degree:.1f} -> node mode auto picks "
          f"{'dense DMF' if mean_degree >= 10 else 'sparse'} on the full graph; "
          f"noise {args.noise_deg:g} deg/axis, {int(graph.outlier.sum())} gross outliers "
          f"({args.outliers:.0%} of non-chain edges), seed {args.seed}, order {args.order}")

    extra = shlex.split(args.extra_node_args)
    node_cmd = [
        args.node_bin, "--ros-args",
        "-p", f"solve_period:={args.solve_period}",
        "-p", f"orientations_qos_depth:={max(10000, 2 * args.nodes)}",
        *extra,
    ]
    if args.extra_node_args == DEFAULT_EXTRA_NODE_ARGS:
        print(f"NOTE: the node runs with the benchmark's default extra args {extra}, not the "
              "node's solver defaults (depths 2,4,6,8 x 1000 iterations; a cold solve of the "
              "default graph: 6.8 s with those, 0.7 s with depth 2 x 300 iterations). Pass "
              "--extra-node-args='' for the node's defaults.")
    print(f"node: {shlex.join(node_cmd)}")
    print(f"code: {code_version()}")
    print(f"env: ROS_DOMAIN_ID={domain_id} ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST")

    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import TransformStamped
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    proc, log_path, timer, ctx, node = start_node_and_client(
        node_cmd, args.hard_timeout, domain_id, "bench_node_stream")
    obs = Observer()

    def qos(depth: int) -> QoSProfile:
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                          reliability=ReliabilityPolicy.RELIABLE)

    pub = node.create_publisher(TransformStamped, f"/{NODE_NAME}/edges", qos(max(E, 1000)))
    sub_o: Any = None

    def on_orientation(msg: Any) -> None:
        # Take the orientations already queued in the same callback (as the node does with
        # its edges): one wait-set rebuild per message would make this receiver, not the
        # node, the slow part of the measured latency (0.3-1.2 s for 1000 messages).
        obs.on_orientation(msg)
        for _ in range(4 * args.nodes):
            with sub_o.handle:
                taken = sub_o.handle.take_message(sub_o.msg_type, sub_o.raw)
            if taken is None:
                break
            obs.on_orientation(taken[0])

    sub_o = node.create_subscription(TransformStamped, f"/{NODE_NAME}/orientations",
                                     on_orientation, qos(max(10000, 4 * args.nodes)))
    sub_d = node.create_subscription(DiagnosticArray, "/diagnostics", obs.on_diagnostics,
                                     qos(1000))
    ex, stop, spinner = start_spinner(node, ctx)

    rc = 1
    samples: dict[str, ProcSample | None] = {}
    try:
        # ------------------------------------------------------------ wait for matching
        t_launch = time.monotonic()
        wait_for_match(proc, log_path, min(deadline, t_launch + args.match_timeout),
                       args.match_timeout,
                       lambda: (pub.get_subscription_count() >= 1
                                and sub_o.get_publisher_count() >= 1
                                and sub_d.get_publisher_count() >= 1))
        print(f"matched {time.monotonic() - t_launch:.2f} s after the node was launched")
        # The node imports the solver (torch) on its worker thread at start-up; wait until it
        # is idle so that the stream measures the steady state, not the start-up.
        prev = wait_node_idle(proc, log_path,
                              min(deadline, time.monotonic() + args.match_timeout))
        print(f"node idle {time.monotonic() - t_launch:.2f} s after launch "
              f"(start-up CPU {prev.cpu_s:.2f} s)")
        samples["start"] = prev

        # ------------------------------------------------------------ build messages
        quats = matrix_to_quat(graph.R)
        msgs = []
        for k in range(E):
            m = TransformStamped()
            m.header.frame_id = graph.ids[graph.i[k]]
            m.child_frame_id = graph.ids[graph.j[k]]
            r = m.transform.rotation
            r.x, r.y, r.z, r.w = (float(v) for v in quats[k])
            msgs.append(m)

        # ------------------------------------------------------------ stream
        clock = node.get_clock()
        period = 1.0 / args.rate
        max_lag = 0.0
        t0 = time.monotonic()
        t_first = t_last = t0
        t_last_wall_ns = 0
        for k, m in enumerate(msgs):
            target = t0 + k * period
            now = time.monotonic()
            if target > now:
                time.sleep(target - now)
            else:
                max_lag = max(max_lag, now - target)
            m.header.stamp = clock.now().to_msg()
            if k == E - 1:
                t_last_wall_ns = time.time_ns()
                t_last = time.monotonic()
            elif k == 0:
                t_first = time.monotonic()
            pub.publish(m)
        t_after = time.monotonic()
        samples["streamed"] = proc_sample(proc.pid)
        span = t_last - t_first
        achieved = (E - 1) / span if span > 0 else math.inf
        print(f"sent {E} edges in {span:.3f} s: achieved {achieved:.1f} edges/s "
              f"(target {args.rate:g}); max lag behind schedule {max_lag * 1e3:.1f} ms; "
              f"last publish call took {(t_after - t_last) * 1e3:.2f} ms")

        # ------------------------------------------------------------ wait for the final solve
        final: DiagRecord | None = None
        fallback: DiagRecord | None = None  # first solve of the whole graph as received
        latest: DiagRecord | None = None
        first_final_looking = math.nan
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                raise RuntimeError(f"node exited (rc {proc.returncode}):\n{tail(log_path)}")
            with obs.lock:
                diags = list(obs.diags)
            if diags:
                latest = diags[-1]
            for d in diags:
                if d.stamp_ns < t_last_wall_ns:
                    continue
                if d.num("solved_version") != d.num("graph_version"):
                    continue
                if fallback is None:
                    fallback = d
                    first_final_looking = time.monotonic()
                if int(d.num("edges_received", -1)) == E:
                    final = d
                    break
            if final is not None:
                break
            if (not math.isnan(first_final_looking)
                    and time.monotonic() > first_final_looking + args.drain_timeout):
                break
            time.sleep(0.02)

        if args.verbose:
            with obs.lock:
                diags = list(obs.diags)
            print()
            print("diagnostics timeline (recv s after last send, stamp s after last send, "
                  "received, graph_version, solved_version, last_solve_duration_s, "
                  "skipped busy):")
            for d in diags:
                print(f"  {d.t_recv - t_last:+8.3f} {(d.stamp_ns - t_last_wall_ns) / 1e9:+8.3f} "
                      f"{d.values.get('edges_received')} {d.values.get('graph_version')} "
                      f"{d.values.get('solved_version')} "
                      f"{d.values.get('last_solve_duration_s')} "
                      f"{d.values.get('timer_ticks_skipped_busy')}")

        # ------------------------------------------------------------ counters
        rec = final or latest
        print()
        print("== edges (from /diagnostics) ==")
        if rec is None:
            print("no diagnostics received")
            lost_ok = False
        else:
            received = int(rec.num("edges_received", -1))
            accepted = int(rec.num("edges_accepted", -1))
            rejected = int(rec.num("edges_rejected", -1))
            lost_ok = received == E and accepted + rejected == E
            print(f"sent {E}  received {received}  accepted {accepted}  rejected {rejected}")
            reasons = {k: v for k, v in rec.values.items()
                       if k not in ("edges_rejected",) and v not in ("0", "0.0")
                       and k in ("zero_quaternion", "non_unit_quaternion", "non_finite",
                                 "self_loop", "reserved_frame_id", "empty_frame_id",
                                 "invalid_measurement")}
            if reasons:
                print(f"rejection reasons: {reasons}")
            print(f"no edge lost (received == sent and accepted + rejected == sent): "
                  f"{fmt_pf(lost_ok)}")
            with obs.lock:
                all_in = next((d for d in obs.diags if int(d.num("edges_received", -1)) == E),
                              None)
            if all_in is not None:
                print(f"the node's diagnostics first showed received == sent "
                      f"{all_in.t_recv - t_last:.3f} s after the last send (an upper bound: "
                      f"while the graph changes, diagnostics come only after each solve)")

        # ------------------------------------------------------------ latency
        print()
        print("== end-to-end latency (last edge sent -> complete orientations received) ==")
        latency_ok = False
        accuracy_ok = False
        lost_note = ""
        if final is None and fallback is not None:
            lost_note = " [EDGES LOST: measured to the first solve of all edges that arrived]"
            print("edges were lost, so no solve can include every edge; measuring to the first "
                  "solve (stamp >= last send) of the whole graph as received instead "
                  "(the last edge itself may be among the lost ones)")
            final = fallback
        if final is None:
            print("no solve including the last edge was seen before the timeout: FAIL")
        else:
            expected = int(final.num("solved_nodes", args.nodes))
            # Orientations precede the diagnostics of the same solve; allow a moment anyway.
            oset: OrientationSet | None = None
            t_wait = time.monotonic() + 10.0
            while time.monotonic() < min(deadline, t_wait):
                with obs.lock:
                    s = obs.sets.get(final.stamp_ns)
                    if s is not None and not math.isnan(s.t_complete(expected)):
                        oset = s
                        break
                time.sleep(0.02)
            solve_s = final.num("last_solve_duration_s")
            budget = args.solve_period + solve_s
            wait_s = (final.stamp_ns - t_last_wall_ns) / 1e9
            with obs.lock:
                diags = list(obs.diags)
            # The solve that was running when the last edge was sent: its diagnostics carry
            # its snapshot stamp (before the last send) and arrive after the last send.
            busy = [d for k, d in enumerate(diags)
                    if d.stamp_ns < t_last_wall_ns and d.t_recv > t_last
                    and d.stamp_ns / 1e9 + d.num("last_solve_duration_s", 0.0)
                    > t_last_wall_ns / 1e9
                    and (k == 0 or d.values.get("solved_version")
                         != diags[k - 1].values.get("solved_version"))]
            print(f"final solve: stamp - last send = {wait_s:.3f} s (wait for the timer"
                  f"{' and the running solve' if busy else ''}), "
                  f"solve {solve_s:.3f} s, {final.values.get('solved_nodes', '?')} nodes, "
                  f"{final.values.get('measurements', '?')} measurements, depth "
                  f"{final.values.get('depth', '?')}, solves completed "
                  f"{final.values.get('solves_completed', '?')}, timer ticks skipped busy "
                  f"{final.values.get('timer_ticks_skipped_busy', '?')}")
            if busy:
                b = busy[0]
                print(f"a solve was running when the last edge was sent (started "
                      f"{(t_last_wall_ns - b.stamp_ns) / 1e9:.3f} s before it, lasted "
                      f"{b.num('last_solve_duration_s'):.3f} s); the final solve could only "
                      f"start at the first timer tick after it ended")
            if oset is None:
                print("orientations of the final solve incomplete or missing: FAIL")
            else:
                t_done = oset.t_complete(expected)
                latency = t_done - t_last
                pub_s = t_done - oset.t_first
                print(f"latency {latency:.3f} s   vs   solve_period + last solve duration = "
                      f"{args.solve_period:.3f} + {solve_s:.3f} = {budget:.3f} s "
                      f"(+ {args.tolerance:g} s tolerance for DDS transport and publication "
                      f"of {expected} messages){lost_note}")
                print(f"  (publish -> receive of the {expected} orientations took "
                      f"{pub_s:.3f} s; first orientation arrived "
                      f"{oset.t_first - t_last - wait_s - solve_s:+.3f} s after "
                      f"stamp + solve)")
                latency_ok = latency <= budget + args.tolerance
                if busy:
                    b = busy[0]
                    busy_left = ((b.stamp_ns - t_last_wall_ns) / 1e9
                                 + b.num("last_solve_duration_s"))
                    bound = busy_left + budget
                    print(f"  (informative: with the running solve's remaining "
                          f"{busy_left:.3f} s added the bound is {bound:.3f} s: latency "
                          f"{'within' if latency <= bound + args.tolerance else 'ABOVE'} it)")
                print(f"latency <= one timer period + solve time (+{args.tolerance:g} s): "
                      f"{fmt_pf(latency_ok)}")

                # ---------------------------------------------------- accuracy
                print()
                print("== accuracy vs synthetic ground truth (gauge-aligned, "
                      "rotavg_ros.core.metrics.evaluate) ==")
                est = {k: quat_to_matrix(np.asarray(q)).T for k, q in oset.quats.items()}
                stats = evaluate(est, graph.gt)
                print(f"nodes compared {stats.num_nodes}/{args.nodes}: mean "
                      f"{stats.mean_deg:.3f} deg, median {stats.median_deg:.3f} deg, max "
                      f"{stats.max_deg:.3f} deg")
                print(f"node diagnostics: residual median "
                      f"{final.num('residual_median_deg'):.3f} deg, filtered outliers "
                      f"{final.values.get('filtered_outliers', '?')} (injected "
                      f"{int(graph.outlier.sum())}), components "
                      f"{final.values.get('components', '?')}, level {final.level} "
                      f"({final.message})")
                accuracy_ok = stats.num_nodes == args.nodes

        # ------------------------------------------------------------ CPU / RSS
        samples["end"] = proc_sample(proc.pid)
        print()
        print(f"== node process (pid {proc.pid}) CPU / memory (/proc) ==")
        s0, s1, s2 = samples.get("start"), samples.get("streamed"), samples.get("end")
        if s0 and s1 and s2:
            print(f"CPU before streaming (start-up, imports): {s0.cpu_s:.2f} s")
            d1 = s1.t - s0.t
            print(f"CPU while streaming: {s1.cpu_s - s0.cpu_s:.2f} s in {d1:.2f} s "
                  f"({100 * (s1.cpu_s - s0.cpu_s) / d1:.0f}% of one core)")
            d2 = s2.t - s1.t
            print(f"CPU after streaming until the final result: {s2.cpu_s - s1.cpu_s:.2f} s "
                  f"in {d2:.2f} s ({100 * (s2.cpu_s - s1.cpu_s) / max(d2, 1e-9):.0f}% of one "
                  f"core)")
            print(f"RSS: {s0.rss_mb:.0f} MiB before streaming, {s1.rss_mb:.0f} MiB after, "
                  f"{s2.rss_mb:.0f} MiB at the end; peak VmHWM {s2.hwm_mb:.0f} MiB; "
                  f"threads {s2.threads}")
        else:
            print("could not read /proc for the node")

        print()
        print(f"SUMMARY: no edge lost {fmt_pf(lost_ok)}; latency {fmt_pf(latency_ok)}; "
              f"orientations complete {fmt_pf(accuracy_ok)}; "
              f"wall time {time.monotonic() - t_start:.1f} s")
        rc = 0 if (lost_ok and latency_ok and accuracy_ok) else 1
    except RuntimeError as exc:
        print(f"ERROR: {exc}")
        rc = 2
    finally:
        stop.set()
        spinner.join(timeout=5)
        ex.shutdown()
        node.destroy_node()
        ctx.try_shutdown()
        how = stop_process(proc, timeout=15.0)
        print(f"node shutdown: {how}")
        if proc.returncode not in (0, -signal.SIGINT, 130) or rc == 2:
            print(f"node log tail ({log_path}):\n{tail(log_path)}")
        else:
            log_path.unlink(missing_ok=True)
        timer.cancel()
    return rc


if __name__ == "__main__":
    sys.exit(main())
