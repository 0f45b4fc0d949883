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
import os
import sys
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

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
from rclpy.exceptions import InvalidHandle, ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from rotavg_ros.app.accumulator import (
    AccumulatorStats,
    EdgeAccumulator,
    EdgeMeasurement,
    Rejection,
    make_accumulator,
)
from rotavg_ros.app.diagnostics import diagnostic_name, diagnostic_values
from rotavg_ros.app.parameters import (
    NODE_NAME,
    PARAMETER_TABLE,
    FloatRange,
    IntRange,
    ParameterSpec,
    Settings,
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
from rotavg_ros.io.graph_store import load_graph, save_graph
from rotavg_ros.msg_adapters.inputs import edge_from_odometry, edge_from_transform
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
        for name, (default, descriptor) in PARAMETERS.items():
            self.declare_parameter(name, default, descriptor)
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
        # Held from the worker's "was the graph reset?" check to the end of its publishing,
        # and by ~/reset: a reset never interleaves with the publication of a stale result.
        self._publish_lock = threading.Lock()
        # Solve bookkeeping: written by the worker (and ~/reset under _publish_lock), except
        # skipped_busy, which the timer counts under _sched_lock.
        self._book = SolveBookkeeping()

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
        self._pub_orientations = self._orientations_publisher()
        self._markers_shown: SolveResult | None = None  # result of the last markers published
        self._pub_markers = self.create_publisher(MarkerArray, "~/markers", QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
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
        ))

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

    def destroy_node(self) -> None:
        """Stop the worker (waits for a running solve), save the graph, destroy the node."""
        with self._sched_lock:
            self._closing = True
        self._pool.shutdown(wait=True, cancel_futures=True)
        if self._graph_file and self._acc.stats().accepted:  # with the newest result
            ok, message = self.save_graph()
            if self.context.ok():
                (self.get_logger().info if ok else self.get_logger().error)(message)
            else:  # after Ctrl-C / SIGTERM the context is down: /rosout is gone
                print(f"[{self.get_name()}] {message}", file=sys.stderr, flush=True)
        if self._runner is not None:
            self._runner.close()
        super().destroy_node()

    # ------------------------------------------------------------------ parameters
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
        while not future.done():  # keep ingesting: this callback holds the ingest group
            if not self._take_queued(INGEST_BATCH):
                concurrent.futures.wait([future], timeout=SOLVE_POLL_S)
        try:
            outcome = future.result()
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
            if self._closing:
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
        if attempt.status == SOLVED:
            with self._publish_lock:
                if self._acc.generation != snap.generation:
                    return SolveOutcome(False, "graph was reset during the solve; result discarded")
                self._book.record(attempt, snap.version)
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
        level, message, values = diagnostic_values(stats, self._book, self._settings)
        status = diagnostic_status(
            diagnostic_name(self.get_name()), level, message, values,
            hardware_id=self.get_fully_qualified_name(),
        )
        self._pub_diag.publish(diagnostic_array([status], stamp))


FASTDDS_PROFILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "fastdds_profile.xml")
"""Fast DDS profile with a 100 ms writer heartbeat (see the file for why)."""


def main(args: Sequence[str] | None = None) -> None:
    """Console script ``rotavg_node``: spin the node on a SingleThreadedExecutor.

    A parameter the node refuses or a broken ``graph_file`` ends it with exit status 2 and
    one line on stderr that says why.

    Unless ``FASTRTPS_DEFAULT_PROFILES_FILE`` is set, it points Fast DDS at
    :data:`FASTDDS_PROFILE` first (read when the DDS participant is created; other RMWs
    ignore it). Processes that embed :class:`RotavgNode` can set the variable themselves.
    """
    if os.path.exists(FASTDDS_PROFILE):
        os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", FASTDDS_PROFILE)
    rclpy.init(args=list(args) if args is not None else None)
    node: RotavgNode | None = None
    try:
        try:
            node = RotavgNode()
        except (ValueError, OSError, ParameterException) as exc:
            # A refused parameter or an unreadable graph_file: one line, no traceback.
            print(f"rotavg_node: error: {exc}", file=sys.stderr, flush=True)
            sys.exit(2)
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
