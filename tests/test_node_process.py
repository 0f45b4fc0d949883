"""``rotavg_node`` as its own process: signals, exit status, graph_file checks, --help.

Each test starts the console script with ``--ros-args -p ...`` (see ``ros_fixtures``) and
talks to it over DDS from an :class:`EdgeClient` in the test process.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from ros_fixtures import (
    EdgeClient,
    NodeProcess,
    RosHarness,
    node_command,
    pid_alive,
    process_env,
    ros,  # noqa: F401 - pytest fixture
    unique_namespace,
    wait_until,
)
from std_srvs.srv import Trigger

from rotavg_ros.app.parameters import PARAMETER_TABLE
from rotavg_ros.core.so3 import random_rotations
from rotavg_ros.io.g2o import write_g2o
from rotavg_ros.io.graph_store import load_graph

REPO = Path(__file__).resolve().parents[1]
NAME = "rotavg_proc"
# A dense solve of 300 nodes with this many iterations runs for minutes: a signal always
# finds it running.
LONG_SOLVE = ["solve_period:=3600.0", "mode:=dense", "depths:=[2, 4]",
              "iterations:=10000000"]
EXIT_BOUND_S = 2.0
"""Required: exit within 2 s of the signal (measured 0.2-0.4 s on the loaded 2-core
machine); the measured times are printed (pytest -s) and reported in the stderr line."""


def ring_graph(n: int, seed: int = 0) -> list[tuple[str, str, np.ndarray]]:
    """A ring of ``n`` nodes plus three chords per node, noise-free."""
    rng = np.random.default_rng(seed)
    R = random_rotations(n, rng)
    pairs = {(k, (k + 1) % n) for k in range(n)}
    for k in range(n):
        for d in rng.choice(np.arange(2, n - 1), size=3, replace=False):
            pairs.add((k, int((k + d) % n)))
    return [(f"n{a}", f"n{b}", R[a] @ R[b].T) for a, b in sorted(pairs)]


def send_and_wait(client: EdgeClient, edges: list[tuple[str, str, np.ndarray]]) -> None:
    for a, b, R in edges:
        client.send_edge(a, b, R)

    def received() -> bool:
        diag = client.latest_diagnostics()
        return diag is not None and int(diag[2]["edges_received"]) >= len(edges)

    assert wait_until(received, 30.0), f"the node did not report {len(edges)} edges"


def start(ros: RosHarness, tmp_path: Path, params: list[str]) -> tuple[  # noqa: F811
        NodeProcess, EdgeClient]:
    node = NodeProcess(node_command(ros.namespace, NAME, params), tmp_path)
    client = ros.add(EdgeClient(f"{ros.namespace}/{NAME}", context=ros.context,
                                namespace=ros.namespace))
    ros.start()
    assert client.wait_connected(60.0), "the node process did not show up over DDS:\n" + \
        node.output
    return node, client


def cpu_seconds(pids: list[int]) -> float:
    """User + system CPU time of ``pids`` (from /proc, clock ticks of 10 ms)."""
    total = 0.0
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(fields[11]) + int(fields[12])) / 100.0
    return total


def wait_for_idle(pids: list[int], timeout: float = 60.0) -> None:
    """Wait until ``pids`` use (almost) no CPU over 0.3 s: the solver child has imported the
    solver, so the CPU it uses next is the solve's."""
    def idle() -> bool:
        before = cpu_seconds(pids)
        time.sleep(0.3)
        return cpu_seconds(pids) - before < 0.05
    assert wait_until(idle, timeout), "the node does not settle"


def wait_for_child_cpu(node: NodeProcess, seconds: float, timeout: float = 60.0,
                       itself: bool = False) -> None:
    """Wait until a child of the node (or, with ``itself``, the node process) has used
    ``seconds`` of CPU: the solve is running."""
    def pids() -> list[int]:
        return [node.proc.pid] if itself else node.descendants()
    start = cpu_seconds(pids())
    assert wait_until(lambda: cpu_seconds(pids()) - start >= seconds, timeout), \
        "no solve is running"


def request_long_solve(node: NodeProcess, client: EdgeClient, itself: bool = False) -> None:
    """Call ~/solve (without waiting for the answer) once the node is idle, and return when
    the solve has used 0.5 s of CPU."""
    wait_for_idle([node.proc.pid] + node.descendants())
    client.solve_client.call_async(Trigger.Request())
    wait_for_child_cpu(node, 0.5, itself=itself)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_during_a_long_solve_saves_and_exits_within_2_s(
    ros: RosHarness, tmp_path: Path, signum: int,  # noqa: F811
) -> None:
    graph_file = tmp_path / "live.g2o"
    node, client = start(ros, tmp_path, LONG_SOLVE + [f"graph_file:={graph_file}"])
    try:
        edges = ring_graph(300, seed=3)
        send_and_wait(client, edges)
        wait_for_idle([node.proc.pid] + node.descendants())
        answer = client.solve_client.call_async(Trigger.Request())
        wait_for_child_cpu(node, 0.5)
        children = node.descendants()
        assert children
        t0 = time.monotonic()
        node.proc.send_signal(signum)
        rc = node.proc.wait(10.0)
        elapsed = time.monotonic() - t0
    finally:
        node.stop()
    print(f"\n{signal.Signals(signum).name} during a 300-node solve: exit after "
          f"{elapsed:.2f} s")
    err = node.stderr
    assert rc == 0, node.output
    assert elapsed < EXIT_BOUND_S, f"took {elapsed:.2f} s\n{node.output}"
    assert f"{signal.Signals(signum).name}: stopping" in err
    assert "abandoned the running solve" in err
    assert f"saved {len(edges)} measurements to {graph_file}" in err
    for word in ("failed", "error", "Traceback", "exception"):
        assert word.lower() not in err.lower(), err
    assert len(load_graph(graph_file).measurements) == len(edges)
    assert wait_until(lambda: not any(pid_alive(p) for p in children), 5.0), \
        "the solver child outlived the node"
    if answer.done():  # an answer may or may not have gone out before the node went away
        assert not answer.result().success


def test_signal_during_a_solve_in_the_worker_thread(
    ros: RosHarness, tmp_path: Path,  # noqa: F811
) -> None:
    """solve_in_subprocess:=false: the thread cannot be interrupted, the node exits anyway."""
    graph_file = tmp_path / "live.g2o"
    node, client = start(ros, tmp_path, LONG_SOLVE + [f"graph_file:={graph_file}",
                                                      "solve_in_subprocess:=false"])
    try:
        edges = ring_graph(300, seed=6)
        send_and_wait(client, edges)
        request_long_solve(node, client, itself=True)
        t0 = time.monotonic()
        node.proc.send_signal(signal.SIGINT)
        rc = node.proc.wait(10.0)
        elapsed = time.monotonic() - t0
    finally:
        node.stop()
    print(f"\nSIGINT during a 300-node solve in the worker thread: exit after {elapsed:.2f} s")
    assert rc == 0, node.output
    assert elapsed < EXIT_BOUND_S, node.output
    assert "abandoned the running solve" in node.stderr
    assert "error" not in node.stderr.lower(), node.stderr
    assert len(load_graph(graph_file).measurements) == len(edges)


def test_second_signal_exits_at_once(ros: RosHarness, tmp_path: Path) -> None:  # noqa: F811
    node, client = start(ros, tmp_path, LONG_SOLVE)
    try:
        send_and_wait(client, ring_graph(300, seed=4))
        request_long_solve(node, client)
        children = node.descendants()
        t0 = time.monotonic()
        node.proc.send_signal(signal.SIGINT)
        node.proc.send_signal(signal.SIGTERM)
        rc = node.proc.wait(10.0)
        elapsed = time.monotonic() - t0
    finally:
        node.stop()
    print(f"\nSIGINT + SIGTERM during a solve: exit after {elapsed:.2f} s")
    # 0: the first one stopped the node before the second came. Else the second one handled
    # exits at once: SIGTERM's, or SIGINT's where SIGTERM reached Python's handler first
    # (the kernel may deliver two signals sent back to back to two threads at once).
    assert rc in (128 + signal.SIGTERM, 128 + signal.SIGINT, 0), node.output
    assert elapsed < EXIT_BOUND_S, node.output
    if rc:
        assert f"{signal.Signals(rc - 128).name} again: exiting now" in node.stderr
    assert wait_until(lambda: not any(pid_alive(p) for p in children), 5.0)


def test_failed_save_at_exit_gives_a_non_zero_status(
    ros: RosHarness, tmp_path: Path,  # noqa: F811
) -> None:
    folder = tmp_path / "graphs"
    folder.mkdir()
    graph_file = folder / "live.g2o"
    node, client = start(ros, tmp_path, ["solve_period:=3600.0", f"graph_file:={graph_file}"])
    try:
        send_and_wait(client, ring_graph(10, seed=5))
        folder.rmdir()  # the save at exit cannot write any more
        t0 = time.monotonic()
        node.proc.send_signal(signal.SIGINT)  # soon after the start: the solver child
        rc = node.proc.wait(10.0)             # may still be importing torch
        elapsed = time.monotonic() - t0
    finally:
        node.stop()
    assert rc == 1, node.output
    assert f"could not write {graph_file}" in node.stderr
    assert elapsed < EXIT_BOUND_S, node.output
    assert "leaked" not in node.stderr and "Traceback" not in node.stderr, node.stderr


@pytest.mark.parametrize(("graph_file", "fragment"), [
    ("{tmp}/missing/live.g2o", "does not exist"),
    ("/proc/live.g2o", "is not writable"),  # refused even to root
])
def test_unusable_graph_file_is_refused_at_start(
    tmp_path: Path, graph_file: str, fragment: str,
) -> None:
    cmd = node_command("/", NAME, [f"graph_file:={graph_file.format(tmp=tmp_path)}"])
    proc = subprocess.run(cmd, cwd=REPO, env=process_env(), capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rotavg_node: error:"), proc.stderr
    assert fragment in lines[0]


@pytest.mark.parametrize("flag", ["--help", "-h"])
def test_help_lists_parameters_and_does_not_start_ros(flag: str) -> None:
    env = dict(process_env(), ROS_DOMAIN_ID="not-a-number")  # rclpy.init would fail on it
    cmd = node_command("/", NAME)
    proc = subprocess.run(cmd[:cmd.index("--ros-args")] + [flag], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    for spec in PARAMETER_TABLE:
        assert f"  {spec.name} (" in proc.stdout
    assert "solve_period (double, default 1.0) [range 0.01 to 3600; read-only" in proc.stdout
    assert "edge_reliability (string, default reliable) [one of: reliable, best_effort" \
        in proc.stdout
    assert proc.stderr == ""


@pytest.mark.parametrize("from_file", [False, True], ids=["synthetic", "g2o"])
def test_example_client_solves_and_prints_every_orientation(
    tmp_path: Path, from_file: bool,
) -> None:
    namespace = unique_namespace()
    node = NodeProcess(node_command(namespace, NAME, ["solve_period:=3600.0",
                                                      "iterations:=300", "depths:=[2, 4]"]),
                       tmp_path)
    cmd = [sys.executable, str(REPO / "scripts" / "example_client.py"),
           "--node", f"{namespace}/{NAME}", "--timeout", "60"]
    frames = [f"cam_{k}" for k in range(12)]
    if from_file:
        graph = tmp_path / "graph.g2o"
        R = random_rotations(6, np.random.default_rng(9))
        edges = SimpleNamespace(i=[0, 1, 2, 3, 4, 5, 0], j=[1, 2, 3, 4, 5, 0, 3],
                       R=[R[a] @ R[b].T for a, b in [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5),
                                                     (5, 0), (0, 3)]], weight=[1.0] * 7)
        write_g2o(graph, list(range(6)), np.tile(np.eye(3), (6, 1, 1)), edges)
        cmd.append(str(graph))
        frames = [str(k) for k in range(6)]
    try:
        proc = subprocess.run(cmd, cwd=REPO, env=process_env(), capture_output=True,
                              text=True, timeout=180)
    finally:
        node.proc.send_signal(signal.SIGINT)
        node.proc.wait(10.0)
        node.stop()
    assert proc.returncode == 0, proc.stdout + proc.stderr + node.output
    out = proc.stdout
    assert "~/solve: success=True (solved" in out, out
    for frame in frames:
        assert re.search(rf"^  {frame}: ([+-]\d\.\d{{6}} ?){{4}}$", out, re.MULTILINE), out
    assert re.search(r"^diagnostics: OK: \d+ nodes solved$", out, re.MULTILINE), out
    assert f"  solved_nodes: {len(frames)}" in out
