"""``rotavg_node``: live rotation averaging over ROS 2 topics (the rclpy shell).

Parameters with descriptors, subscriptions, services, the solve timer and publishing live
here; everything the node shares with the offline replay (parameters, ingest, solve session,
solver process, diagnostics) is in :mod:`rotavg_ros.app`. Interfaces, scheduling, executors
and diagnostics keys are described in ``docs/node.md``.

Conventions: ``R_i`` is world-to-node; an edge ``(i, j)`` carries ``R_ij ~= R_i R_j^T`` (a
``TransformStamped`` with ``header.frame_id = i``, ``child_frame_id = j``); the node publishes
node-to-world ``R_i^T`` with ``header.frame_id = world_frame``, ``child_frame_id = i``.
"""

from __future__ import annotations

import concurrent.futures
import functools
import os
import signal
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from types import FrameType
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
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.exceptions import InvalidHandle, ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSPolicyKind,
    QoSProfile,
    ReliabilityPolicy,
)
from rclpy.signals import SignalHandlerOptions
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from rotavg_ros.app.accumulator import (
    AccumulatorStats,
    EdgeAccumulator,
    EdgeMeasurement,
    Rejection,
    make_accumulator,
)
from rotavg_ros.app.diagnostics import (
    diagnostic_name,
    diagnostic_values,
    inlier_residuals_deg,
)
from rotavg_ros.app.parameters import (
    NODE_NAME,
    PARAMETER_TABLE,
    FloatRange,
    IntRange,
    ParameterSpec,
    Settings,
    parameters_help,
    settings_from_parameters,
)
from rotavg_ros.app.session import (
    FAILED,
    NO_EDGES,
    SOLVED,
    SolveAttempt,
    SolveBookkeeping,
    SolveFn,
    WarmStart,
    solve_snapshot,
)
from rotavg_ros.app.solver_process import SubprocessSolver
from rotavg_ros.core.result import SolveResult
from rotavg_ros.io.graph_store import check_writable, load_graph, save_graph
from rotavg_ros.msg_adapters.inputs import edge_from_odometry, edge_from_transform
from rotavg_ros.msg_adapters.outputs import Level
from rotavg_ros.ros.messages import (
    clear_markers,
    diagnostic_array,
    diagnostic_status,
    orientation_markers,
    orientation_transforms,
)

INGEST_BATCH = 256
"""Queued edges a callback of the ingest group takes beyond the one it was given."""
DIAGNOSTICS_PERIOD_S = 1.0
"""Period of the /diagnostics publication besides solves (aggregators expect about 1 Hz)."""
SOLVE_POLL_S = 0.01
"""While ``~/solve`` waits for its solve, it looks for queued edges this often (s)."""


def _warm_import() -> None:
    try:
        import rotavg_ros.core.solver  # noqa: F401
    except Exception:  # noqa: BLE001 - reported by the first solve instead
        pass


@dataclass(frozen=True)
class SolveOutcome:
    """What one solve job did; ``~/solve`` answers with it."""

    success: bool
    message: str


def descriptor(spec: ParameterSpec) -> ParameterDescriptor:
    """The ``ParameterDescriptor`` of one row of the parameter table."""
    desc = ParameterDescriptor(
        description=spec.description, read_only=spec.read_only,
        additional_constraints=spec.constraint_text,
    )
    if isinstance(spec.range, FloatRange):
        desc.floating_point_range = [
            FloatingPointRange(from_value=spec.range.low, to_value=spec.range.high, step=0.0)
        ]
    elif isinstance(spec.range, IntRange):
        desc.integer_range = [
            IntegerRange(from_value=spec.range.low, to_value=spec.range.high, step=0)
        ]
    return desc


# name -> (default, descriptor): every parameter the node declares (from
# rotavg_ros.app.parameters.PARAMETER_TABLE, as config/rotavg.yaml is).
PARAMETERS: dict[str, tuple[Any, ParameterDescriptor]] = {
    spec.name: (spec.default, descriptor(spec)) for spec in PARAMETER_TABLE
}


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
        self._coerce_integer_overrides()
        for name, (default, descriptor) in PARAMETERS.items():
            self.declare_parameter(name, default, descriptor)
        self._warn_unknown_overrides()
        self._settings = self._read_settings()  # raises ValueError for an invalid value
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)

        # Test hook, else None: the default solver runs in a child process (no GIL contention
        # with the subscriptions) when ``solve_in_subprocess``, in the worker thread otherwise.
        self._solve_fn: SolveFn | None = solve_fn
        self._runner: SubprocessSolver | None = (
            SubprocessSolver(self.get_parameter("solver_niceness").value) if solve_fn is None
            and self.get_parameter("solve_in_subprocess").value else None)
        self._acc = make_accumulator(self.get_parameter("repeat_policy").value)
        self._graph_file = str(self.get_parameter("graph_file").value)
        if self._graph_file:  # refuse at start what would fail at the first save
            check_writable(self._graph_file)
        self.final_save_ok: bool | None = None
        """Whether :meth:`destroy_node` saved ``graph_file`` (None: nothing to save)."""
        # Orientations (and depth) stored in graph_file: the warm start of the first solve
        # after a restart (then the last result takes over); cleared by ~/reset.
        self._stored: WarmStart | None = None
        if self._graph_file and os.path.exists(self._graph_file):
            stored = load_graph(self._graph_file)  # a broken file stops the start: say why
            self._acc.add_many(stored.measurements)
            if stored.orientations:
                self._stored = WarmStart(stored.orientations, stored.depth)
            self.get_logger().info(
                f"loaded {len(stored.measurements)} measurements and "
                f"{len(stored.orientations)} orientations from {self._graph_file}")

        # Scheduling state, guarded by _sched_lock.
        self._sched_lock = threading.Lock()
        # Jobs submitted to the worker whose _follow_up has not run yet: a timer tick that
        # sees one is "busy". Counted, not read from futures, so no tick can slip in between
        # a job's follow-up check and its future completing (that lost a follow-up solve).
        self._jobs_pending = 0
        self._forced: concurrent.futures.Future[SolveOutcome] | None = None
        self._last_attempted_version = -1
        self._tick_skipped = False  # a busy tick saw a changed graph: solve after the running one
        self._closing = False
        self._abandoned = False  # stop(): the running solve was abandoned, do not wait for it
        # Held from the worker's "was the graph reset?" check to the end of its publishing,
        # and by ~/reset: a reset never interleaves with the publication of a stale result.
        self._publish_lock = threading.Lock()
        # Solve bookkeeping: written by the worker (and ~/reset under _publish_lock), except
        # skipped_busy, which the timer counts under _sched_lock.
        self._book = SolveBookkeeping()
        # Diagnostics level last published (state changes are logged) and incompatible-QoS
        # events seen on any endpoint; both under _status_lock.
        self._status_lock = threading.Lock()
        self._level: Level | None = None
        self._incompatible_qos = 0

        self._pool = concurrent.futures.ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="rotavg_solver"
        )
        if self._runner is not None:
            self._runner.warm_up()
        elif solve_fn is None:
            self._pool.submit(_warm_import)

        self._ingest_group = MutuallyExclusiveCallbackGroup()
        self._control_group = ReentrantCallbackGroup()
        in_qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=self.get_parameter("qos_depth").value,
            reliability=(ReliabilityPolicy.BEST_EFFORT
                         if self.get_parameter("edge_reliability").value == "best_effort"
                         else ReliabilityPolicy.RELIABLE),
        )
        self._sub_tf = self.create_subscription(
            TransformStamped, "~/edges", self._on_transform, in_qos,
            callback_group=self._ingest_group, event_callbacks=self._sub_events("~/edges"),
        )
        self._sub_odom = self.create_subscription(
            Odometry, "~/edges_with_covariance", self._on_odometry, in_qos,
            callback_group=self._ingest_group,
            event_callbacks=self._sub_events("~/edges_with_covariance"),
        )
        self._pub_orientations = self._orientations_publisher()
        self._markers_shown: SolveResult | None = None  # result of the last markers published
        self._pub_markers = self.create_publisher(MarkerArray, "~/markers", QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL),
            event_callbacks=self._pub_events("~/markers"))
        self._pub_diag = self.create_publisher(
            DiagnosticArray, "/diagnostics", 10, event_callbacks=self._pub_events("/diagnostics"))
        self._srv_solve = self.create_service(
            Trigger, "~/solve", self._on_solve_request, callback_group=self._ingest_group
        )
        self._srv_reset = self.create_service(
            Trigger, "~/reset", self._on_reset_request, callback_group=self._control_group
        )
        self._srv_save = self.create_service(
            Trigger, "~/save_graph", self._on_save_request, callback_group=self._control_group
        )
        self._timer = self.create_timer(
            self.get_parameter("solve_period").value, self._on_timer,
            callback_group=self._control_group,
        )
        self._diag_timer = self.create_timer(
            DIAGNOSTICS_PERIOD_S, self._on_diagnostics_timer, callback_group=self._control_group,
        )
        self.get_logger().info(
            f"averaging rotations from {self._sub_tf.topic_name} and "
            f"{self._sub_odom.topic_name} into {self._pub_orientations.topic_name}"
        )

    def _orientations_publisher(self) -> Any:
        # Transient local: a subscriber that joins later (and asks for transient-local
        # durability) still gets the latest orientations, as with /tf_static.
        return self.create_publisher(TransformStamped, "~/orientations", QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=self.get_parameter("orientations_qos_depth").value,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        ), event_callbacks=self._pub_events("~/orientations"))

    # ------------------------------------------------------------------ QoS events
    def _sub_events(self, topic: str) -> SubscriptionEventCallbacks:
        return SubscriptionEventCallbacks(
            incompatible_qos=functools.partial(self._on_incompatible_qos, topic, "publisher"))

    def _pub_events(self, topic: str) -> PublisherEventCallbacks:
        return PublisherEventCallbacks(
            incompatible_qos=functools.partial(self._on_incompatible_qos, topic, "subscription"))

    def _on_incompatible_qos(self, topic: str, peer: str, info: Any) -> None:
        """A peer on ``topic`` asks for QoS this endpoint does not offer (or the reverse):
        they do not match and no message flows between them. Logged and counted."""
        with self._status_lock:
            self._incompatible_qos += max(int(info.total_count_change), 1)
        try:
            policy = QoSPolicyKind(info.last_policy_kind).name
        except ValueError:
            policy = str(info.last_policy_kind)
        self.get_logger().warning(
            f"incompatible QoS on {self.resolve_topic_name(topic)}: a {peer} does not match "
            f"(policy {policy}); no messages flow between them"
            + (" (edge_reliability:=best_effort accepts best-effort publishers)"
               if peer == "publisher" and policy == "RELIABILITY" else ""))

    @property
    def incompatible_qos_events(self) -> int:
        """Incompatible-QoS events on any of the node's endpoints since the start."""
        with self._status_lock:
            return self._incompatible_qos

    # ------------------------------------------------------------------ public
    @property
    def accumulator(self) -> EdgeAccumulator:
        """The live edge store (thread-safe)."""
        return self._acc

    @property
    def last_result(self) -> SolveResult | None:
        """The last successful solve's result (None before the first one or after a reset)."""
        return self._book.last_result

    def request_solve(self) -> concurrent.futures.Future[SolveOutcome]:
        """Queue a solve (what ``~/solve`` does) and return its future."""
        with self._sched_lock:
            forced = self._forced
            if forced is not None and not forced.running() and not forced.done():
                return forced  # queued, not started: it will see every edge accepted so far
            future = self._submit_locked(force=True)
            self._forced = future
            return future

    def stop(self) -> bool:
        """Abandon the running solve and start no other: the solver child is terminated.

        For a fast shutdown (``rotavg_node`` calls it on SIGINT / SIGTERM); then
        :meth:`destroy_node` saves the graph without waiting for the solve. A solve in the
        worker thread (``solve_in_subprocess:=false``) cannot be interrupted: its result is
        discarded. Returns whether a solve was running or queued.
        """
        with self._sched_lock:
            self._closing = True
            self._abandoned = True
            busy = self._jobs_pending > 0
        self._pool.shutdown(wait=False, cancel_futures=True)
        if self._runner is not None:
            self._runner.abort()
        return busy

    def solver_pids(self) -> list[int]:
        """Process ids of the solver child (empty when solving in the worker thread)."""
        return self._runner.child_pids() if self._runner is not None else []

    def destroy_node(self) -> None:
        """Stop the worker (waits for a running solve unless :meth:`stop` abandoned it),
        save the graph (:attr:`final_save_ok` says whether that worked), destroy the node."""
        with self._sched_lock:
            self._closing = True
        self._pool.shutdown(wait=not self._abandoned, cancel_futures=True)
        if self._graph_file and self._acc.stats().accepted:  # with the newest result
            ok, message = self.save_graph()
            self.final_save_ok = ok
            if self.context.ok():
                (self.get_logger().info if ok else self.get_logger().error)(message)
            else:  # the context is down (shut down by someone else): /rosout is gone
                print(f"[{self.get_name()}] {message}", file=sys.stderr, flush=True)
        if self._runner is not None:
            self._runner.close()
        super().destroy_node()

    # ------------------------------------------------------------------ parameters
    def _coerce_integer_overrides(self) -> None:
        """An integer given for a double parameter (``-p solve_period:=1``, ``sigma: 1`` in
        a params file) becomes that double, before the parameters are declared."""
        # rclpy keeps the command-line, params-file and constructor overrides in this dict
        # and reads it in declare_parameter; it has no public accessor.
        overrides: dict[str, Parameter] = self._parameter_overrides
        for name, (default, _) in PARAMETERS.items():
            given = overrides.get(name)
            if (isinstance(default, float) and given is not None
                    and given.type_ == Parameter.Type.INTEGER):
                overrides[name] = Parameter(name, Parameter.Type.DOUBLE, float(given.value))

    def _warn_unknown_overrides(self) -> None:
        """WARN about overrides that name no parameter of this node (a misspelled name)."""
        unknown = sorted(
            name for name in self._parameter_overrides
            if not self.has_parameter(name) and not name.startswith("qos_overrides."))
        if unknown:
            self.get_logger().warning(
                f"ignoring unknown parameter(s): {', '.join(unknown)} (not parameters of "
                f"{self.get_name()}; rotavg_node --help lists them)")

    def _read_settings(self, changed: Sequence[Parameter] = ()) -> Settings:
        """Settings from the current parameter values, with ``changed`` applied on top.

        Raises ``ValueError`` (see :func:`rotavg_ros.app.parameters.settings_from_parameters`).
        """
        values = {name: self.get_parameter(name).value for name in PARAMETERS}
        values.update({p.name: p.value for p in changed})
        return settings_from_parameters(values)

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        try:
            self._read_settings(params)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _after_set_parameters(self, params: list[Parameter]) -> None:
        self._settings = self._read_settings()

    # ------------------------------------------------------------------ ingestion
    def _on_transform(self, msg: TransformStamped) -> None:
        self._ingest(edge_from_transform(msg, self._settings.adapter))
        self._take_queued(INGEST_BATCH)

    def _on_odometry(self, msg: Odometry) -> None:
        self._ingest(edge_from_odometry(msg, self._settings.adapter))
        self._take_queued(INGEST_BATCH)

    def _take_queued(self, limit: int) -> int:
        """Take and ingest up to ``limit`` edges waiting in the subscriptions' queues.

        Only for callbacks of the ingest group (see "Executors" in the module docstring).
        Returns how many were taken.
        """
        taken = 0
        for sub, adapt in ((self._sub_tf, edge_from_transform),
                           (self._sub_odom, edge_from_odometry)):
            while taken < limit:
                try:
                    with sub.handle:
                        msg_info = sub.handle.take_message(sub.msg_type, sub.raw)
                except InvalidHandle:  # destroyed: the node is shutting down
                    return taken
                if msg_info is None:
                    break
                self._ingest(adapt(msg_info[0], self._settings.adapter))
                taken += 1
        return taken

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
            busy = self._jobs_pending > 0
            changed = stats.version != self._last_attempted_version
            if busy:
                if changed:
                    self._book.skipped_busy += 1
                    self._tick_skipped = True
                return
            if changed:
                self._submit_locked(force=False)

    def _on_diagnostics_timer(self) -> None:
        with self._sched_lock:
            if self._closing:
                return
        stamp = self.get_clock().now().to_msg()
        settings = self._settings
        try:
            with self._publish_lock:  # a viewer that subscribed after solves left markers out
                last = self._book.last_result
                if (settings.publish_markers and last is not None
                        and last is not self._markers_shown
                        and self._pub_markers.get_subscription_count() > 0):
                    self._publish_markers(last, stamp, settings)
            self._publish_diagnostics(stamp)
        except InvalidHandle:  # destroyed meanwhile: the node is shutting down
            pass

    def _on_solve_request(
        self, request: Trigger.Request, response: Trigger.Response
    ) -> Trigger.Response:
        future = self.request_solve()
        # Keep ingesting: this callback holds the ingest group. Stop waiting on stop(): a
        # solve in the worker thread cannot be interrupted.
        while not future.done() and not self._abandoned:
            if not self._take_queued(INGEST_BATCH):
                concurrent.futures.wait([future], timeout=SOLVE_POLL_S)
        try:
            outcome = (future.result() if future.done()
                       else SolveOutcome(False, "node is shutting down: solve abandoned"))
        except concurrent.futures.CancelledError:
            outcome = SolveOutcome(False, "node is shutting down")
        response.success = outcome.success
        response.message = outcome.message
        return response

    def _on_reset_request(
        self, request: Trigger.Request, response: Trigger.Response
    ) -> Trigger.Response:
        with self._publish_lock:
            self._acc.reset()
            self._book.reset()
            self._stored = None
            # Late (transient-local) subscribers must not get pre-reset output.
            self.destroy_publisher(self._pub_orientations)
            self._pub_orientations = self._orientations_publisher()
            if self._markers_shown is not None:
                self._pub_markers.publish(clear_markers(
                    self._settings.world_frame, self.get_clock().now().to_msg()))
                self._markers_shown = None
        self.get_logger().info("graph reset")
        response.success = True
        response.message = "graph and counters cleared"
        return response

    def _on_save_request(
        self, request: Trigger.Request, response: Trigger.Response
    ) -> Trigger.Response:
        response.success, response.message = self.save_graph()
        return response

    def _warm_start(self) -> WarmStart | None:
        """The last result's orientations, else those loaded from ``graph_file``."""
        return WarmStart.of(self._book.last_result) or self._stored

    def save_graph(self) -> tuple[bool, str]:
        """Write the live graph and the last orientations to ``graph_file``."""
        if not self._graph_file:
            return False, "graph_file parameter is empty: nowhere to save"
        snap = self._acc.snapshot()
        warm = self._warm_start()
        try:
            count = save_graph(self._graph_file, snap.graph,
                               warm.rotations if warm else None, warm.depth if warm else None)
        except OSError as exc:
            return False, f"could not write {self._graph_file}: {exc}"
        return True, f"saved {count} measurements to {self._graph_file}"

    # ------------------------------------------------------------------ worker
    def _solve_job(self, force: bool) -> SolveOutcome:
        """Runs on the worker thread: snapshot, solve, publish."""
        try:
            return self._solve_and_publish(force)
        except Exception as exc:  # noqa: BLE001 - never let the worker die silently
            if self._closing or not self.context.ok():  # e.g. publishing after Ctrl-C
                return SolveOutcome(False, "node is shutting down")
            self.get_logger().error(f"solve job failed: {exc!r}")
            return SolveOutcome(False, f"internal error: {exc!r}")
        finally:
            self._follow_up()

    def _submit_locked(self, force: bool) -> concurrent.futures.Future[SolveOutcome]:
        """Queue a solve job on the worker; the caller holds ``_sched_lock``."""
        future = self._pool.submit(self._solve_job, force)
        self._jobs_pending += 1  # the job's _follow_up waits for this lock to decrement
        return future

    def _follow_up(self) -> None:
        """End of a job: queue the solve that busy timer ticks skipped (one, however many)."""
        with self._sched_lock:
            self._jobs_pending -= 1
            if not self._tick_skipped or self._closing:
                return
            self._tick_skipped = False
            if self._jobs_pending > 0:
                return  # the ~/solve job queued behind this one sees those edges too
            self._submit_locked(force=False)

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
        attempt = solve_snapshot(snap, settings, self._solve_fn, self._warm_start(),
                                 self._runner)
        if self._abandoned:  # stop() terminated the solver, or wants no more output
            return SolveOutcome(False, "node is shutting down: solve abandoned")
        if attempt.status == SOLVED:
            with self._publish_lock:
                if self._acc.generation != snap.generation:
                    return SolveOutcome(False, "graph was reset during the solve; result discarded")
                self._book.record(attempt, snap.version)
                self._log_solve(attempt)
                self._publish_result(attempt, stamp, settings)
            return SolveOutcome(True, attempt.message)
        self._book.record(attempt, snap.version)
        if attempt.status == NO_EDGES and settings.publish_markers:
            with self._publish_lock:
                self._pub_markers.publish(clear_markers(settings.world_frame, stamp))
                self._markers_shown = None
        elif attempt.status == FAILED:
            self.get_logger().error(
                f"solve failed, keeping the last orientations: {attempt.error}"
            )
        self._publish_diagnostics(stamp)
        return SolveOutcome(False, attempt.message)

    def _log_solve(self, attempt: SolveAttempt) -> None:
        """One INFO line per solve: what went in, what was left out, depth, time, residual."""
        result = attempt.result
        assert result is not None
        inlier = inlier_residuals_deg(result)
        median = f"{float(np.median(inlier)):.3f} deg" if inlier.size else "n/a"
        self.get_logger().info(
            f"solved {len(result.node_ids)} nodes, {np.asarray(result.residuals_deg).size} "
            f"edges ({self._acc.stats().num_rejected} messages rejected, "
            f"{result.num_filtered} edges filtered, {result.num_rejected_verify} rejected by "
            f"verification), {len(result.anchors)} component(s), depth {result.depth}, "
            f"{attempt.duration_s:.3f} s, median residual {median}")

    def _publish_result(self, attempt: SolveAttempt, stamp: Any, settings: Settings) -> None:
        result = attempt.result
        assert result is not None
        for msg in orientation_transforms(
            result.node_ids, result.rotations, settings.world_frame, stamp
        ):
            self._pub_orientations.publish(msg)
        # Markers cost about 1.5 ms per node to build in Python: only for an actual viewer.
        if settings.publish_markers and self._pub_markers.get_subscription_count() > 0:
            self._publish_markers(result, stamp, settings)
        self._publish_diagnostics(stamp)

    def _publish_markers(self, result: SolveResult, stamp: Any, settings: Settings) -> None:
        """Under ``_publish_lock``."""
        self._pub_markers.publish(orientation_markers(
            result.node_ids, result.rotations, result.component, result.anchors,
            settings.world_frame, stamp, spacing=settings.marker_spacing,
        ))
        self._markers_shown = result

    # ------------------------------------------------------------------ diagnostics
    def _publish_diagnostics(self, stamp: Any, stats: AccumulatorStats | None = None) -> None:
        stats = stats if stats is not None else self._acc.stats()
        level, message, values = diagnostic_values(stats, self._book, self._settings,
                                                   self.incompatible_qos_events)
        with self._status_lock:
            previous, self._level = self._level, level
        if level != previous and level >= Level.WARN:
            self.get_logger().warning(f"state {level.name}: {message}")
        elif level != previous and previous is not None:
            self.get_logger().info(f"state {level.name}: {message}")
        status = diagnostic_status(
            diagnostic_name(self.get_name()), level, message, values,
            hardware_id=self.get_fully_qualified_name(),
        )
        self._pub_diag.publish(diagnostic_array([status], stamp))


FASTDDS_PROFILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "fastdds_profile.xml")
"""Fast DDS profile with a 100 ms writer heartbeat (see the file for why)."""


class StopSignals:
    """SIGINT / SIGTERM handling of ``rotavg_node`` (installed instead of rclpy's).

    rclpy's own handlers shut the context down at once, so a solve that ends afterwards
    cannot publish ("publisher's context is invalid") and the node waits for it. Here the
    first signal only sets :attr:`event`; a thread then calls :meth:`RotavgNode.stop` (the
    solver child is terminated) and the spin loop ends, so the node saves ``graph_file``
    and shuts down with its context still valid. A second signal exits at once (status
    128 + signal number), killing the solver child first.
    """

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signum: int | None = None
        self.received_at = 0.0
        self.node: RotavgNode | None = None
        self._stop_lock = threading.Lock()
        self._stopped = False
        self._previous: dict[int, Any] = {}
        for signum in (signal.SIGINT, signal.SIGTERM):
            # A SIGINT ignored by whoever started us (`nohup`, `cmd &` in a script) stays so.
            if signal.getsignal(signum) is not signal.SIG_IGN:
                self._previous[signum] = signal.signal(signum, self._handle)

    def restore(self) -> None:
        """Put the previous handlers back (``main`` called in-process, e.g. by a test)."""
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.event.is_set():  # the second signal: now, without saving
            for pid in self.node.solver_pids() if self.node is not None else []:
                try:
                    os.kill(pid, signal.SIGKILL)
                except OSError:
                    pass
            os.write(2, f"[{NODE_NAME}] {signal.Signals(signum).name} again: exiting now, "
                        "graph_file not saved\n".encode())
            os._exit(128 + signum)
        self.signum = signum
        self.received_at = time.monotonic()
        self.event.set()  # no locks or logging here: the main thread may hold them

    def watch(self, node: RotavgNode) -> None:
        """Start the thread that stops ``node`` once a signal came (the executor thread may
        be blocked in ``~/solve``, waiting for the solve)."""
        self.node = node

        def stop_on_signal() -> None:
            self.event.wait()
            self.stop_node()

        threading.Thread(target=stop_on_signal, name="rotavg_stop", daemon=True).start()

    def stop_node(self) -> None:
        """Once, after a signal: log it and :meth:`RotavgNode.stop` the node. Returns when
        that is done, whichever thread did it."""
        with self._stop_lock:
            node = self.node
            if self._stopped or node is None or not self.event.is_set():
                return
            self._stopped = True
            name = signal.Signals(self.signum or signal.SIGINT).name
            node.get_logger().info(f"{name}: stopping")
            if node.stop():
                node.get_logger().info("abandoned the running solve")


def _user_args(argv: Sequence[str]) -> list[str]:
    """The arguments before ``--ros-args`` (without the program name)."""
    args = list(argv[1:])
    return args[:args.index("--ros-args")] if "--ros-args" in args else args


def main(args: Sequence[str] | None = None) -> None:
    """Console script ``rotavg_node``: spin the node on a SingleThreadedExecutor.

    ``-h`` / ``--help`` prints the parameters (defaults, ranges, choices) and exits 0
    without starting ROS. A parameter the node refuses, a broken ``graph_file`` or one
    whose folder is missing or not writable ends it with exit status 2 and one line on
    stderr that says why. SIGINT or SIGTERM abandons a running solve, saves ``graph_file``
    and exits with 0 (1 if that save failed); a second signal exits at once (see
    :class:`StopSignals`).

    Unless ``FASTRTPS_DEFAULT_PROFILES_FILE`` is set, it points Fast DDS at
    :data:`FASTDDS_PROFILE` first (read when the DDS participant is created; other RMWs
    ignore it). Processes that embed :class:`RotavgNode` can set the variable themselves.
    """
    argv = list(args) if args is not None else list(sys.argv)
    user = _user_args(argv)
    if "-h" in user or "--help" in user:
        sys.stdout.write(parameters_help())
        sys.exit(0)
    if os.path.exists(FASTDDS_PROFILE):
        os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", FASTDDS_PROFILE)
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    signals = StopSignals()
    node: RotavgNode | None = None
    status = 0
    try:
        try:
            node = RotavgNode()
        except (ValueError, OSError, ParameterException) as exc:
            # A refused parameter or an unusable graph_file: one line, no traceback.
            print(f"rotavg_node: error: {exc}", file=sys.stderr, flush=True)
            status = 2
        else:
            signals.watch(node)
            executor = SingleThreadedExecutor()
            executor.add_node(node)
            # Short waits: a signal's Python handler runs only when the wait returns.
            while not signals.event.is_set() and rclpy.ok():
                executor.spin_once(timeout_sec=0.1)
            signals.stop_node()  # unless the watcher thread already did
            executor.remove_node(node)
            executor.shutdown(timeout_sec=0.5)
    except ExternalShutdownException:
        pass
    finally:
        if node is not None:
            node.destroy_node()
            if node.final_save_ok is False:
                status = 1
        rclpy.try_shutdown()
        signals.restore()
        if signals.signum is not None:
            print(f"[{NODE_NAME}] stopped {time.monotonic() - signals.received_at:.2f} s "
                  f"after {signal.Signals(signals.signum).name}", file=sys.stderr, flush=True)
    worker = [t for t in threading.enumerate() if t.name.startswith("rotavg_solver")]
    if any(t.is_alive() for t in worker):  # a solve in the worker thread (no child process)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)  # concurrent.futures would join that thread at exit
    sys.exit(status)


if __name__ == "__main__":
    main()
