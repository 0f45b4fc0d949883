"""EdgeAccumulator: counters, versions, snapshots, thread safety (no ROS involved)."""

from __future__ import annotations

import sys
import threading

import numpy as np

from rotavg_ros.app.accumulator import (
    INVALID_MEASUREMENT,
    EdgeAccumulator,
    EdgeMeasurement,
    Rejection,
)
from rotavg_ros.core.so3 import random_rotations
from rotavg_ros.core.view_graph import RepeatPolicy, ViewGraph


def edge(i: str, j: str, R: np.ndarray | None = None, w: float = 1.0,
         notes: tuple[str, ...] = ()) -> EdgeMeasurement:
    return EdgeMeasurement(i, j, np.eye(3) if R is None else R, w, 0, notes)


def test_counts_and_invariant() -> None:
    acc = EdgeAccumulator(reasons=("self_loop", "zero_quaternion"), note_keys=("n1",))
    s = acc.stats()
    assert (s.received, s.accepted, s.num_rejected, s.version) == (0, 0, 0, 0)
    assert s.rejected == {"self_loop": 0, "zero_quaternion": 0} and s.notes == {"n1": 0}
    assert acc.add(edge("a", "b"))
    assert acc.add(edge("b", "c", notes=("n1",)))
    assert not acc.add(Rejection("self_loop"))
    assert not acc.add(Rejection("brand_new_reason", "detail"))
    # What ViewGraph refuses is counted, not raised.
    assert not acc.add(edge("c", "d", np.full((3, 3), np.nan)))
    assert not acc.add(edge("c", "d", w=0.0))
    assert not acc.add(edge("c", "c"))
    s = acc.stats()
    assert s.received == 7 and s.accepted == 2
    assert s.rejected == {"self_loop": 1, "zero_quaternion": 0, "brand_new_reason": 1,
                          INVALID_MEASUREMENT: 3}
    assert s.received == s.accepted + s.num_rejected
    assert s.notes == {"n1": 1}
    assert (s.num_nodes, s.num_measurements, s.version) == (3, 2, 2)
    assert acc.add_many([edge("a", "c"), Rejection("self_loop"), edge("d", "e")]) == 2
    assert acc.stats().received == 10 and acc.version == 4


def test_version_and_generation() -> None:
    acc = EdgeAccumulator()
    v0 = acc.version
    acc.add(Rejection("self_loop"))
    assert acc.version == v0  # rejections do not change the graph
    acc.add(edge("a", "b"))
    v1 = acc.version
    assert v1 != v0
    acc.reset(counters=False)
    assert acc.version not in (v0, v1) and acc.generation == 1
    s = acc.stats()
    assert (s.num_nodes, s.received, s.accepted) == (0, 2, 1)  # counters kept
    acc.reset()
    s = acc.stats()
    assert (s.received, s.accepted, s.num_rejected, s.generation) == (0, 0, 0, 2)


def test_snapshot_is_independent_and_complete() -> None:
    rng = np.random.default_rng(0)
    R = random_rotations(6, rng)
    acc = EdgeAccumulator(RepeatPolicy.LATEST)
    acc.add(edge("a", "b", R[0]))
    acc.add(edge("c", "b", R[1], 2.0))  # reversed w.r.t. index order: stored transposed
    snap = acc.snapshot()
    assert snap.version == acc.version and snap.first_node == "a"
    assert snap.graph.repeat_policy is RepeatPolicy.LATEST
    before = snap.graph.edge_arrays()
    # Edges arriving "during a solve" go to the live graph only ...
    acc.add(edge("a", "b", R[2]))
    acc.add(edge("d", "a", R[3]))
    assert snap.graph.num_measurements == 2 and snap.graph.num_nodes == 3
    np.testing.assert_array_equal(snap.graph.edge_arrays().R, before.R)
    # ... and the live graph is untouched by work on the snapshot.
    snap.graph.add_edge("x", "y", R[4])
    assert not acc.has_node("x")
    # ... and they are part of the next snapshot.
    nxt = acc.snapshot()
    assert nxt.version > snap.version and nxt.graph.num_measurements == 4
    assert nxt.graph.node_ids == ["a", "b", "c", "d"]
    # The copy equals a graph built from scratch from the same measurements.
    ref = ViewGraph(RepeatPolicy.LATEST)
    for i, j, M, w in [("a", "b", R[0], 1.0), ("c", "b", R[1], 2.0), ("a", "b", R[2], 1.0),
                       ("d", "a", R[3], 1.0)]:
        ref.add_edge(i, j, M, w)
    got, want = nxt.graph.edge_arrays(), ref.edge_arrays()
    for name in ("i", "j", "R", "weight", "multiplicity"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))


def test_empty_snapshot() -> None:
    snap = EdgeAccumulator().snapshot()
    assert snap.graph.num_nodes == 0 and snap.first_node is None


def test_concurrent_producers_keep_counters_consistent() -> None:
    n_threads, per_thread = 6, 1500
    acc = EdgeAccumulator(reasons=("zero_quaternion",), note_keys=("note",))
    rng = np.random.default_rng(1)
    rotations = random_rotations(64, rng)
    start = threading.Barrier(n_threads + 1)
    stop = threading.Event()
    errors: list[str] = []
    old_interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-5)  # make the threads interleave a lot

    def produce(t: int) -> None:
        start.wait()
        for k in range(per_thread):
            if k % 5 == 0:
                acc.add(Rejection("zero_quaternion"))
            elif k % 7 == 0:
                acc.add(edge(f"n{t}", f"n{t}"))  # invalid_measurement
            else:
                i, j = (t * 31 + k) % 40, (t * 17 + 3 * k + 1) % 40
                if i == j:
                    j = (j + 1) % 40
                acc.add(edge(f"n{i}", f"n{j}", rotations[k % 64], notes=("note",)))

    def observe() -> None:
        start.wait()
        last_version = -1
        while not stop.is_set():
            s = acc.stats()
            if s.received != s.accepted + s.num_rejected:
                errors.append(f"invariant broken: {s}")
            if s.notes["note"] != s.accepted:
                errors.append(f"notes out of step: {s}")
            snap = acc.snapshot()
            # No reset: the version counts accepted edges, so a snapshot is self-consistent.
            if snap.graph.num_measurements != snap.version:
                errors.append(f"snapshot torn: {snap.graph.num_measurements} != {snap.version}")
            if snap.version < last_version:
                errors.append("version went backwards")
            last_version = snap.version
            snap.graph.edge_arrays()  # consolidating a copy must not disturb producers

    try:
        threads = [threading.Thread(target=produce, args=(t,)) for t in range(n_threads)]
        observer = threading.Thread(target=observe)
        for th in threads + [observer]:
            th.start()
        for th in threads:
            th.join()
        stop.set()
        observer.join()
    finally:
        sys.setswitchinterval(old_interval)

    assert not errors, errors[:3]
    s = acc.stats()
    total = n_threads * per_thread
    n_rejected_q = n_threads * len(range(0, per_thread, 5))
    n_invalid = n_threads * sum(1 for k in range(per_thread) if k % 5 and k % 7 == 0)
    assert s.received == total
    assert s.rejected == {"zero_quaternion": n_rejected_q, INVALID_MEASUREMENT: n_invalid}
    assert s.accepted == total - n_rejected_q - n_invalid
    assert s.num_measurements == s.accepted == s.version
    assert acc.snapshot().graph.num_measurements == s.accepted
