"""One solve of a graph snapshot (anchor, warm start, solver call) and what the node keeps.

Conventions: ``R_i`` world-to-node, edges ``R_ij ~= R_i R_j^T``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass
from enum import Enum
from typing import Any

from rotavg_ros.app.accumulator import GraphSnapshot
from rotavg_ros.app.parameters import Settings
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.result import SolveResult
from rotavg_ros.core.types import FloatArray
from rotavg_ros.core.view_graph import ViewGraph

SolveFn = Callable[[ViewGraph, Hashable | None, SolverOptions], SolveResult]
"""``(graph, anchor, options) -> SolveResult``; a test hook that replaces the solver."""
Runner = Callable[
    [ViewGraph, Hashable | None, SolverOptions, Mapping[Hashable, FloatArray] | None,
     int | None],
    SolveResult,
]
"""``(graph, anchor, options, initial, initial_depth) -> SolveResult``."""


def default_solve(graph: ViewGraph, anchor: Hashable | None, options: SolverOptions) -> SolveResult:
    """Run the filtered-DMF solver (imported lazily: it pulls in torch)."""
    return run_solver(graph, anchor, options)


def run_solver(
    graph: ViewGraph, anchor: Hashable | None, options: SolverOptions,
    initial: Mapping[Any, FloatArray] | None = None, initial_depth: int | None = None,
) -> SolveResult:
    """In-process :meth:`RotationAverager.solve`, optionally warm-started."""
    from rotavg_ros.core.solver import RotationAverager

    return RotationAverager(options).solve(
        graph, anchor=anchor, initial=initial, initial_depth=initial_depth)


@dataclass(frozen=True)
class WarmStart:
    """Where a solve starts: known world-to-node rotations by node id, and the DMF depth
    that found them (None: the first candidate depth)."""

    rotations: Mapping[Any, FloatArray]
    depth: int | None = None

    @staticmethod
    def of(result: SolveResult | None) -> WarmStart | None:
        """The warm start a solve's result gives the next solve (None for no result)."""
        if result is None:
            return None
        return WarmStart(dict(zip(result.node_ids, result.rotations, strict=True)),
                         result.depth or None)


def _runner_fn(runner: Runner, warm: WarmStart | None) -> SolveFn:
    """A :data:`SolveFn` that calls ``runner``, warm-started from ``warm`` if given."""
    if warm is None or not warm.rotations:
        return lambda graph, anchor, options: runner(graph, anchor, options, None, None)
    return lambda graph, anchor, options: runner(graph, anchor, options, warm.rotations,
                                                 warm.depth)


class SolveStatus(str, Enum):
    """How an attempt to solve a snapshot ended (the value is the stable text key)."""

    SOLVED = "solved"
    NO_EDGES = "no_edges"
    ANCHOR_MISSING = "anchor_missing"
    FAILED = "failed"

    def __str__(self) -> str:
        return self.value


# Module-level names of the statuses, for readable comparisons.
SOLVED = SolveStatus.SOLVED
NO_EDGES = SolveStatus.NO_EDGES
ANCHOR_MISSING = SolveStatus.ANCHOR_MISSING
FAILED = SolveStatus.FAILED


@dataclass(frozen=True)
class SolveAttempt:
    """What solving one snapshot gave; nothing is published here."""

    status: SolveStatus
    result: SolveResult | None = None
    anchor: Hashable | None = None
    duration_s: float = math.nan
    error: str = ""
    """``"<ExceptionType>: <text>"`` when the solver raised."""
    anchor_warning: str = ""

    @property
    def success(self) -> bool:
        return self.status == SOLVED

    @property
    def message(self) -> str:
        """One line, as the node's ``~/solve`` answers."""
        if self.status == NO_EDGES:
            return "no edges yet"
        if self.status == ANCHOR_MISSING:
            return self.anchor_warning
        if self.status == FAILED:
            return f"solve failed: {self.error}"
        result = self.result
        assert result is not None
        return (
            f"solved {len(result.node_ids)} nodes in {len(result.anchors)} component(s) "
            f"in {self.duration_s:.3f} s (depth {result.depth}, {result.num_filtered} filtered)"
        )


def choose_anchor(graph: ViewGraph, first_node: Hashable | None,
                  anchor_frame: str) -> tuple[Hashable | None, str]:
    """``(anchor, warning)``: ``anchor_frame`` if set (warning if not seen yet), else the
    first frame accepted."""
    if anchor_frame:
        if not graph.has_node(anchor_frame):
            return None, f"anchor frame {anchor_frame!r} not seen yet"
        return anchor_frame, ""
    return first_node, ""


def solve_snapshot(
    snap: GraphSnapshot, settings: Settings, solve_fn: SolveFn | None = None,
    warm: WarmStart | None = None, runner: Runner | None = None,
) -> SolveAttempt:
    """Choose the anchor and solve ``snap.graph`` with ``settings.solver``.

    ``solve_fn`` (a test hook) replaces the solver outright. Otherwise ``runner`` (default
    :func:`run_solver`, in process; the node passes a :class:`SubprocessSolver`) solves,
    warm-started from ``warm`` when ``settings.warm_start`` (the previous result's, see
    :meth:`WarmStart.of`, or the orientations and depth stored in a graph file).
    Never raises for a solver error: that is ``SolveStatus.FAILED`` with the exception
    text.
    """
    graph = snap.graph
    if graph.num_nodes == 0:
        return SolveAttempt(NO_EDGES)
    anchor, warning = choose_anchor(graph, snap.first_node, settings.anchor_frame)
    if warning:
        return SolveAttempt(ANCHOR_MISSING, anchor_warning=warning)
    fn = solve_fn if solve_fn is not None else _runner_fn(
        runner or run_solver, warm if settings.warm_start else None)
    t0 = time.perf_counter()
    try:
        result = fn(graph, anchor, settings.solver)
    except Exception as exc:  # noqa: BLE001 - reported as a failed attempt
        return SolveAttempt(FAILED, anchor=anchor, duration_s=time.perf_counter() - t0,
                            error=f"{type(exc).__name__}: {exc}")
    return SolveAttempt(SOLVED, result=result, anchor=anchor,
                        duration_s=time.perf_counter() - t0)


@dataclass
class SolveBookkeeping:
    """What the node remembers about its solves (feeds the diagnostics)."""

    last_result: SolveResult | None = None
    last_solved_version: int = -1
    last_duration_s: float = math.nan
    last_error: str = ""
    anchor_warning: str = ""
    solves_ok: int = 0
    solves_failed: int = 0
    skipped_busy: int = 0

    def record(self, attempt: SolveAttempt, version: int) -> None:
        """Update after an attempt on the snapshot taken at graph ``version``."""
        if attempt.status == NO_EDGES:
            self.last_result = None
            self.anchor_warning = ""
        elif attempt.status == ANCHOR_MISSING:
            self.anchor_warning = attempt.anchor_warning
        elif attempt.status == FAILED:
            self.anchor_warning = ""
            self.last_duration_s = attempt.duration_s
            self.last_error = attempt.error
            self.solves_failed += 1
        else:
            self.anchor_warning = ""
            self.last_result = attempt.result
            self.last_solved_version = version
            self.last_duration_s = attempt.duration_s
            self.last_error = ""
            self.solves_ok += 1

    def reset(self) -> None:
        """After ``~/reset``: forget the result, errors and warnings (counters stay)."""
        self.last_result = None
        self.last_error = ""
        self.anchor_warning = ""

