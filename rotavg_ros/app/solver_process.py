"""The solver's child process: solves run there so the node's callbacks keep the interpreter."""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Hashable, Mapping
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from rotavg_ros.app.session import run_solver
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.result import SolveResult
from rotavg_ros.core.types import FloatArray
from rotavg_ros.core.view_graph import ViewGraph


class SubprocessSolver:
    """Runs :func:`run_solver` in one persistent child process (spawned on first use).

    A solve is Python-heavy (an optimiser loop of small torch ops); in a thread it would
    hold the interpreter lock often enough to starve the node's subscriptions. In a child
    process it competes only for CPU, and ``niceness`` (added to the child's nice value,
    POSIX only) makes it yield that CPU to the node and to whatever runs beside it (a SLAM
    front end): a solve then uses the cores nobody else wants. The child keeps torch loaded
    between solves. If the child dies, that solve raises and the next one starts a new child.
    """

    def __init__(self, niceness: int = 0) -> None:
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()
        self._niceness = niceness
        self._solved = 0  # solves the current child has returned

    def _get_pool(self) -> ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                self._solved = 0
                self._pool = ProcessPoolExecutor(
                    max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                    initializer=_init_child, initargs=(self._niceness,))
            return self._pool

    def __call__(
        self, graph: ViewGraph, anchor: Hashable | None, options: SolverOptions,
        initial: Mapping[Any, FloatArray] | None = None,
        initial_depth: int | None = None,
    ) -> SolveResult:
        pool = self._get_pool()
        options = options.replace_flat(progress=None)  # callables do not pickle
        try:
            result = pool.submit(run_solver, graph, anchor, options,
                                 dict(initial) if initial else None, initial_depth).result()
        except BrokenProcessPool as exc:
            with self._lock:
                self._pool = None
                first = self._solved == 0
            if first:
                raise RuntimeError(
                    "the solver child process died before returning its first solve. A "
                    "script that creates RotavgNode must do so under `if __name__ == "
                    "\"__main__\":` (the child is started with multiprocessing 'spawn', which "
                    "re-imports the main module) or set solve_in_subprocess:=false; otherwise "
                    "the child was killed or ran out of memory") from exc
            raise RuntimeError("the solver child process died during the solve (killed, or "
                               "out of memory?); the next solve starts a new one") from exc
        with self._lock:
            self._solved += 1
        return result

    def warm_up(self) -> None:
        """Start the child and import the solver there, ahead of the first solve."""
        self._get_pool().submit(_import_solver)

    def child_pids(self) -> list[int]:
        """Process ids of the current child (none before the first use or after abort).

        Takes no lock: safe to call from a signal handler.
        """
        pool = self._pool
        processes = getattr(pool, "_processes", None) or {}
        return [proc.pid for proc in list(processes.values()) if proc.pid is not None]

    def abort(self) -> None:
        """Terminate the child now: a running solve raises ``RuntimeError`` at once and the
        next solve starts a new child. For a shutdown that must not wait for a long solve."""
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is None:
            return
        # ProcessPoolExecutor has no public way to stop a running call before Python 3.14
        # (terminate_workers); its _processes map is the one it keeps since Python 3.2.
        for proc in list((getattr(pool, "_processes", None) or {}).values()):
            proc.terminate()
        # Quick once the child is gone; waiting lets the pool release its queues (else the
        # resource tracker warns about leaked semaphores at exit).
        pool.shutdown(wait=True, cancel_futures=True)

    def close(self) -> None:
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)


def _import_solver() -> None:
    import rotavg_ros.core.solver  # noqa: F401


PARENT_CHECK_PERIOD = 1.0
"""Seconds between the child's checks that its parent is still alive."""


def _init_child(niceness: int) -> None:
    """Child-process initializer: raise the nice value by ``niceness``; ignore SIGINT; exit
    when the parent is gone.

    A Ctrl-C in a terminal reaches the whole process group; the parent handles it and
    shuts this child down, so the child need not die mid-queue with a traceback. A parent
    killed outright (SIGKILL, the OOM killer) cannot: the child would wait for work forever
    (it holds its own end of the work queue, so the queue never reports the parent gone),
    keeping the solver's memory. A daemon thread watches for that and ends the child.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if niceness > 0 and hasattr(os, "nice"):
        os.nice(niceness)
    parent = os.getppid()
    threading.Thread(target=_exit_when_orphaned, args=(parent,), daemon=True,
                     name="parent_watch").start()


def _exit_when_orphaned(parent: int) -> None:
    """End this process once its parent is no longer ``parent`` (it died: re-parented)."""
    while os.getppid() == parent:
        time.sleep(PARENT_CHECK_PERIOD)
    os._exit(1)

