"""What a replay did, per topic and per solve, and its printed summary."""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Hashable
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np

from rotavg_ros.app.session import FAILED, SolveAttempt
from rotavg_ros.core.metrics import ErrorStats
from rotavg_ros.core.result import (
    SolveResult,
    components_warning,
    contested_warning,
    parallel_warning,
)
from rotavg_ros.io.bag_messages import TF_MESSAGE
from rotavg_ros.replay.config import EXIT_OK


class TopicRole(str, Enum):
    """What the replay does with a topic's messages."""

    EDGES = "edges"
    GROUND_TRUTH = "ground_truth"
    IGNORED = "ignored"

    def __str__(self) -> str:
        return self.value


@dataclass
class TopicStats:
    topic: str
    msgtype: str
    role: TopicRole
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
        return sum(t.used for t in self.topics.values() if t.role == TopicRole.EDGES)

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
        rows = [t for t in self.topics.values() if t.role != TopicRole.IGNORED]
        if rows:
            width = max(len(t.topic) for t in rows)
            twidth = max(len(t.msgtype) for t in rows)
            lines.append(f"  {'topic':<{width}}  {'type':<{twidth}}  {'msgs':>7}  "
                         f"{'used':>7}  {'rejected':>8}")
            for t in rows:
                if t.role == TopicRole.GROUND_TRUTH:
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
        ignored = [t for t in self.topics.values() if t.role == TopicRole.IGNORED]
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
        failed = sum(1 for s in self.solves if s.attempt.status == FAILED)
        solve_time = sum(s.attempt.duration_s for s in self.solves
                         if math.isfinite(s.attempt.duration_s))
        lines.append(f"  solves: {len(self.solves)} ({ok} ok, {failed} failed), "
                     f"{solve_time:.2f} s solving")
        errors = dict.fromkeys(s.attempt.error for s in self.solves
                               if s.attempt.status == FAILED and s.attempt.error)
        lines += [f"    failed: {error}" for error in errors]
        if self.final is not None:
            r = self.final
            lines.append(f"  final: {len(r.node_ids)} nodes, {len(r.anchors)} component(s), "
                         f"depth {r.depth}, {r.num_filtered} edges filtered")
            lines += [f"    warning: {line}" for line in (components_warning(r),
                                                           parallel_warning(r),
                                                           contested_warning(r))
                      if line is not None]
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
