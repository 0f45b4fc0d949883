"""ROS-free core of ``rotavg_node``: parameters -> settings, snapshot -> solve, diagnostics.

The live node (:mod:`rotavg_ros.node`) and the offline bag replay (:mod:`rotavg_ros.replay`)
must turn the same messages into the same orientations. Everything they share that does not
need rclpy lives here:

* :data:`PARAMETER_DEFAULTS`, :func:`validate_parameter` and :func:`settings_from_parameters`:
  the node's parameters (names, defaults, checks) and the :class:`Settings` built from them.
* :func:`make_accumulator`: the :class:`~rotavg_ros.accumulator.EdgeAccumulator` with every
  rejection reason and note pre-seeded (so reports list them all).
* :func:`solve_snapshot`: anchor choice + solve of one graph snapshot, without publishing.
* :class:`SolveBookkeeping` and :func:`diagnostic_values`: what the node remembers about its
  solves and the ``/diagnostics`` key/values, level and message built from it.
* :func:`grid_layout`, :func:`node_to_world_quaternions`, :func:`format_diagnostic_value`:
  pure helpers of the output builders (rclpy ones in ``msg_adapters.outputs``, rosbags ones
  in :mod:`rotavg_ros.bag_outputs`).

Conventions: ``R_i`` world-to-node, edges ``R_ij ~= R_i R_j^T``; outputs carry the
node-to-world rotation ``R_i^T`` (``header.frame_id = world_frame``, ``child_frame_id = i``).
"""

from __future__ import annotations

import dataclasses
import math
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Hashable, Mapping
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from msg_adapters.inputs import (
    ADAPTER_REASONS,
    DEFAULT_REFERENCE_VARIANCE,
    NOTE_KEYS,
    AdapterConfig,
)
from rotavg_ros.accumulator import (
    INVALID_MEASUREMENT,
    AccumulatorStats,
    EdgeAccumulator,
    GraphSnapshot,
)
from rotavg_ros.so3 import matrix_to_quat
from rotavg_ros.solver_types import SolveResult, SolverOptions
from rotavg_ros.view_graph import RepeatPolicy, ViewGraph

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

SolveFn = Callable[[ViewGraph, Hashable | None, SolverOptions], SolveResult]
Runner = Callable[
    [ViewGraph, Hashable | None, SolverOptions, Mapping[Hashable, NDArray[np.float64]] | None,
     int | None],
    SolveResult,
]
"""``(graph, anchor, options, initial, initial_depth) -> SolveResult``."""
"""``(graph, anchor, options) -> SolveResult``; the default runs :class:`RotationAverager`."""

NODE_NAME = "rotavg_node"
MAX_DETACHED_LISTED = 20

_SOLVER_DEFAULTS = SolverOptions()

PARAMETER_DEFAULTS: dict[str, Any] = {
    "world_frame": "world",
    "anchor_frame": "",
    "solve_period": 1.0,
    "repeat_policy": "merge",
    "quaternion_tolerance": 1e-3,
    "reference_variance": DEFAULT_REFERENCE_VARIANCE,
    "min_weight": 1e-3,
    "max_weight": 1e3,
    "mode": _SOLVER_DEFAULTS.mode,
    "depths": list(_SOLVER_DEFAULTS.depths),
    "iterations": _SOLVER_DEFAULTS.iterations,
    "sigma": _SOLVER_DEFAULTS.sigma,
    "seed": 0,
    "warm_start": True,
    "solve_in_subprocess": True,
    "solver_niceness": 10,
    "graph_file": "",
    "device": "cpu",
    "threads": 0,
    "publish_markers": True,
    "marker_spacing": 1.0,
    "residual_warn_deg": 5.0,
    "qos_depth": 10000,
    "orientations_qos_depth": 10000,
}
"""Every ``rotavg_node`` parameter and its default (the node adds descriptors and ranges)."""


class Level(IntEnum):
    """``diagnostic_msgs/DiagnosticStatus`` levels as ints (the message field is a byte).

    Re-exported by ``msg_adapters.outputs``.
    """

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3


def validate_parameter(name: str, value: Any) -> str | None:
    """Reason why ``value`` is not acceptable for parameter ``name``, or None.

    The solver parameters (``mode``, ``depths``, ``iterations``, ``sigma``, ``device``, ...)
    are checked together by :meth:`SolverOptions.validate` in :func:`settings_from_parameters`.
    """
    if name == "repeat_policy":
        try:
            RepeatPolicy(value)
        except ValueError:
            return f"repeat_policy must be one of merge, latest, first; got {value!r}"
    elif name == "world_frame":
        if not value or value.startswith("/") or not value.isprintable() or " " in value:
            return f"world_frame must be a non-empty tf2 frame id; got {value!r}"
    elif name in ("min_weight", "max_weight", "reference_variance", "marker_spacing"):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            return f"{name} must be a finite number > 0; got {value!r}"
    return None


@dataclass(frozen=True)
class Settings:
    """Parameter values as used by the node and the replay."""

    world_frame: str
    anchor_frame: str
    publish_markers: bool
    marker_spacing: float
    residual_warn_deg: float
    adapter: AdapterConfig
    solver: SolverOptions
    warm_start: bool = True


def solver_options_from_parameters(p: Mapping[str, Any]) -> SolverOptions:
    """The node's :class:`SolverOptions` (fields without a parameter keep their default)."""
    threads = int(p["threads"])
    return SolverOptions(
        mode=str(p["mode"]),
        depths=tuple(int(d) for d in p["depths"]),
        iterations=int(p["iterations"]),
        sigma=float(p["sigma"]),
        seed=int(p["seed"]),
        device=str(p["device"]),
        threads=threads if threads > 0 else None,
    )


def settings_from_parameters(
    values: Mapping[str, Any], solver: SolverOptions | None = None
) -> Settings:
    """:class:`Settings` from parameter values (missing names take their default).

    ``solver`` replaces the options built from the solver parameters (the replay passes the
    ones from its command line). Raises ``ValueError`` for an invalid value or
    ``min_weight > max_weight``.
    """
    unknown = set(values) - set(PARAMETER_DEFAULTS)
    if unknown:
        raise ValueError(f"unknown parameter(s): {', '.join(sorted(unknown))}")
    p = {**PARAMETER_DEFAULTS, **values}
    for name, value in p.items():
        reason = validate_parameter(name, value)
        if reason is not None:
            raise ValueError(reason)
    if float(p["min_weight"]) > float(p["max_weight"]):
        raise ValueError("min_weight > max_weight")
    options = solver if solver is not None else solver_options_from_parameters(p)
    options.validate()
    return Settings(
        world_frame=str(p["world_frame"]),
        anchor_frame=str(p["anchor_frame"]),
        publish_markers=bool(p["publish_markers"]),
        marker_spacing=float(p["marker_spacing"]),
        residual_warn_deg=float(p["residual_warn_deg"]),
        adapter=AdapterConfig(
            quaternion_tolerance=float(p["quaternion_tolerance"]),
            reference_variance=float(p["reference_variance"]),
            min_weight=float(p["min_weight"]),
            max_weight=float(p["max_weight"]),
            reserved_frames=frozenset({str(p["world_frame"])}),
        ),
        solver=options,
        warm_start=bool(p["warm_start"]),
    )


def make_accumulator(repeat_policy: RepeatPolicy | str = RepeatPolicy.MERGE) -> EdgeAccumulator:
    """The node's accumulator: every adapter reason and note pre-seeded with zero."""
    return EdgeAccumulator(
        repeat_policy,
        reasons=(*ADAPTER_REASONS, INVALID_MEASUREMENT),
        note_keys=NOTE_KEYS,
    )


def default_solve(graph: ViewGraph, anchor: Hashable | None, options: SolverOptions) -> SolveResult:
    """Run the filtered-DMF solver (imported lazily: it pulls in torch)."""
    return run_solver(graph, anchor, options)


def run_solver(
    graph: ViewGraph, anchor: Hashable | None, options: SolverOptions,
    initial: Mapping[Any, FloatArray] | None = None, initial_depth: int | None = None,
) -> SolveResult:
    """In-process :meth:`RotationAverager.solve`, optionally warm-started."""
    from rotavg_ros.solver import RotationAverager

    return RotationAverager(options).solve(
        graph, anchor=anchor, initial=initial, initial_depth=initial_depth)


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
        options = dataclasses.replace(options, progress=None)  # callables do not pickle
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

    def close(self) -> None:
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)


def _import_solver() -> None:
    import rotavg_ros.solver  # noqa: F401


def _init_child(niceness: int) -> None:
    """Child-process initializer: raise the nice value by ``niceness``; ignore SIGINT.

    A Ctrl-C in a terminal reaches the whole process group; the parent handles it and
    shuts this child down, so the child need not die mid-queue with a traceback.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if niceness > 0 and hasattr(os, "nice"):
        os.nice(niceness)


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


# ---------------------------------------------------------------------- solving
NO_EDGES = "no_edges"
ANCHOR_MISSING = "anchor_missing"
FAILED = "failed"
SOLVED = "solved"


@dataclass(frozen=True)
class SolveAttempt:
    """What solving one snapshot gave; nothing is published here."""

    status: str
    """``solved``, ``no_edges``, ``anchor_missing`` or ``failed``."""
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
    Never raises for a solver error: that is ``status == "failed"`` with the exception text.
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


def diagnostic_name(node_name: str) -> str:
    return f"{node_name}: rotation averaging"


def inlier_residuals_deg(result: SolveResult) -> FloatArray:
    return np.asarray(result.residuals_deg)[np.asarray(result.edge_inlier, bool)]


def diagnostic_values(
    stats: AccumulatorStats, book: SolveBookkeeping, settings: Settings
) -> tuple[Level, str, dict[str, Any]]:
    """``(level, message, key/values)`` of the node's ``DiagnosticStatus``."""
    result = book.last_result
    values: dict[str, Any] = {
        "nodes": stats.num_nodes,
        "measurements": stats.num_measurements,
        "edges_received": stats.received,
        "edges_accepted": stats.accepted,
        "edges_rejected": stats.num_rejected,
    }
    values.update(stats.rejected)
    values.update(stats.notes)
    problems: list[str] = []
    level = Level.OK
    if result is not None:
        inlier = inlier_residuals_deg(result)
        median = float(np.median(inlier)) if inlier.size else math.nan
        num_components = len(result.anchors)
        detached = describe_detached(result)
        values.update({
            "solved_nodes": len(result.node_ids),
            "solved_edges": int(np.asarray(result.residuals_deg).size),
            "anchor": str(result.anchors[0]) if result.anchors else "",
            "components": num_components,
            "detached_components": detached or "none",
            "filtered_outliers": result.num_filtered,
            "depth": result.depth,
            "residual_median_deg": median,
            "residual_mean_deg": float(np.mean(inlier)) if inlier.size else math.nan,
            "residual_max_deg": float(np.max(inlier)) if inlier.size else math.nan,
        })
        if num_components > 1:
            level = Level.WARN
            problems.append(f"{num_components - 1} component(s) not connected to the anchor")
        if math.isfinite(median) and median > settings.residual_warn_deg:
            level = Level.WARN
            problems.append(
                f"median residual {median:.2f} deg > {settings.residual_warn_deg:g} deg"
            )
    values.update({
        "last_solve_duration_s": book.last_duration_s,
        "graph_version": stats.version,
        "solved_version": book.last_solved_version,
        "solves_completed": book.solves_ok,
        "solves_failed": book.solves_failed,
        "timer_ticks_skipped_busy": book.skipped_busy,
        "last_error": book.last_error or "none",
    })
    if book.anchor_warning:
        level = max(level, Level.WARN)
        problems.insert(0, book.anchor_warning)
    if book.last_error:
        level = Level.ERROR
        problems.insert(0, f"last solve failed ({book.last_error}); keeping last result")
    if problems:
        message = "; ".join(problems)
    elif result is None:
        message = "waiting for edges"
    else:
        message = f"{len(result.node_ids)} nodes solved"
    return level, message, values


def describe_detached(result: SolveResult) -> str:
    """``"anchor_a (5 nodes), anchor_b (2 nodes)"`` for components other than 0."""
    component = np.asarray(result.component)
    sizes = np.bincount(component, minlength=len(result.anchors))
    parts = [
        f"{result.anchors[c]} ({int(sizes[c])} nodes)"
        for c in range(1, min(len(result.anchors), MAX_DETACHED_LISTED + 1))
    ]
    if len(result.anchors) - 1 > MAX_DETACHED_LISTED:
        parts.append(f"... {len(result.anchors) - 1 - MAX_DETACHED_LISTED} more")
    return ", ".join(parts)


# ---------------------------------------------------------------------- output helpers
def node_to_world_quaternions(rotations: FloatArray) -> FloatArray:
    """``(N, 4)`` quaternions (x, y, z, w) of ``R_i^T`` for world-to-node ``rotations``."""
    R = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    return matrix_to_quat(np.swapaxes(R, 1, 2))


def grid_layout(component: IntArray, spacing: float = 1.0) -> FloatArray:
    """``(N, 3)`` marker positions: each component on its own square grid in the z=0 plane.

    Component 0 (the anchor's) starts at the origin; the next components follow along +x with
    a gap of two ``spacing``. Inside a component, nodes keep their index order row by row.
    """
    comp = np.asarray(component, dtype=np.int64).reshape(-1)
    pos = np.zeros((comp.size, 3))
    x0 = 0.0
    for label in np.unique(comp):
        idx = np.flatnonzero(comp == label)
        cols = max(1, math.ceil(math.sqrt(idx.size)))
        k = np.arange(idx.size)
        pos[idx, 0] = x0 + (k % cols) * spacing
        pos[idx, 1] = -(k // cols) * spacing
        x0 += (cols + 1) * spacing
    return pos


def format_diagnostic_value(value: Any) -> str:
    """Floats with 6 significant digits, booleans ``true``/``false``, lists comma-separated."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(format_diagnostic_value(v) for v in value)
    return str(value)
