"""Thread-safe accumulation of relative-rotation measurements into a :class:`ViewGraph`.

This module is ROS-free on purpose: the live node (``rotavg_ros.ros.node``) and the offline bag
replay both feed it. Message parsing lives in ``rotavg_ros.msg_adapters.inputs``, which turns a
ROS (or
rosbags) message into either an :class:`EdgeMeasurement` or a :class:`Rejection`; the
accumulator takes both and keeps the counters.

Conventions
-----------
* ``R_i`` is the **world-to-node** rotation of node ``i`` (``x_node = R_i x_world``).
* An :class:`EdgeMeasurement` ``(frame_i, frame_j, R)`` carries ``R ~= R_i R_j^T``: the
  orientation of frame ``j`` expressed in frame ``i`` (the TF convention for a transform with
  ``header.frame_id = i`` and ``child_frame_id = j``).

Counters
--------
``received == accepted + sum(rejected.values())`` holds in every :meth:`EdgeAccumulator.stats`
snapshot. ``notes`` counts remarks about *accepted* measurements (for example
``default_weight_covariance``); notes never count as rejections.

Solving while edges keep arriving
---------------------------------
:meth:`EdgeAccumulator.snapshot` returns an independent copy of the live graph together with
its :attr:`~EdgeAccumulator.version`. Edges accepted while a solve runs on the copy go into the
live graph, bump the version and are part of the next snapshot: nothing is lost.
"""

from __future__ import annotations

import copy
import threading
from collections import Counter
from collections.abc import Hashable, Iterable, Mapping
from dataclasses import dataclass, field

from rotavg_ros.core.measurement import EdgeMeasurement, Rejection
from rotavg_ros.core.view_graph import RepeatPolicy, ViewGraph
from rotavg_ros.msg_adapters.inputs import ADAPTER_REASONS, NOTE_KEYS

INVALID_MEASUREMENT = "invalid_measurement"
"""Rejection reason used when :meth:`ViewGraph.add_edge` refuses a measurement that the
adapter let through (non-finite matrix, bad weight, ...). Normally never seen."""


@dataclass(frozen=True)
class AccumulatorStats:
    """Consistent copy of the counters (taken under the accumulator's lock)."""

    received: int
    accepted: int
    rejected: Mapping[str, int]
    notes: Mapping[str, int]
    num_nodes: int
    num_measurements: int
    version: int
    generation: int

    @property
    def num_rejected(self) -> int:
        return int(sum(self.rejected.values()))


@dataclass(frozen=True)
class GraphSnapshot:
    """An independent copy of the graph plus the version and generation it was taken at."""

    graph: ViewGraph
    version: int
    generation: int
    first_node: Hashable | None = field(default=None)


class EdgeAccumulator:
    """Owns the live :class:`ViewGraph`; every public method is thread-safe.

    :param repeat_policy: how parallel measurements of one pair are merged at solve time.
    :param reasons: rejection reasons to pre-seed with zero so that reports list them all.
    :param note_keys: note keys to pre-seed with zero.
    """

    def __init__(
        self,
        repeat_policy: RepeatPolicy | str = RepeatPolicy.MERGE,
        reasons: Iterable[str] = (),
        note_keys: Iterable[str] = (),
    ) -> None:
        self._lock = threading.Lock()
        self._graph = ViewGraph(repeat_policy)
        self._seed_reasons = tuple(reasons)
        self._seed_notes = tuple(note_keys)
        self._received = 0
        self._accepted = 0
        self._rejected: Counter[str] = Counter()
        self._notes: Counter[str] = Counter()
        self._version = 0
        self._generation = 0
        self._reset_counters_locked()

    # ---------------------------------------------------------------- properties
    @property
    def repeat_policy(self) -> RepeatPolicy:
        return self._graph.repeat_policy

    @property
    def version(self) -> int:
        """Changes (increases) whenever the graph changes: an accepted edge or a reset."""
        with self._lock:
            return self._version

    @property
    def generation(self) -> int:
        """Increases on every :meth:`reset`; lets a solver discard results of a cleared graph."""
        with self._lock:
            return self._generation

    # ---------------------------------------------------------------- ingestion
    def add(self, item: EdgeMeasurement | Rejection) -> bool:
        """Count ``item`` and add it to the graph if it is a measurement; True if accepted."""
        with self._lock:
            return self._add_locked(item)

    def add_many(self, items: Iterable[EdgeMeasurement | Rejection]) -> int:
        """Add several items under one lock acquisition; returns how many were accepted."""
        with self._lock:
            return sum(self._add_locked(item) for item in items)

    def _add_locked(self, item: EdgeMeasurement | Rejection) -> bool:
        self._received += 1
        if isinstance(item, Rejection):
            self._rejected[item.reason] += 1
            return False
        try:
            self._graph.add_edge(item.frame_i, item.frame_j, item.R, float(item.weight))
        except (ValueError, TypeError):
            self._rejected[INVALID_MEASUREMENT] += 1
            return False
        self._accepted += 1
        for note in item.notes:
            self._notes[note] += 1
        self._version += 1
        return True

    # ---------------------------------------------------------------- read side
    def snapshot(self) -> GraphSnapshot:
        """Independent copy of the live graph for a solve, with its version.

        The copy shares the (never mutated) per-measurement rotation arrays with the live
        graph, so it costs O(measurements) pointer copies under the lock, not a deep copy.
        """
        with self._lock:
            graph = _copy_graph(self._graph)
            ids = graph.node_ids
            return GraphSnapshot(
                graph=graph,
                version=self._version,
                generation=self._generation,
                first_node=ids[0] if ids else None,
            )

    def stats(self) -> AccumulatorStats:
        with self._lock:
            return AccumulatorStats(
                received=self._received,
                accepted=self._accepted,
                rejected=dict(self._rejected),
                notes=dict(self._notes),
                num_nodes=self._graph.num_nodes,
                num_measurements=self._graph.num_measurements,
                version=self._version,
                generation=self._generation,
            )

    def has_node(self, node_id: Hashable) -> bool:
        with self._lock:
            return self._graph.has_node(node_id)

    # ---------------------------------------------------------------- reset
    def reset(self, counters: bool = True) -> None:
        """Clear the graph (and, by default, the counters); bumps version and generation."""
        with self._lock:
            self._graph.clear()
            if counters:
                self._reset_counters_locked()
            self._version += 1
            self._generation += 1

    def _reset_counters_locked(self) -> None:
        self._received = 0
        self._accepted = 0
        self._rejected = Counter({r: 0 for r in self._seed_reasons})
        self._notes = Counter({n: 0 for n in self._seed_notes})


def _copy_graph(graph: ViewGraph) -> ViewGraph:
    """Copy a ViewGraph so that later ``add_edge`` calls on either side do not leak across.

    Prefers a ``copy()`` method if ViewGraph provides one. Otherwise makes a shallow copy and
    duplicates every container attribute: the stored 3x3 arrays are copied on insertion by
    ``ViewGraph.add_edge`` and never mutated afterwards, so sharing them is safe.
    """
    own_copy = getattr(graph, "copy", None)
    if callable(own_copy):
        result = own_copy()
        if isinstance(result, ViewGraph):
            return result
    new = copy.copy(graph)
    for name, value in vars(new).items():
        if isinstance(value, (list, dict, set)):
            setattr(new, name, value.copy())
    return new


def make_accumulator(repeat_policy: RepeatPolicy | str = RepeatPolicy.MERGE) -> EdgeAccumulator:
    """The node's accumulator: every adapter reason and note pre-seeded with zero."""
    return EdgeAccumulator(
        repeat_policy,
        reasons=(*ADAPTER_REASONS, INVALID_MEASUREMENT),
        note_keys=NOTE_KEYS,
    )
