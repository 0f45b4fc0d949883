"""The replay engine: a recorded rosbag2 bag through the node's pipeline, offline.

What it does
------------
* Reads a rosbag2 MCAP bag (a directory with ``metadata.yaml`` or a lone ``.mcap``) without
  ROS (:mod:`rotavg_ros.io.bag_reader`; damaged bags are read as far as possible).
* Edge topics are chosen by type unless ``--edge-topics`` names them:
  ``geometry_msgs/msg/TransformStamped`` (except the ground-truth topic),
  ``nav_msgs/msg/Odometry`` and ``tf2_msgs/msg/TFMessage`` (every transform inside is one
  edge). Not chosen by default: ``/tf``, ``/tf_static`` (a robot's TF tree is not a set of
  rotation measurements) and the replayed node's own ``/<node>/orientations`` (so an output
  bag can be replayed without feeding the results back in).
* Messages go, in log-time order, through the **same** code as ``rotavg_node``:
  ``rotavg_ros.msg_adapters.inputs`` (validation, covariance weights) -> ``EdgeAccumulator`` ->
  :func:`rotavg_ros.app.session.solve_snapshot` (anchor choice, ``RotationAverager``) ->
  :func:`rotavg_ros.app.diagnostics.diagnostic_values`.
* ``--solve-once`` (default): one solve after the last message, stamped with its log time.
  ``--solve-period S``: the node's timer in bag time: ticks at ``start + k*S`` (``start`` =
  the bag's first message); a tick solves if the graph changed since the last attempt (a
  message stamped exactly on a tick counts before it), otherwise it republishes the
  diagnostics if the counters moved (rejections). After the last message one more tick runs,
  so the final graph is always solved. Solving takes no bag time here (the live node keeps
  ingesting while it solves), so replay is deterministic.
* ``--output OUT``: a rosbag2 MCAP bag as Jazzy writes one (:mod:`rotavg_ros.io.bag_writer`:
  metadata version 9, CRCs, each topic's offered QoS) with what the node would publish,
  stamped (header and log time) at each solve's bag time: ``/<node>/orientations``
  (TransformStamped per node, node-to-world, parent ``world_frame``), ``/tf`` (one
  TFMessage with all of them), ``/<node>/markers`` (MarkerArray) and ``/diagnostics``
  (DiagnosticArray).
* Ground truth: a ``TransformStamped`` (or ``TFMessage``) topic, default ``/ground_truth``,
  ``header.frame_id = world``, ``child_frame_id = <node>``, rotation node-to-world (the form
  of the published orientations). It is read first, so every solve is scored (gauge-aligned,
  :func:`rotavg_ros.core.metrics.evaluate`) against all of it.
* ``--output-g2o FILE``: the final orientations as ``VERTEX_SE3:QUAT`` lines
  (node-to-world quaternions, :func:`rotavg_ros.io.g2o.write_g2o`). g2o ids are integers:
  when every frame id is ``<prefix><integer>`` with one common prefix (possibly empty) and
  the integers round-trip (``cam_7``, not ``cam_007``), the integer is the g2o id; otherwise
  ids are ``0..N-1`` in solve order and ``FILE.frames.tsv`` maps ``g2o_id<TAB>frame_id``. A
  ``#`` comment at the top of the g2o file says which mapping was used.

Exit status: 0 when edges were used and the last solve succeeded; 1 when nothing usable was
read (no edge accepted); 2 for unusable input (no such bag, not a bag, bad arguments); 3 when
the last solve failed.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from rotavg_ros.app.accumulator import INVALID_MEASUREMENT, make_accumulator
from rotavg_ros.app.diagnostics import diagnostic_name, diagnostic_values
from rotavg_ros.app.session import (
    ANCHOR_MISSING,
    FAILED,
    NO_EDGES,
    SOLVED,
    SolveBookkeeping,
    SolveFn,
    WarmStart,
    solve_snapshot,
)
from rotavg_ros.core.measurement import EdgeMeasurement, Rejection
from rotavg_ros.core.metrics import ErrorStats, evaluate
from rotavg_ros.core.result import SolveResult
from rotavg_ros.core.so3 import quat_to_matrix
from rotavg_ros.errors import InputError
from rotavg_ros.io.bag_messages import TF_MESSAGE, TRANSFORM_STAMPED, MessageFactory
from rotavg_ros.io.bag_reader import BagError, BagRecord, BagSource, DecodeError, open_bag
from rotavg_ros.io.bag_writer import OutputBag
from rotavg_ros.io.g2o import write_g2o_with_mapping
from rotavg_ros.msg_adapters import outputs
from rotavg_ros.msg_adapters.inputs import edge_from_odometry, edge_from_transform
from rotavg_ros.replay.config import (
    DEFAULT_GT_TOPIC,
    EDGE_TYPES,
    EMPTY_TF,
    EXIT_NOTHING_USABLE,
    EXIT_SOLVE_FAILED,
    NOT_BY_DEFAULT,
    ODOMETRY,
    UNDECODABLE,
    ReplayConfig,
)
from rotavg_ros.replay.progress import ProgressBar, isatty
from rotavg_ros.replay.report import ReplayReport, SolveRecord, TopicRole, TopicStats


def _node_to_world_rotation(quat: Any) -> np.ndarray | None:
    q = np.array([quat.x, quat.y, quat.z, quat.w], dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not np.all(np.isfinite(q)) or norm < 1e-9 or abs(norm - 1.0) > 1e-2:
        return None
    return quat_to_matrix(q / norm)


class Replayer:
    """One replay: owns the accumulator, the bookkeeping, the outputs and the report."""

    def __init__(self, config: ReplayConfig, solve_fn: SolveFn | None = None,
                 out: TextIO | None = None, err: TextIO | None = None) -> None:
        self.config = config
        self.settings = config.settings
        self.solve_fn = solve_fn
        self.out = out if out is not None else sys.stdout
        self.err = err if err is not None else sys.stderr
        self.acc = make_accumulator(config.repeat_policy)
        self.book = SolveBookkeeping()
        self.report = ReplayReport(bag=config.bag)
        self.factory = MessageFactory()
        self.writer: OutputBag | None = None
        self.last_attempted_version = -1
        self.last_diag_received = -1
        self.progress: ProgressBar | None = None
        self.node_fqn = f"/{config.node_name}"

    # ------------------------------------------------------------------ entry
    def run(self) -> ReplayReport:
        t_wall = time.perf_counter()
        report = self.report
        try:
            with open_bag(self.config.bag, self.config.merge_mcap_files) as source:
                report.reader = source.reader
                edge_topics, gt_topic = self._choose_topics(source)
                if gt_topic:
                    self._read_ground_truth(source, gt_topic)
                if self.config.output is not None:
                    _check_output_path(self.config.output, self.config.bag)
                    self.writer = OutputBag(self.config.output, self.config.node_name,
                                            self.factory, self.config.overwrite)
                    report.output = self.config.output
                try:
                    self._replay(source, edge_topics)
                finally:
                    report.problems = list(dict.fromkeys(source.problems + report.problems))
                    if self.writer is not None:
                        self.writer.close()
        except BagError as exc:
            raise InputError(str(exc)) from exc
        if report.final is not None and self.config.output_g2o is not None:
            report.g2o_mapping = write_g2o_with_mapping(self.config.output_g2o, report.final)
            report.output_g2o = self.config.output_g2o
        if report.edges_used == 0:
            report.exit_code = EXIT_NOTHING_USABLE
        elif report.solves and report.solves[-1].attempt.status == FAILED:
            report.exit_code = EXIT_SOLVE_FAILED
        report.wall_s = time.perf_counter() - t_wall
        return report

    # ------------------------------------------------------------------ topics
    def _choose_topics(self, source: BagSource) -> tuple[list[str], str]:
        cfg = self.config
        report = self.report
        gt_topic = cfg.gt_topic if cfg.gt_topic in source.topics else ""
        own = f"/{cfg.node_name}/orientations"
        chosen: list[str] = []
        for topic, msgtype in source.topics.items():
            stats = TopicStats(topic, msgtype, TopicRole.IGNORED,
                               declared=source.declared.get(topic, 0))
            report.topics[topic] = stats
            if topic == gt_topic:
                stats.role = TopicRole.GROUND_TRUTH
                if msgtype not in (TRANSFORM_STAMPED, TF_MESSAGE):
                    stats.role = TopicRole.IGNORED
                    stats.note = ("ground-truth topic must be TransformStamped or TFMessage")
                    gt_topic = ""
                continue
            if cfg.edge_topics is not None:
                if topic not in cfg.edge_topics:
                    stats.note = "not in --edge-topics"
                    continue
                if msgtype not in EDGE_TYPES:
                    stats.note = "not an edge message type"
                    report.problems.append(
                        f"{topic}: type {msgtype or '(unknown)'} cannot carry edges "
                        f"(expected one of {', '.join(EDGE_TYPES)}); skipped")
                    continue
            else:
                if msgtype not in EDGE_TYPES:
                    stats.note = "not an edge message type"
                    continue
                if topic in NOT_BY_DEFAULT or topic in (own, DEFAULT_GT_TOPIC):
                    stats.note = "not an edge topic by default (name it in --edge-topics)"
                    continue
            stats.role = TopicRole.EDGES
            chosen.append(topic)
        if cfg.edge_topics is not None:
            for topic in cfg.edge_topics:
                if topic not in source.topics:
                    report.problems.append(f"{topic}: not in the bag")
        # keep the table in a stable order: edges, ground truth, ignored
        order = {TopicRole.EDGES: 0, TopicRole.GROUND_TRUTH: 1, TopicRole.IGNORED: 2}
        report.topics = dict(sorted(report.topics.items(),
                                    key=lambda kv: (order[kv[1].role], kv[0])))
        return chosen, gt_topic

    def _read_ground_truth(self, source: BagSource, topic: str) -> None:
        stats = self.report.topics[topic]
        gt = self.report.gt
        for record in source.read([topic]):
            stats.read += 1
            try:
                msg = source.decode(record)
            except DecodeError as exc:
                stats.reject(UNDECODABLE, str(exc))
                continue
            try:
                transforms = msg.transforms if record.msgtype == TF_MESSAGE else [msg]
                frames = [(tf.child_frame_id, _node_to_world_rotation(tf.transform.rotation))
                          for tf in transforms]
            except Exception as exc:  # noqa: BLE001 - decoded with an unexpected shape
                stats.reject(UNDECODABLE, f"{type(exc).__name__}: {exc}")
                continue
            for child, R in frames:
                if R is None or not isinstance(child, str) or not child:
                    stats.reject("invalid_ground_truth", f"{child!r}")
                    continue
                gt[child] = R.T  # world-to-node
        if gt and stats.read:
            stats.used = len(gt)

    # ------------------------------------------------------------------ main loop
    def _replay(self, source: BagSource, topics: list[str]) -> None:
        cfg = self.config
        report = self.report
        total = source.count(topics)
        show = cfg.progress
        if show is None:
            show = not cfg.quiet and isatty(self.err)
        self.progress = ProgressBar(total, self.err, bool(show))
        period_ns = (None if cfg.solve_period is None
                     else max(1, int(round(cfg.solve_period * 1e9))))
        t0: int | None = source.start_ns
        next_tick: int | None = None
        last_time: int | None = None
        done = 0
        for record in source.read(topics):
            t = record.log_time_ns
            if t0 is None or t < t0:
                t0 = t
            report.bag_start_ns = t0
            if period_ns is not None:
                if next_tick is None:
                    next_tick = t0 + period_ns
                if t > next_tick:
                    self._tick(next_tick)
                    # every later boundary before t sees no change: jump to the next one >= t
                    next_tick = t0 + -(-(t - t0) // period_ns) * period_ns
            self._ingest(source, record)
            last_time = t
            done += 1
            self.progress.update(done, self._progress_extra())
        report.bag_end_ns = last_time
        if last_time is not None:
            if period_ns is not None:
                assert next_tick is not None
                self._tick(next_tick)
            else:
                self._solve(last_time)
        if done:
            self.progress.extra = self._progress_extra()
            self.progress.finish()
        if report.final is not None and report.gt:
            report.final_errors = _score(report.final, report.gt)

    def _progress_extra(self) -> str:
        return f"| {len(self.report.solves)} solve(s)" if self.report.solves else ""

    def _ingest(self, source: BagSource, record: BagRecord) -> None:
        stats = self.report.topics[record.topic]
        stats.read += 1
        try:
            msg = source.decode(record)
        except DecodeError as exc:
            stats.reject(UNDECODABLE, str(exc))
            self.acc.add(Rejection(UNDECODABLE, str(exc)))
            return
        adapter = self.settings.adapter
        items: list[EdgeMeasurement | Rejection]
        try:
            if record.msgtype == TF_MESSAGE:
                items = [edge_from_transform(tf, adapter) for tf in msg.transforms]
                if not items:
                    stats.reject(EMPTY_TF)
                    return
            elif record.msgtype == ODOMETRY:
                items = [edge_from_odometry(msg, adapter)]
            else:
                items = [edge_from_transform(msg, adapter)]
        except Exception as exc:  # noqa: BLE001 - a message of an unexpected shape
            stats.reject(UNDECODABLE, f"{type(exc).__name__}: {exc}")
            self.acc.add(Rejection(UNDECODABLE, str(exc)))
            return
        for item in items:
            if self.acc.add(item):
                stats.used += 1
            elif isinstance(item, Rejection):
                stats.reject(item.reason, item.detail)
            else:
                stats.reject(INVALID_MEASUREMENT, f"{item.frame_i} -> {item.frame_j}")

    # ------------------------------------------------------------------ solving
    def _tick(self, stamp_ns: int) -> None:
        stats = self.acc.stats()
        if stats.version != self.last_attempted_version:
            self._solve(stamp_ns)
        elif stats.received != self.last_diag_received:
            self._write_diagnostics(stamp_ns)
            self.report.diagnostics_only_ticks += 1

    def _solve(self, stamp_ns: int) -> None:
        snap = self.acc.snapshot()
        self.last_attempted_version = snap.version
        attempt = solve_snapshot(snap, self.settings, self.solve_fn,
                                 WarmStart.of(self.book.last_result))
        self.book.record(attempt, snap.version)
        record = SolveRecord(len(self.report.solves) + 1, stamp_ns, attempt)
        self.report.solves.append(record)
        settings = self.settings
        w = self.writer
        if attempt.status == SOLVED:
            result = attempt.result
            assert result is not None
            self.report.final = result
            if w is not None:
                transforms = outputs.orientation_transforms(
                    self.factory, result.node_ids, result.rotations, settings.world_frame,
                    stamp_ns)
                for msg in transforms:
                    w.write("orientations", msg, stamp_ns)
                w.write("tf", outputs.tf_message(self.factory, transforms), stamp_ns)
                if settings.publish_markers:
                    w.write("markers", outputs.orientation_markers(
                        self.factory, result.node_ids, result.rotations, result.component,
                        result.anchors, settings.world_frame, stamp_ns,
                        spacing=settings.marker_spacing), stamp_ns)
            if self.report.gt:
                record.errors = _score(result, self.report.gt)
        elif attempt.status == NO_EDGES and w is not None and settings.publish_markers:
            w.write("markers", outputs.clear_markers(self.factory, settings.world_frame,
                                                     stamp_ns), stamp_ns)
        self._write_diagnostics(stamp_ns)
        self._announce(record)

    def _write_diagnostics(self, stamp_ns: int) -> None:
        stats = self.acc.stats()
        self.last_diag_received = stats.received
        if self.writer is None:
            return
        level, message, values = diagnostic_values(stats, self.book, self.settings)
        status = outputs.diagnostic_status(
            self.factory, diagnostic_name(self.config.node_name), level, message, values,
            self.node_fqn)
        self.writer.write("diagnostics", outputs.diagnostic_array(self.factory, [status],
                                                                  stamp_ns), stamp_ns)

    def _announce(self, record: SolveRecord) -> None:
        if self.config.quiet:
            return
        start = self.report.bag_start_ns or record.bag_time_ns
        attempt = record.attempt
        line = f"solve {record.index} at bag time {(record.bag_time_ns - start) / 1e9:.3f} s: "
        if attempt.success:
            r = attempt.result
            assert r is not None
            line += (f"{len(r.node_ids)} nodes, {len(r.anchors)} component(s), depth "
                     f"{r.depth}, {r.num_filtered} filtered, {attempt.duration_s:.2f} s")
            if record.errors is not None:
                e = record.errors
                line += (f" | vs ground truth ({e.num_nodes} nodes): mean {e.mean_deg:.3f} "
                         f"deg, median {e.median_deg:.3f} deg")
        elif attempt.status == ANCHOR_MISSING:
            line += attempt.anchor_warning
        else:
            line += attempt.message
        if self.progress is not None:
            self.progress.clear()
        print(line, file=self.out, flush=True)


def _check_output_path(output: Path, bag: Path) -> None:
    out, src = output.resolve(), bag.resolve()
    if out == src or out in src.parents or src in out.parents:
        raise InputError(f"--output {output} must not be the input bag or overlap it")


def _score(result: SolveResult, gt: dict[str, np.ndarray]) -> ErrorStats | None:
    est = {str(k): R for k, R in zip(result.node_ids, result.rotations, strict=True)}
    if not any(k in gt for k in est):
        return None
    return evaluate(est, gt)


def run_replay(config: ReplayConfig, solve_fn: SolveFn | None = None,
               out: TextIO | None = None, err: TextIO | None = None) -> ReplayReport:
    """Replay and print the summary to ``out``; raises :class:`ReplayError` for bad input."""
    out = out if out is not None else sys.stdout
    report = Replayer(config, solve_fn, out, err).run()
    print(report.summary(), file=out, flush=True)
    return report
