"""``rotavg_node``: live rotation averaging over ROS 2 topics (rclpy).

Conventions
-----------
* ``R_i`` is the **world-to-node** rotation of node (frame) ``i``; an edge carries
  ``R_ij ~= R_i R_j^T``.
* Input: a ``geometry_msgs/msg/TransformStamped`` with ``header.frame_id = i`` and
  ``child_frame_id = j`` whose rotation is frame ``j``'s orientation in frame ``i`` (the TF
  convention) *is* ``R_ij``. ``nav_msgs/msg/Odometry`` is read the same way
  (``pose.pose.orientation``), its rotation covariance sets the edge weight. Translations are
  ignored. See :mod:`msg_adapters.inputs` for validation and the weight mapping; an edge that
  names ``world_frame`` itself is rejected (``reserved_frame_id``): it would publish
  ``world_frame -> world_frame``.
* Output: node-to-world ``R_i^T`` as ``TransformStamped`` with
  ``header.frame_id = world_frame`` and ``child_frame_id = i`` (tf2-ready; zero translation).

Interfaces (relative names live under the node's name, e.g. ``/rotavg_node/edges``)
-------------------------------------------------------------------------------------
* Subscriptions: ``~/edges`` (TransformStamped), ``~/edges_with_covariance`` (Odometry);
  reliable, KEEP_LAST ``qos_depth`` (1000).
* Publishers: ``~/orientations`` (TransformStamped, one per node per solve; reliable,
  KEEP_LAST ``orientations_qos_depth``), ``~/markers`` (MarkerArray), ``/diagnostics``
  (DiagnosticArray).
* Services (std_srvs/srv/Trigger): ``~/solve`` solves now and answers after the result has
  been published (``success`` false when there is nothing to solve or the solve failed);
  ``~/reset`` clears the graph and the counters.

Solving
-------
A timer fires every ``solve_period`` seconds and starts a solve only if the graph's version
changed since the last attempt. Solves run on one worker thread
(``ThreadPoolExecutor(max_workers=1)``), never on the executor thread, so subscriptions keep
being served; edges that arrive during a solve go into the live graph and into the next solve.
At most one solve runs at a time and timer solves never stack: a tick that finds a solve
running is skipped and counted (``timer_ticks_skipped_busy``). A ``~/solve`` request queues at
most one extra solve behind the running one (concurrent requests share it), so its answer
reflects every edge accepted before the request.

Every output of a solve (orientations, markers, diagnostics) carries the same stamp: the node
clock's time when the graph snapshot for that solve was taken. Between solves, the timer
republishes the diagnostics (stamped now) only when the counters moved, e.g. after rejections.

Diagnostics (one ``DiagnosticStatus`` named ``"<node name>: rotation averaging"``, hardware_id
= the node's fully qualified name): ``nodes``, ``measurements``, ``edges_received``,
``edges_accepted``, ``edges_rejected``, one key per rejection reason (the adapters' reason
strings, e.g. ``zero_quaternion``), ``default_weight_covariance``, ``clamped_weight``; after a
solve ``solved_nodes``, ``solved_edges``, ``anchor``, ``components``, ``detached_components``,
``filtered_outliers``, ``depth``, ``residual_{median,mean,max}_deg`` (inlier edges); and
``last_solve_duration_s``, ``graph_version``, ``solved_version``, ``solves_completed``,
``solves_failed``, ``timer_ticks_skipped_busy``, ``last_error``. Level: ERROR while the last
solve raised; WARN for detached components, a median inlier residual above
``residual_warn_deg`` or an ``anchor_frame`` not seen yet; OK otherwise.

If the solver raises, the diagnostics turn ERROR with the exception text, the last good
orientations are kept (nothing new is published) and edges keep being accepted; the graph is
solved again once it changes. ``~/reset`` during a solve makes the node discard that result.

Anchor and components
---------------------
``anchor_frame`` fixes the gauge: that frame gets identity. Empty (default) means the first
frame ever accepted (``header.frame_id`` of the first valid edge). If ``anchor_frame`` is set
but not seen yet, nothing is solved (diagnostics WARN) until it appears. Components that are
not connected to the anchor are solved on their own, each with its own anchor = identity, and
are still published under ``world_frame``; their rotations are not related to the anchor
component's. The diagnostics turn WARN and list them (``detached_components``), and the
markers draw them in the ``detached_*`` namespaces with muted colours.

Executors
---------
The node works under ``SingleThreadedExecutor`` (what ``main`` uses) and
``MultiThreadedExecutor``. ``~/solve`` is a coroutine callback that awaits the worker's future
without blocking the executor (the worker wakes the executor with a guard condition when it
finishes), so even a single-threaded executor keeps serving subscriptions while a service
request waits for its solve. Subscriptions share one mutually exclusive callback group
(messages are ingested one at a time, in order — this matters for ``repeat_policy`` latest /
first); the timer and services use a reentrant group and coordinate through a lock.
"""

from __future__ import annotations

import concurrent.futures
import math
import threading
import time
from collections.abc import Callable, Generator, Hashable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from msg_adapters.inputs import (
    ADAPTER_REASONS,
    DEFAULT_REFERENCE_VARIANCE,
    NOTE_KEYS,
    AdapterConfig,
    edge_from_odometry,
    edge_from_transform,
)
from msg_adapters.outputs import (
    Level,
    clear_markers,
    diagnostic_array,
    diagnostic_status,
    orientation_markers,
    orientation_transforms,
)
from rotavg_ros.accumulator import (
    INVALID_MEASUREMENT,
    AccumulatorStats,
    EdgeAccumulator,
    EdgeMeasurement,
    Rejection,
)
from rotavg_ros.solver_types import SolveResult, SolverOptions
from rotavg_ros.view_graph import RepeatPolicy, ViewGraph

SolveFn = Callable[[ViewGraph, Hashable | None, SolverOptions], SolveResult]
"""``(graph, anchor, options) -> SolveResult``; the default runs :class:`RotationAverager`."""

NODE_NAME = "rotavg_node"
MAX_DETACHED_LISTED = 20


def default_solve(graph: ViewGraph, anchor: Hashable | None, options: SolverOptions) -> SolveResult:
    """Run the filtered-DMF solver (imported lazily: it pulls in torch)."""
    from rotavg_ros.solver import RotationAverager

    return RotationAverager(options).solve(graph, anchor=anchor)


def _warm_import() -> None:
    try:
        import rotavg_ros.solver  # noqa: F401
    except Exception:  # noqa: BLE001 - reported by the first solve instead
        pass


@dataclass(frozen=True)
class Settings:
    """Parameter values as used by the node (refreshed after every successful set)."""

    world_frame: str
    anchor_frame: str
    publish_markers: bool
    marker_spacing: float
    residual_warn_deg: float
    adapter: AdapterConfig
    solver: SolverOptions


@dataclass(frozen=True)
class SolveOutcome:
    """What one solve job did; ``~/solve`` answers with it."""

    success: bool
    message: str


class _AwaitFuture:
    """Awaitable for a ``concurrent.futures.Future`` inside an rclpy coroutine callback.

    rclpy re-runs a pending coroutine task on every executor wake-up; the worker triggers a
    guard condition when it finishes so that wake-up happens promptly.
    """

    def __init__(self, future: concurrent.futures.Future[SolveOutcome]) -> None:
        self._future = future

    def __await__(self) -> Generator[None, None, SolveOutcome]:
        while not self._future.done():
            yield
        return self._future.result()


def _descriptor(
    description: str,
    *,
    fp_range: tuple[float, float] | None = None,
    int_range: tuple[int, int] | None = None,
    read_only: bool = False,
    constraints: str = "",
) -> ParameterDescriptor:
    desc = ParameterDescriptor(
        description=description, read_only=read_only, additional_constraints=constraints
    )
    if fp_range is not None:
        desc.floating_point_range = [
            FloatingPointRange(from_value=fp_range[0], to_value=fp_range[1], step=0.0)
        ]
    if int_range is not None:
        desc.integer_range = [IntegerRange(from_value=int_range[0], to_value=int_range[1], step=0)]
    return desc


_SOLVER_DEFAULTS = SolverOptions()

# name -> (default, descriptor). Every parameter the node has; see config/rotavg.yaml.
PARAMETERS: dict[str, tuple[Any, ParameterDescriptor]] = {
    "world_frame": ("world", _descriptor(
        "Frame id of the published orientations' header (the parent frame in TF).",
        constraints="non-empty frame id without '/' prefix")),
    "anchor_frame": ("", _descriptor(
        "Frame that gets the identity rotation; empty = the first frame accepted.")),
    "solve_period": (1.0, _descriptor(
        "Seconds between timer checks; a solve starts only if the graph changed.",
        fp_range=(0.01, 3600.0), read_only=True)),
    "repeat_policy": ("merge", _descriptor(
        "How repeated measurements of one frame pair combine: merge (robust average, weights "
        "add), latest (newest wins) or first (oldest wins).",
        read_only=True, constraints="one of: merge, latest, first")),
    "quaternion_tolerance": (1e-3, _descriptor(
        "Accepted | |q| - 1 |; within it the quaternion is normalised, beyond it the edge is "
        "rejected as non_unit_quaternion.", fp_range=(0.0, 0.5))),
    "reference_variance": (DEFAULT_REFERENCE_VARIANCE, _descriptor(
        "Per-axis rotation variance (rad^2) of an Odometry edge that gets weight 1; "
        "weight = 3 * reference_variance / trace(rotation covariance). Default (1 deg)^2.",
        fp_range=(1e-12, 10.0))),
    "min_weight": (1e-3, _descriptor(
        "Lower clamp of covariance-derived edge weights.", fp_range=(1e-9, 1e9))),
    "max_weight": (1e3, _descriptor(
        "Upper clamp of covariance-derived edge weights.", fp_range=(1e-9, 1e9))),
    "mode": (_SOLVER_DEFAULTS.mode, _descriptor(
        "Solver variant: dense (the paper's DMF), sparse (chordal warm start + Huber + "
        "L-BFGS, for chain-like SLAM graphs) or auto (by mean degree).",
        constraints="one of: auto, dense, sparse")),
    "depths": (list(_SOLVER_DEFAULTS.depths), _descriptor(
        "Candidate DMF depths (positive, even); the one with the lowest cost wins.",
        constraints="non-empty list of positive even integers")),
    "iterations": (_SOLVER_DEFAULTS.iterations, _descriptor(
        "Gradient iterations of the DMF optimisation per depth.", int_range=(1, 10_000_000))),
    "sigma": (_SOLVER_DEFAULTS.sigma, _descriptor(
        "Spanning-tree filter threshold on the chordal distance d_chord(R_ij, R_ij^tree).",
        fp_range=(0.0, 2.83))),
    "seed": (0, _descriptor("Random seed of the solver.", int_range=(0, 2**31 - 1))),
    "device": ("cpu", _descriptor(
        "Torch device of the solver, e.g. cpu or cuda:0.", constraints="torch device string")),
    "threads": (0, _descriptor(
        "Torch CPU threads for the solver; 0 = torch's default.", int_range=(0, 1024))),
    "publish_markers": (True, _descriptor("Publish ~/markers (RViz MarkerArray) after solves.")),
    "marker_spacing": (1.0, _descriptor(
        "Grid spacing (m) of the marker layout (there are no translations to show).",
        fp_range=(0.01, 100.0))),
    "residual_warn_deg": (5.0, _descriptor(
        "Diagnostics turn WARN when the median inlier residual exceeds this (deg).",
        fp_range=(0.0, 180.0))),
    "qos_depth": (1000, _descriptor(
        "KEEP_LAST depth of the reliable edge subscriptions.",
        int_range=(1, 1_000_000), read_only=True)),
    "orientations_qos_depth": (10000, _descriptor(
        "KEEP_LAST depth of ~/orientations; a solve publishes one message per node, so keep "
        "it at least the number of nodes.", int_range=(1, 10_000_000), read_only=True)),
}


def _validate(name: str, value: Any) -> str | None:
    """Reason why ``value`` is not acceptable for parameter ``name``, or None."""
    if name == "repeat_policy":
        try:
            RepeatPolicy(value)
        except ValueError:
            return f"repeat_policy must be one of merge, latest, first; got {value!r}"
    elif name == "mode":
        if value not in ("auto", "dense", "sparse"):
            return f"mode must be one of auto, dense, sparse; got {value!r}"
    elif name == "depths":
        depths = list(value)
        if not depths or any(int(d) <= 0 or int(d) % 2 for d in depths):
            return f"depths must be a non-empty list of positive even integers; got {depths}"
    elif name == "world_frame":
        if not value or value.startswith("/") or not value.isprintable() or " " in value:
            return f"world_frame must be a non-empty tf2 frame id; got {value!r}"
    elif name == "device":
        if not str(value).strip():
            return "device must not be empty"
    return None


class RotavgNode(Node):
    """ROS 2 node that averages relative rotations into absolute orientations.

    :param solve_fn: replaces the solver (tests inject slow or failing solvers here).
    :param node_name: node name (remapping with ``-r __node:=...`` still applies).
    :param kwargs: forwarded to :class:`rclpy.node.Node` (``context``, ``namespace``,
        ``parameter_overrides``, ``cli_args``, ...).
    """

    def __init__(
        self, *, solve_fn: SolveFn | None = None, node_name: str = NODE_NAME, **kwargs: Any
    ) -> None:
        super().__init__(node_name, **kwargs)
        for name, (default, descriptor) in PARAMETERS.items():
            self.declare_parameter(name, default, descriptor)
        for name in PARAMETERS:
            reason = _validate(name, self.get_parameter(name).value)
            if reason is not None:
                raise ValueError(reason)
        self._settings = self._read_settings()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)

        self._solve_fn: SolveFn = solve_fn if solve_fn is not None else default_solve
        self._acc = EdgeAccumulator(
            self.get_parameter("repeat_policy").value,
            reasons=(*ADAPTER_REASONS, INVALID_MEASUREMENT),
            note_keys=NOTE_KEYS,
        )

        # Scheduling state, guarded by _sched_lock.
        self._sched_lock = threading.Lock()
        self._current: concurrent.futures.Future[SolveOutcome] | None = None
        self._forced: concurrent.futures.Future[SolveOutcome] | None = None
        self._last_attempted_version = -1
        self._last_diag_received = -1
        self._skipped_busy = 0
        self._closing = False
        # Held from the worker's "was the graph reset?" check to the end of its publishing,
        # and by ~/reset: a reset never interleaves with the publication of a stale result.
        self._publish_lock = threading.Lock()
        # Solve bookkeeping, written by the worker only.
        self._last_result: SolveResult | None = None
        self._last_solved_version = -1
        self._last_duration_s = math.nan
        self._last_error = ""
        self._anchor_warning = ""
        self._solves_ok = 0
        self._solves_failed = 0

        self._pool = concurrent.futures.ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="rotavg_solver"
        )
        if solve_fn is None:
            self._pool.submit(_warm_import)

        self._ingest_group = MutuallyExclusiveCallbackGroup()
        self._control_group = ReentrantCallbackGroup()
        in_qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=self.get_parameter("qos_depth").value,
            reliability=ReliabilityPolicy.RELIABLE,
        )
        out_qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=self.get_parameter("orientations_qos_depth").value,
            reliability=ReliabilityPolicy.RELIABLE,
        )
        self._sub_tf = self.create_subscription(
            TransformStamped, "~/edges", self._on_transform, in_qos,
            callback_group=self._ingest_group,
        )
        self._sub_odom = self.create_subscription(
            Odometry, "~/edges_with_covariance", self._on_odometry, in_qos,
            callback_group=self._ingest_group,
        )
        self._pub_orientations = self.create_publisher(
            TransformStamped, "~/orientations", out_qos
        )
        self._pub_markers = self.create_publisher(MarkerArray, "~/markers", 10)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._srv_solve = self.create_service(
            Trigger, "~/solve", self._on_solve_request, callback_group=self._control_group
        )
        self._srv_reset = self.create_service(
            Trigger, "~/reset", self._on_reset_request, callback_group=self._control_group
        )
        self._wake = self.create_guard_condition(
            lambda: None, callback_group=self._control_group
        )
        self._timer = self.create_timer(
            self.get_parameter("solve_period").value, self._on_timer,
            callback_group=self._control_group,
        )
        self.get_logger().info(
            f"averaging rotations from {self._sub_tf.topic_name} and "
            f"{self._sub_odom.topic_name} into {self._pub_orientations.topic_name}"
        )

    # ------------------------------------------------------------------ public
    @property
    def accumulator(self) -> EdgeAccumulator:
        """The live edge store (thread-safe)."""
        return self._acc

    @property
    def last_result(self) -> SolveResult | None:
        """The last successful solve's result (None before the first one or after a reset)."""
        return self._last_result

    def request_solve(self) -> concurrent.futures.Future[SolveOutcome]:
        """Queue a solve (what ``~/solve`` does) and return its future."""
        with self._sched_lock:
            forced = self._forced
            if forced is not None and not forced.running() and not forced.done():
                return forced  # queued, not started: it will see every edge accepted so far
            future = self._pool.submit(self._solve_job, True)
            future.add_done_callback(self._on_job_done)
            self._forced = future
            self._current = future
            return future

    def destroy_node(self) -> None:
        """Stop the worker (waits for a running solve) and destroy the node."""
        with self._sched_lock:
            self._closing = True
        self._pool.shutdown(wait=True, cancel_futures=True)
        super().destroy_node()

    # ------------------------------------------------------------------ parameters
    def _read_settings(self) -> Settings:
        p = {name: self.get_parameter(name).value for name in PARAMETERS}
        threads = int(p["threads"])
        return Settings(
            world_frame=p["world_frame"],
            anchor_frame=p["anchor_frame"],
            publish_markers=bool(p["publish_markers"]),
            marker_spacing=float(p["marker_spacing"]),
            residual_warn_deg=float(p["residual_warn_deg"]),
            adapter=AdapterConfig(
                quaternion_tolerance=float(p["quaternion_tolerance"]),
                reference_variance=float(p["reference_variance"]),
                min_weight=float(p["min_weight"]),
                max_weight=float(p["max_weight"]),
                reserved_frames=frozenset({p["world_frame"]}),
            ),
            solver=SolverOptions(
                mode=str(p["mode"]),
                depths=tuple(int(d) for d in p["depths"]),
                iterations=int(p["iterations"]),
                sigma=float(p["sigma"]),
                seed=int(p["seed"]),
                device=str(p["device"]),
                threads=threads if threads > 0 else None,
            ),
        )

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        for param in params:
            reason = _validate(param.name, param.value)
            if reason is not None:
                return SetParametersResult(successful=False, reason=reason)
        values = {name: self.get_parameter(name).value for name in ("min_weight", "max_weight")}
        values.update({p.name: p.value for p in params if p.name in values})
        if values["min_weight"] > values["max_weight"]:
            return SetParametersResult(successful=False, reason="min_weight > max_weight")
        return SetParametersResult(successful=True)

    def _after_set_parameters(self, params: list[Parameter]) -> None:
        self._settings = self._read_settings()

    # ------------------------------------------------------------------ ingestion
    def _on_transform(self, msg: TransformStamped) -> None:
        self._ingest(edge_from_transform(msg, self._settings.adapter))

    def _on_odometry(self, msg: Odometry) -> None:
        self._ingest(edge_from_odometry(msg, self._settings.adapter))

    def _ingest(self, item: EdgeMeasurement | Rejection) -> None:
        if not self._acc.add(item) and isinstance(item, Rejection):
            self.get_logger().warning(
                f"rejected edge ({item.reason}): {item.detail}", throttle_duration_sec=5.0
            )

    # ------------------------------------------------------------------ scheduling
    def _on_timer(self) -> None:
        stats = self._acc.stats()
        with self._sched_lock:
            if self._closing:
                return
            busy = self._current is not None and not self._current.done()
            changed = stats.version != self._last_attempted_version
            if busy:
                if changed:
                    self._skipped_busy += 1
                return
            if changed:
                self._current = self._pool.submit(self._solve_job, False)
                return
            republish = stats.received != self._last_diag_received
        if republish:  # counters moved (e.g. rejections) without a graph change
            self._publish_diagnostics(self.get_clock().now().to_msg(), stats)

    async def _on_solve_request(
        self, request: Trigger.Request, response: Trigger.Response
    ) -> Trigger.Response:
        outcome = await _AwaitFuture(self.request_solve())
        response.success = outcome.success
        response.message = outcome.message
        return response

    def _on_reset_request(
        self, request: Trigger.Request, response: Trigger.Response
    ) -> Trigger.Response:
        with self._publish_lock:
            self._acc.reset()
            self._last_result = None
            self._last_error = ""
            self._anchor_warning = ""
        self.get_logger().info("graph reset")
        response.success = True
        response.message = "graph and counters cleared"
        return response

    def _on_job_done(self, _future: concurrent.futures.Future[SolveOutcome]) -> None:
        try:
            self._wake.trigger()
        except Exception:  # noqa: BLE001 - node already destroyed
            pass

    # ------------------------------------------------------------------ worker
    def _solve_job(self, force: bool) -> SolveOutcome:
        """Runs on the worker thread: snapshot, solve, publish."""
        try:
            return self._solve_and_publish(force)
        except Exception as exc:  # noqa: BLE001 - never let the worker die silently
            if self._closing:
                return SolveOutcome(False, "node is shutting down")
            self.get_logger().error(f"solve job failed: {exc!r}")
            return SolveOutcome(False, f"internal error: {exc!r}")

    def _solve_and_publish(self, force: bool) -> SolveOutcome:
        if self._closing:
            return SolveOutcome(False, "node is shutting down")
        settings = self._settings
        snap = self._acc.snapshot()
        with self._sched_lock:
            if not force and snap.version == self._last_attempted_version:
                return SolveOutcome(True, "graph unchanged")
            self._last_attempted_version = snap.version
        stamp = self.get_clock().now().to_msg()
        graph = snap.graph
        if graph.num_nodes == 0:
            self._last_result = None
            self._anchor_warning = ""
            if settings.publish_markers:
                self._pub_markers.publish(clear_markers(settings.world_frame, stamp))
            self._publish_diagnostics(stamp)
            return SolveOutcome(False, "no edges yet")
        anchor: Hashable | None = snap.first_node
        if settings.anchor_frame:
            if not graph.has_node(settings.anchor_frame):
                self._anchor_warning = f"anchor frame {settings.anchor_frame!r} not seen yet"
                self._publish_diagnostics(stamp)
                return SolveOutcome(False, self._anchor_warning)
            anchor = settings.anchor_frame
        self._anchor_warning = ""

        t0 = time.perf_counter()
        try:
            result = self._solve_fn(graph, anchor, settings.solver)
        except Exception as exc:  # noqa: BLE001 - reported as ERROR, node keeps running
            self._last_duration_s = time.perf_counter() - t0
            self._last_error = f"{type(exc).__name__}: {exc}"
            self._solves_failed += 1
            self.get_logger().error(f"solve failed, keeping the last orientations: {exc!r}")
            self._publish_diagnostics(stamp)
            return SolveOutcome(False, f"solve failed: {self._last_error}")
        duration = time.perf_counter() - t0
        with self._publish_lock:
            if self._acc.generation != snap.generation:
                return SolveOutcome(False, "graph was reset during the solve; result discarded")
            self._publish_result(result, snap.version, duration, stamp, settings)
        num_components = len(result.anchors)
        return SolveOutcome(
            True,
            f"solved {len(result.node_ids)} nodes in {num_components} component(s) "
            f"in {duration:.3f} s (depth {result.depth}, {result.num_filtered} filtered)",
        )

    def _publish_result(
        self, result: SolveResult, version: int, duration: float, stamp: Any, settings: Settings
    ) -> None:
        self._last_result = result
        self._last_solved_version = version
        self._last_duration_s = duration
        self._last_error = ""
        self._solves_ok += 1
        for msg in orientation_transforms(
            result.node_ids, result.rotations, settings.world_frame, stamp
        ):
            self._pub_orientations.publish(msg)
        if settings.publish_markers:
            self._pub_markers.publish(orientation_markers(
                result.node_ids, result.rotations, result.component, result.anchors,
                settings.world_frame, stamp, spacing=settings.marker_spacing,
            ))
        self._publish_diagnostics(stamp)

    # ------------------------------------------------------------------ diagnostics
    def _publish_diagnostics(self, stamp: Any, stats: AccumulatorStats | None = None) -> None:
        stats = stats if stats is not None else self._acc.stats()
        level, message, values = self._diagnostic_values(stats)
        status = diagnostic_status(
            f"{self.get_name()}: rotation averaging", level, message, values,
            hardware_id=self.get_fully_qualified_name(),
        )
        with self._sched_lock:
            self._last_diag_received = stats.received
        self._pub_diag.publish(diagnostic_array([status], stamp))

    def _diagnostic_values(
        self, stats: AccumulatorStats
    ) -> tuple[Level, str, dict[str, Any]]:
        settings = self._settings
        result = self._last_result
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
            inlier = np.asarray(result.residuals_deg)[np.asarray(result.edge_inlier, bool)]
            median = float(np.median(inlier)) if inlier.size else math.nan
            num_components = len(result.anchors)
            detached = _describe_detached(result)
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
                problems.append(
                    f"{num_components - 1} component(s) not connected to the anchor"
                )
            if math.isfinite(median) and median > settings.residual_warn_deg:
                level = Level.WARN
                problems.append(
                    f"median residual {median:.2f} deg > {settings.residual_warn_deg:g} deg"
                )
        with self._sched_lock:
            skipped = self._skipped_busy
        values.update({
            "last_solve_duration_s": self._last_duration_s,
            "graph_version": stats.version,
            "solved_version": self._last_solved_version,
            "solves_completed": self._solves_ok,
            "solves_failed": self._solves_failed,
            "timer_ticks_skipped_busy": skipped,
            "last_error": self._last_error or "none",
        })
        if self._anchor_warning:
            level = max(level, Level.WARN)
            problems.insert(0, self._anchor_warning)
        if self._last_error:
            level = Level.ERROR
            problems.insert(0, f"last solve failed ({self._last_error}); keeping last result")
        if problems:
            message = "; ".join(problems)
        elif result is None:
            message = "waiting for edges"
        else:
            message = f"{len(result.node_ids)} nodes solved"
        return level, message, values


def _describe_detached(result: SolveResult) -> str:
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


def main(args: Sequence[str] | None = None) -> None:
    """Console script ``rotavg_node``: spin the node on a SingleThreadedExecutor."""
    rclpy.init(args=list(args) if args is not None else None)
    node: RotavgNode | None = None
    try:
        node = RotavgNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
