"""The node's solver child process: priority and a real solve through it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from rotavg_ros.app.solver_process import PARENT_CHECK_PERIOD, SubprocessSolver
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.so3 import random_rotations
from rotavg_ros.core.view_graph import ViewGraph


@pytest.mark.skipif(not hasattr(os, "nice"), reason="os.nice is POSIX only")
def test_child_runs_at_the_requested_lower_priority() -> None:
    solver = SubprocessSolver(niceness=5)
    try:
        child = solver._get_pool().submit(os.nice, 0).result(timeout=120)
    finally:
        solver.close()
    assert child == min(19, os.nice(0) + 5)


def test_solve_through_the_child_matches_the_ground_truth() -> None:
    rng = np.random.default_rng(0)
    R = random_rotations(6, rng)
    g = ViewGraph()
    for a in range(6):
        for b in range(a + 1, 6):
            g.add_edge(a, b, R[a] @ R[b].T)
    solver = SubprocessSolver(niceness=3)
    try:
        res = solver(g, 0, SolverOptions.from_flat(mode="sparse"))
    finally:
        solver.close()
    expected = R @ R[0].T  # anchor 0 at identity
    assert np.allclose(res.rotations, expected, atol=1e-6)


def _kill_child(solver: SubprocessSolver) -> None:
    pid = solver._get_pool().submit(os.getpid).result(timeout=120)
    os.kill(pid, signal.SIGKILL)


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")
def test_a_dead_child_is_explained_and_replaced() -> None:
    R = random_rotations(5, np.random.default_rng(1))
    g = ViewGraph()
    for a in range(4):
        g.add_edge(a, a + 1, R[a] @ R[a + 1].T)
    options = SolverOptions.from_flat(mode="sparse")
    solver = SubprocessSolver()
    try:
        # Dies before its first solve: what a script without a __main__ guard causes.
        _kill_child(solver)
        with pytest.raises(RuntimeError, match=r"before returning its first solve.*__main__"):
            solver(g, 0, options)
        assert np.allclose(solver(g, 0, options).rotations, R @ R[0].T, atol=1e-6)
        _kill_child(solver)  # dies after a solve: killed or out of memory
        with pytest.raises(RuntimeError, match="died during the solve"):
            solver(g, 0, options)
        assert np.allclose(solver(g, 0, options).rotations, R @ R[0].T, atol=1e-6)
    finally:
        solver.close()


def test_abort_ends_a_running_solve_at_once_and_the_next_one_gets_a_new_child() -> None:
    rng = np.random.default_rng(1)
    n = 60
    R = random_rotations(n, rng)
    g = ViewGraph()
    for a in range(n):
        for b in range(a + 1, n, 3):
            g.add_edge(a, b, R[a] @ R[b].T)
    solver = SubprocessSolver()
    errors: list[BaseException] = []

    def solve_long() -> None:
        try:
            solver(g, 0, SolverOptions.from_flat(mode="dense", iterations=10_000_000,
                                                 depths=(2,)))
        except BaseException as exc:  # noqa: BLE001 - recorded for the assertion
            errors.append(exc)

    worker = threading.Thread(target=solve_long)
    try:
        worker.start()
        deadline = time.monotonic() + 60
        while not solver.child_pids() and time.monotonic() < deadline:
            time.sleep(0.01)
        pids = solver.child_pids()
        assert pids
        time.sleep(1.0)  # the child imports the solver and starts
        t0 = time.monotonic()
        solver.abort()
        worker.join(10.0)
        elapsed = time.monotonic() - t0
        assert not worker.is_alive() and elapsed < 2.0
        assert len(errors) == 1 and isinstance(errors[0], RuntimeError)
        assert solver.child_pids() == []
        for pid in pids:  # reaped by the pool's manager thread, or at least dying
            deadline = time.monotonic() + 5
            while time.monotonic() < deadline:
                try:
                    os.kill(pid, 0)
                except OSError:
                    break
                if open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0] == "Z":
                    break
                time.sleep(0.05)
            else:
                pytest.fail(f"solver child {pid} still runs after abort")
        res = solver(g, 0, SolverOptions.from_flat(mode="sparse"))  # a new child
        expected = R[np.asarray(res.node_ids, dtype=int)] @ R[0].T
        assert np.allclose(res.rotations, expected, atol=1e-6)
    finally:
        solver.close()


def _gone(pid: int) -> bool:
    """Whether process ``pid`` has exited (a zombie nobody reaped counts as exited)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="reads /proc")
def test_the_child_exits_when_its_parent_is_killed() -> None:
    # A node killed outright (SIGKILL, the OOM killer) cannot shut its child down, and the
    # child, blocked on its work queue, used to stay forever with the solver's memory.
    script = ("import os, time\n"
              "from rotavg_ros.app.solver_process import SubprocessSolver\n"
              "s = SubprocessSolver()\n"
              "print(s._get_pool().submit(os.getpid).result(timeout=120), flush=True)\n"
              "time.sleep(600)\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        filter(None, [str(Path(__file__).resolve().parents[1]), os.environ.get("PYTHONPATH")])))
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE,
                              text=True, env=env)
    try:
        assert parent.stdout is not None
        child = int(parent.stdout.readline())
        assert not _gone(child)
        parent.kill()
        parent.wait(timeout=10)
        deadline = time.monotonic() + 10 * PARENT_CHECK_PERIOD
        while not _gone(child) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert _gone(child), "the solver child outlived its killed parent"
    finally:
        parent.kill()
