"""``rotavg replay BAG``: run a recorded rosbag2 bag through the node's pipeline, offline.

What it does
------------
* Reads a rosbag2 MCAP bag (a directory with ``metadata.yaml`` or a lone ``.mcap``) without
  ROS (:mod:`rotavg_ros.bag_reader`; damaged bags are read as far as possible).
* Edge topics are chosen by type unless ``--edge-topics`` names them:
  ``geometry_msgs/msg/TransformStamped`` (except the ground-truth topic),
  ``nav_msgs/msg/Odometry`` and ``tf2_msgs/msg/TFMessage`` (every transform inside is one
  edge). Not chosen by default: ``/tf``, ``/tf_static`` (a robot's TF tree is not a set of
  rotation measurements) and the replayed node's own ``/<node>/orientations`` (so an output
  bag can be replayed without feeding the results back in).
* Messages go, in log-time order, through the **same** code as ``rotavg_node``:
  ``msg_adapters.inputs`` (validation, covariance weights) -> ``EdgeAccumulator`` ->
  :func:`rotavg_ros.pipeline.solve_snapshot` (anchor choice, ``RotationAverager``) ->
  :func:`rotavg_ros.pipeline.diagnostic_values`.
* ``--solve-once`` (default): one solve after the last message, stamped with its log time.
  ``--solve-period S``: the node's timer in bag time: ticks at ``start + k*S`` (``start`` =
  the bag's first message); a tick solves if the graph changed since the last attempt (a
  message stamped exactly on a tick counts before it), otherwise it republishes the
  diagnostics if the counters moved (rejections). After the last message one more tick runs,
  so the final graph is always solved. Solving takes no bag time here (the live node keeps
  ingesting while it solves), so replay is deterministic.
* ``--output OUT``: a rosbag2 MCAP bag (Jazzy types, zstd-compressed chunks) with what the
  node would publish, stamped (header and log time) at each solve's bag time:
  ``/<node>/orientations`` (TransformStamped per node, node-to-world, parent
  ``world_frame``), ``/tf`` (one TFMessage with all of them), ``/<node>/markers``
  (MarkerArray) and ``/diagnostics`` (DiagnosticArray).
* Ground truth: a ``TransformStamped`` (or ``TFMessage``) topic, default ``/ground_truth``,
  ``header.frame_id = world``, ``child_frame_id = <node>``, rotation node-to-world (the form
  of the published orientations). It is read first, so every solve is scored (gauge-aligned,
  :func:`rotavg_ros.metrics.evaluate`) against all of it.
* ``--output-g2o FILE``: the final orientations as ``VERTEX_SE3:QUAT`` lines
  (node-to-world quaternions, :func:`rotavg_ros.io_g2o.write_g2o`). g2o ids are integers:
  when every frame id is ``<prefix><integer>`` with one common prefix (possibly empty) and
  the integers round-trip (``cam_7``, not ``cam_007``), the integer is the g2o id; otherwise
  ids are ``0..N-1`` in solve order and ``FILE.frames.tsv`` maps ``g2o_id<TAB>frame_id``. A
  ``#`` comment at the top of the g2o file says which mapping was used.

Exit status: 0 when edges were used and the last solve succeeded; 1 when nothing usable was
read (no edge accepted); 2 for unusable input (no such bag, not a bag, bad arguments); 3 when
the last solve failed.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
import sys
import time
from collections import Counter
from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from msg_adapters.inputs import edge_from_odometry, edge_from_transform
from rotavg_ros.accumulator import INVALID_MEASUREMENT, EdgeMeasurement, Rejection
from rotavg_ros.bag_outputs import (
    DIAGNOSTIC_ARRAY,
    MARKER_ARRAY,
    TF_MESSAGE,
    TRANSFORM_STAMPED,
    MessageFactory,
)
from rotavg_ros.bag_reader import BagError, BagRecord, BagSource, DecodeError, open_bag
from rotavg_ros.metrics import ErrorStats, evaluate
from rotavg_ros.pipeline import (
    ANCHOR_MISSING,
    NO_EDGES,
    NODE_NAME,
    SOLVED,
    Settings,
    SolveAttempt,
    SolveBookkeeping,
    SolveFn,
    WarmStart,
    diagnostic_name,
    diagnostic_values,
    make_accumulator,
    settings_from_parameters,
    solve_snapshot,
)
from rotavg_ros.so3 import quat_to_matrix
from rotavg_ros.solver_types import SolveResult

ODOMETRY = "nav_msgs/msg/Odometry"
EDGE_TYPES = (TRANSFORM_STAMPED, ODOMETRY, TF_MESSAGE)
DEFAULT_GT_TOPIC = "/ground_truth"
NOT_BY_DEFAULT = ("/tf", "/tf_static")
UNDECODABLE = "undecodable_message"
EMPTY_TF = "empty_tf_message"

EXIT_OK = 0
EXIT_NOTHING_USABLE = 1
EXIT_INPUT = 2
EXIT_SOLVE_FAILED = 3


class ReplayError(Exception):
    """Unusable input or arguments (exit status 2)."""


# ---------------------------------------------------------------------- options / report
@dataclass
class ReplayConfig:
    """Everything ``rotavg replay`` needs besides the solver function."""

    bag: Path
    settings: Settings
    repeat_policy: str = "merge"
    solve_period: float | None = None
    """Seconds of bag time between timer ticks; None = solve once at the end."""
    output: Path | None = None
    overwrite: bool = False
    output_g2o: Path | None = None
    gt_topic: str = DEFAULT_GT_TOPIC
    edge_topics: list[str] | None = None
    node_name: str = NODE_NAME
    quiet: bool = False
    progress: bool | None = None
    """Show the progress bar: None = when stderr is a TTY and not quiet."""


@dataclass
class TopicStats:
    topic: str
    msgtype: str
    role: str
    """``edges``, ``ground_truth`` or ``ignored``."""
    declared: int = 0
    read: int = 0
    used: int = 0
    rejected: Counter[str] = field(default_factory=Counter)
    samples: list[str] = field(default_factory=list)
    note: str = ""

    def reject(self, reason: str, detail: str = "") -> None:
        self.rejected[reason] += 1
        if detail and len(self.samples) < 3:
            self.samples.append(f"{reason}: {detail}")


@dataclass
class SolveRecord:
    index: int
    bag_time_ns: int
    attempt: SolveAttempt
    errors: ErrorStats | None = None


@dataclass
class ReplayReport:
    """What a replay did; :meth:`summary` formats it."""

    bag: Path
    reader: str = ""
    topics: dict[str, TopicStats] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    solves: list[SolveRecord] = field(default_factory=list)
    diagnostics_only_ticks: int = 0
    final: SolveResult | None = None
    final_errors: ErrorStats | None = None
    gt: dict[str, np.ndarray] = field(default_factory=dict)
    bag_start_ns: int | None = None
    bag_end_ns: int | None = None
    wall_s: float = 0.0
    output: Path | None = None
    output_g2o: Path | None = None
    g2o_mapping: str = ""
    exit_code: int = EXIT_OK

    @property
    def edges_used(self) -> int:
        return sum(t.used for t in self.topics.values() if t.role == "edges")

    @property
    def messages_read(self) -> int:
        return sum(t.read for t in self.topics.values())

    @property
    def final_orientations(self) -> dict[Hashable, np.ndarray]:
        """World-to-node rotations of the last successful solve."""
        if self.final is None:
            return {}
        return dict(zip(self.final.node_ids, self.final.rotations, strict=True))

    def summary(self) -> str:
        lines = [f"replay summary for {self.bag} (read with {self.reader})"]
        rows = [t for t in self.topics.values() if t.role != "ignored"]
        if rows:
            width = max(len(t.topic) for t in rows)
            twidth = max(len(t.msgtype) for t in rows)
            lines.append(f"  {'topic':<{width}}  {'type':<{twidth}}  {'msgs':>7}  "
                         f"{'used':>7}  {'rejected':>8}")
            for t in rows:
                if t.role == "ground_truth":
                    lines.append(f"  {t.topic:<{width}}  {t.msgtype:<{twidth}}  {t.read:>7}  "
                                 f"ground truth for {len(self.gt)} frame(s)"
                                 + (f", {sum(t.rejected.values())} unusable"
                                    if t.rejected else ""))
                else:
                    lines.append(f"  {t.topic:<{width}}  {t.msgtype:<{twidth}}  {t.read:>7}  "
                                 f"{t.used:>7}  {sum(t.rejected.values()):>8}"
                                 + ("  (edges = transforms)" if t.msgtype == TF_MESSAGE
                                    else ""))
                if t.read < t.declared:
                    lines.append(f"    {t.declared - t.read} of {t.declared} indexed "
                                 "message(s) could not be read")
                if t.rejected:
                    reasons = ", ".join(f"{k} {v}" for k, v in sorted(
                        t.rejected.items(), key=lambda kv: (-kv[1], kv[0])))
                    lines.append(f"    rejected: {reasons}")
                for sample in t.samples:
                    lines.append(f"      e.g. {sample}")
                if t.note:
                    lines.append(f"    {t.note}")
        else:
            lines.append("  no edge topics")
        ignored = [t for t in self.topics.values() if t.role == "ignored"]
        if ignored:
            lines.append("  skipped topics:")
            for t in ignored:
                typ = t.msgtype if t.msgtype not in ("", "__schemaless__") else "no schema"
                lines.append(f"    {t.topic} ({typ}, {t.declared} msgs): "
                             f"{t.note}")
        if self.problems:
            lines.append("  problems:")
            lines += [f"    - {p}" for p in self.problems]
        ok = sum(1 for s in self.solves if s.attempt.success)
        failed = sum(1 for s in self.solves if s.attempt.status == "failed")
        solve_time = sum(s.attempt.duration_s for s in self.solves
                         if math.isfinite(s.attempt.duration_s))
        lines.append(f"  solves: {len(self.solves)} ({ok} ok, {failed} failed), "
                     f"{solve_time:.2f} s solving")
        errors = dict.fromkeys(s.attempt.error for s in self.solves
                               if s.attempt.status == "failed" and s.attempt.error)
        lines += [f"    failed: {error}" for error in errors]
        if self.final is not None:
            r = self.final
            lines.append(f"  final: {len(r.node_ids)} nodes, {len(r.anchors)} component(s), "
                         f"depth {r.depth}, {r.num_filtered} edges filtered")
        if self.final_errors is not None:
            e = self.final_errors
            lines.append(f"  accuracy vs ground truth ({e.num_nodes} nodes): mean "
                         f"{e.mean_deg:.3f} deg, median {e.median_deg:.3f} deg, max "
                         f"{e.max_deg:.3f} deg")
        elif self.gt and self.final is not None:
            lines.append("  accuracy: no frame of the ground truth is in the solution")
        if self.bag_start_ns is not None and self.bag_end_ns is not None:
            lines.append(f"  bag time {(self.bag_end_ns - self.bag_start_ns) / 1e9:.2f} s, "
                         f"{self.messages_read} messages read, {self.edges_used} edges used")
        if self.output is not None:
            lines.append(f"  output bag: {self.output}")
        if self.output_g2o is not None:
            lines.append(f"  output g2o: {self.output_g2o} ({self.g2o_mapping})")
        lines.append(f"  wall time {self.wall_s:.2f} s, exit status {self.exit_code}")
        return "\n".join(lines)


# ---------------------------------------------------------------------- progress bar
class ProgressBar:
    """``\\r[#####     ]  52% 10400/20000 msgs`` on a TTY, at most ~10 redraws a second.

    Plain text (carriage return and spaces, no terminal escapes); :meth:`clear` erases it
    before another line is printed.
    """

    def __init__(self, total: int | None, stream: TextIO, enabled: bool,
                 width: int = 30, min_interval: float = 0.1) -> None:
        self.total = total if total else None
        self.stream = stream
        self.enabled = enabled
        self.width = width
        self.min_interval = min_interval
        self.done = 0
        self.extra = ""
        self._last = -math.inf
        self._shown = False
        self._width_shown = 0

    def text(self) -> str:
        if self.total:
            frac = min(1.0, self.done / self.total)
            filled = int(round(frac * self.width))
            bar = "#" * filled + " " * (self.width - filled)
            text = f"[{bar}] {frac * 100:3.0f}% {self.done}/{self.total} msgs"
        else:
            text = f"{self.done} msgs"
        return f"{text}  {self.extra}".rstrip()

    def update(self, done: int, extra: str | None = None, force: bool = False) -> None:
        self.done = done
        if extra is not None:
            self.extra = extra
        if not self.enabled:
            return
        now = time.monotonic()
        if force or now - self._last >= self.min_interval:
            self._last = now
            text = self.text()
            self.stream.write("\r" + text + " " * max(0, self._width_shown - len(text)))
            self.stream.flush()
            self._width_shown = len(text)
            self._shown = True

    def clear(self) -> None:
        """Erase the bar (before printing a line); the next update redraws it."""
        if self.enabled and self._shown:
            self.stream.write("\r" + " " * self._width_shown + "\r")
            self.stream.flush()
            self._shown = False
            self._width_shown = 0
            self._last = -math.inf

    def finish(self) -> None:
        if self.enabled:
            self.update(self.done, force=True)
            self.stream.write("\n")
            self.stream.flush()
            self._shown = False


# ---------------------------------------------------------------------- output bag
class OutputBag:
    """rosbag2 MCAP writer for the node's outputs (rosbags, Jazzy typestore)."""

    def __init__(self, path: Path, node_name: str, factory: MessageFactory,
                 overwrite: bool = False) -> None:
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

        if path.exists():
            if not overwrite:
                raise ReplayError(f"{path} exists; pass --overwrite to replace it")
            if not (path / "metadata.yaml").is_file():
                raise ReplayError(f"{path} exists and is not a rosbag2 bag; not replacing it")
            import shutil

            shutil.rmtree(path)
        self.factory = factory
        self.writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        self.writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self.writer.open()
        store = factory.typestore
        self.conns = {
            "orientations": self.writer.add_connection(
                f"/{node_name}/orientations", TRANSFORM_STAMPED, typestore=store),
            "tf": self.writer.add_connection("/tf", TF_MESSAGE, typestore=store),
            "markers": self.writer.add_connection(
                f"/{node_name}/markers", MARKER_ARRAY, typestore=store),
            "diagnostics": self.writer.add_connection(
                "/diagnostics", DIAGNOSTIC_ARRAY, typestore=store),
        }
        self.counts: Counter[str] = Counter()

    def write(self, key: str, msg: Any, time_ns: int) -> None:
        self.writer.write(self.conns[key], int(time_ns), self.factory.serialize(msg))
        self.counts[key] += 1

    def close(self) -> None:
        self.writer.close()


# ---------------------------------------------------------------------- the replay
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
            with open_bag(self.config.bag) as source:
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
            raise ReplayError(str(exc)) from exc
        if report.final is not None and self.config.output_g2o is not None:
            report.g2o_mapping = write_g2o_with_mapping(self.config.output_g2o, report.final)
            report.output_g2o = self.config.output_g2o
        if report.edges_used == 0:
            report.exit_code = EXIT_NOTHING_USABLE
        elif report.solves and report.solves[-1].attempt.status == "failed":
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
            stats = TopicStats(topic, msgtype, "ignored",
                               declared=source.declared.get(topic, 0))
            report.topics[topic] = stats
            if topic == gt_topic:
                stats.role = "ground_truth"
                if msgtype not in (TRANSFORM_STAMPED, TF_MESSAGE):
                    stats.role = "ignored"
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
            stats.role = "edges"
            chosen.append(topic)
        if cfg.edge_topics is not None:
            for topic in cfg.edge_topics:
                if topic not in source.topics:
                    report.problems.append(f"{topic}: not in the bag")
        # keep the table in a stable order: edges, ground truth, ignored
        order = {"edges": 0, "ground_truth": 1, "ignored": 2}
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
            show = not cfg.quiet and _isatty(self.err)
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
                transforms = self.factory.orientation_transforms(
                    result.node_ids, result.rotations, settings.world_frame, stamp_ns)
                for msg in transforms:
                    w.write("orientations", msg, stamp_ns)
                w.write("tf", self.factory.tf_message(transforms), stamp_ns)
                if settings.publish_markers:
                    w.write("markers", self.factory.orientation_markers(
                        result.node_ids, result.rotations, result.component, result.anchors,
                        settings.world_frame, stamp_ns, spacing=settings.marker_spacing),
                        stamp_ns)
            if self.report.gt:
                record.errors = _score(result, self.report.gt)
        elif attempt.status == NO_EDGES and w is not None and settings.publish_markers:
            w.write("markers", self.factory.clear_markers(settings.world_frame, stamp_ns),
                    stamp_ns)
        self._write_diagnostics(stamp_ns)
        self._announce(record)

    def _write_diagnostics(self, stamp_ns: int) -> None:
        stats = self.acc.stats()
        self.last_diag_received = stats.received
        if self.writer is None:
            return
        level, message, values = diagnostic_values(stats, self.book, self.settings)
        self.writer.write("diagnostics", self.factory.diagnostic_array(
            diagnostic_name(self.config.node_name), level, message, values,
            self.node_fqn, stamp_ns), stamp_ns)

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
        raise ReplayError(f"--output {output} must not be the input bag or overlap it")


def _score(result: SolveResult, gt: dict[str, np.ndarray]) -> ErrorStats | None:
    est = {str(k): R for k, R in zip(result.node_ids, result.rotations, strict=True)}
    if not any(k in gt for k in est):
        return None
    return evaluate(est, gt)


def _isatty(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


# ---------------------------------------------------------------------- g2o output
_ID_PATTERN = re.compile(r"^(.*?)(0|[1-9][0-9]*)$")


def g2o_id_mapping(node_ids: Sequence[Hashable]) -> tuple[list[int], str]:
    """g2o integer ids for ``node_ids`` and a description of the mapping.

    ``<prefix><int>`` with one common prefix and round-tripping integers (no leading zeros,
    all distinct) -> those integers; otherwise ``0..N-1`` in order.
    """
    names = [str(n) for n in node_ids]
    matches = [_ID_PATTERN.match(n) for n in names]
    if names and all(matches):
        prefixes = {m.group(1) for m in matches if m}
        ints = [int(m.group(2)) for m in matches if m]
        if len(prefixes) == 1 and len(set(ints)) == len(ints):
            prefix = prefixes.pop()
            how = (f"g2o id = the integer in frame id '{prefix}<id>'" if prefix
                   else "g2o id = frame id")
            return ints, how
    return list(range(len(names))), "sequential g2o ids; see the .frames.tsv file"


def write_g2o_with_mapping(path: Path, result: SolveResult) -> str:
    """Write the orientations to ``path`` (plus ``path.frames.tsv`` if ids are sequential)."""
    from rotavg_ros.io_g2o import write_g2o

    ids, how = g2o_id_mapping(result.node_ids)
    write_g2o(path, ids, result.rotations)
    header = [f"# rotavg replay: node-to-world orientations of {len(ids)} frames; {how}"]
    if how.startswith("sequential"):
        sidecar = Path(f"{path}.frames.tsv") if not str(path).endswith(".g2o") else \
            Path(str(path)[:-4] + ".frames.tsv")
        with open(sidecar, "w", encoding="utf-8") as fh:
            fh.write("g2o_id\tframe_id\n")
            for i, node in zip(ids, result.node_ids, strict=True):
                fh.write(f"{i}\t{node}\n")
        header[0] = header[0].replace("the .frames.tsv file", sidecar.name)
        how = how.replace("the .frames.tsv file", str(sidecar))
    if len(set(map(str, result.anchors))) > 1:
        header.append(f"# {len(result.anchors) - 1} component(s) not connected to the anchor "
                      f"{result.anchors[0]} have their own gauge")
    body = Path(path).read_text(encoding="utf-8")
    Path(path).write_text("\n".join(header) + "\n" + body, encoding="utf-8")
    return how


# ---------------------------------------------------------------------- command line
def register(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``replay`` to the ``rotavg`` command line (called by :mod:`rotavg_ros.cli`)."""
    from rotavg_ros.cli import add_solver_arguments

    p = subparsers.add_parser(
        "replay", help="replay a rosbag2 MCAP bag through the node's pipeline, offline",
        description="Replay a rosbag2 MCAP bag (directory or lone .mcap) through the same "
        "adapters, accumulator and solver as rotavg_node, without ROS. Exit status: 0 ok, "
        "1 nothing usable in the bag, 2 bad input, 3 the last solve failed.")
    p.add_argument("bag", help="rosbag2 directory (with metadata.yaml) or a .mcap file")
    p.add_argument("--output", "-o", help="write the node's outputs to this new bag directory")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --output bag")
    when = p.add_mutually_exclusive_group()
    when.add_argument("--solve-period", type=float, metavar="SECONDS",
                      help="solve like the node's timer, every SECONDS of bag time")
    when.add_argument("--solve-once", action="store_true",
                      help="one solve after the last message (the default)")
    p.add_argument("--output-g2o", metavar="FILE", help="write the final orientations as g2o")
    p.add_argument("--ground-truth-topic", default=DEFAULT_GT_TOPIC, metavar="TOPIC",
                   help="TransformStamped/TFMessage world->node ground truth "
                   "(default %(default)s; '' to ignore; a topic named /ground_truth is "
                   "never an edge topic unless named in --edge-topics)")
    p.add_argument("--edge-topics", nargs="+", metavar="TOPIC",
                   help="edge topics (default: every TransformStamped, Odometry and TFMessage "
                   "topic except the ground truth, /tf and /tf_static)")
    p.add_argument("--quiet", "-q", action="store_true",
                   help="no progress bar and no per-solve lines (the summary is printed)")
    p.add_argument("--verbose", "-v", action="store_true", help="print the solver's progress")
    node = p.add_argument_group("node parameters (as rotavg_node's)")
    node.add_argument("--node-name", default=NODE_NAME)
    node.add_argument("--world-frame", default="world")
    node.add_argument("--anchor-frame", default="")
    node.add_argument("--repeat-policy", default="merge", choices=("merge", "latest", "first"))
    node.add_argument("--quaternion-tolerance", type=float, default=1e-3)
    node.add_argument("--reference-variance", type=float, default=None,
                      help="rad^2 per axis that maps to weight 1 (default (1 deg)^2)")
    node.add_argument("--min-weight", type=float, default=1e-3)
    node.add_argument("--max-weight", type=float, default=1e3)
    node.add_argument("--no-markers", action="store_true")
    node.add_argument("--no-warm-start", action="store_true",
                      help="solve every period from scratch (default: warm-start each solve "
                      "from the previous one, as the node does)")
    node.add_argument("--marker-spacing", type=float, default=1.0)
    node.add_argument("--residual-warn-deg", type=float, default=5.0)
    add_solver_arguments(p)
    p.set_defaults(func=cmd_replay)
    return p


def config_from_args(args: argparse.Namespace) -> ReplayConfig:
    """Build the :class:`ReplayConfig` (raises ReplayError / InputError for bad values)."""
    from rotavg_ros.cli import options_from_args

    if args.solve_period is not None and not (
        math.isfinite(args.solve_period) and args.solve_period > 0
    ):
        raise ReplayError(f"--solve-period must be > 0, got {args.solve_period}")
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", args.node_name):
        raise ReplayError(f"--node-name must be a ROS node name, got {args.node_name!r}")
    options = dataclasses.replace(
        options_from_args(args),
        progress=_solver_progress if args.verbose else None)
    params: dict[str, Any] = {
        "world_frame": args.world_frame,
        "anchor_frame": args.anchor_frame,
        "repeat_policy": args.repeat_policy,
        "quaternion_tolerance": args.quaternion_tolerance,
        "min_weight": args.min_weight,
        "max_weight": args.max_weight,
        "publish_markers": not args.no_markers,
        "marker_spacing": args.marker_spacing,
        "residual_warn_deg": args.residual_warn_deg,
        "mode": args.mode,
        "warm_start": not args.no_warm_start,
        "depths": list(options.depths),
    }
    if args.reference_variance is not None:
        params["reference_variance"] = args.reference_variance
    try:
        settings = settings_from_parameters(params, solver=options)
    except ValueError as exc:
        raise ReplayError(str(exc)) from exc
    edge_topics = None
    if args.edge_topics is not None:
        edge_topics = [t.strip() for item in args.edge_topics for t in item.split(",")
                       if t.strip()]
    return ReplayConfig(
        bag=Path(args.bag),
        settings=settings,
        repeat_policy=args.repeat_policy,
        solve_period=args.solve_period,
        output=Path(args.output) if args.output else None,
        overwrite=args.overwrite,
        output_g2o=Path(args.output_g2o) if args.output_g2o else None,
        gt_topic=args.ground_truth_topic,
        edge_topics=edge_topics,
        node_name=args.node_name,
        quiet=args.quiet,
    )


def _solver_progress(text: str) -> None:
    print(f"[rotavg] {text}", file=sys.stderr, flush=True)


def run_replay(config: ReplayConfig, solve_fn: SolveFn | None = None,
               out: TextIO | None = None, err: TextIO | None = None) -> ReplayReport:
    """Replay and print the summary to ``out``; raises :class:`ReplayError` for bad input."""
    out = out if out is not None else sys.stdout
    report = Replayer(config, solve_fn, out, err).run()
    print(report.summary(), file=out, flush=True)
    return report


def cmd_replay(args: argparse.Namespace) -> int:
    try:
        config = config_from_args(args)
        report = run_replay(config)
    except ReplayError as exc:
        print(f"rotavg replay: error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    return report.exit_code


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m rotavg_ros.replay BAG ...`` (same as ``rotavg replay``)."""
    from rotavg_ros.cli import main as cli_main

    return cli_main(["replay", *(argv if argv is not None else sys.argv[1:])])


if __name__ == "__main__":
    sys.exit(main())
