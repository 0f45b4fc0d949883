"""Round trip of the live-graph file (rotavg_ros.io.graph_store)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from rotavg_ros.core.so3 import random_rotations
from rotavg_ros.core.view_graph import ViewGraph
from rotavg_ros.io import graph_store
from rotavg_ros.io.graph_store import check_writable, load_graph, save_graph


def test_round_trip_keeps_frames_order_weights_and_repeats(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    R = random_rotations(4, rng)
    g = ViewGraph()
    edges = [("base_link", "cam/0", 1.0), ("cam/0", "lidar_7", 2.5), ("lidar_7", "base_link", 1.0),
             ("cam/0", "base_link", 4.0), ("x", "lidar_7", 0.5)]
    index = {"base_link": 0, "cam/0": 1, "lidar_7": 2, "x": 3}
    for a, b, w in edges:
        g.add_edge(a, b, R[index[a]] @ R[index[b]].T, w)
    path = tmp_path / "g.g2o"
    assert save_graph(path, g, {"cam/0": R[1]}, depth=6) == len(edges)
    stored = load_graph(path)
    g2 = ViewGraph()
    for m in stored.measurements:
        g2.add_edge(m.frame_i, m.frame_j, m.R, m.weight)
    assert g2.node_ids == g.node_ids
    for x, y in zip(g2.measurement_arrays(), g.measurement_arrays(), strict=True):
        np.testing.assert_allclose(x, y, atol=1e-12)
    np.testing.assert_allclose(stored.orientations["cam/0"], R[1], atol=1e-12)
    # Only solved nodes come back: the identity placeholders of the others are no warm start.
    assert set(stored.orientations) == {"cam/0"} and stored.depth == 6
    save_graph(path, g)  # nothing solved yet
    assert load_graph(path).orientations == {} and load_graph(path).depth is None


def test_version_1_file_loads_without_orientations(tmp_path: Path) -> None:
    g = ViewGraph()
    g.add_edge("a", "b", np.eye(3))
    path = tmp_path / "g.g2o"
    save_graph(path, g, {"a": np.eye(3), "b": np.eye(3)}, depth=2)
    lines = [ln for ln in path.read_text().splitlines()
             if not ln.startswith(("# SOLVED", "# DEPTH"))]
    lines[0] = "# rotavg_ros graph v1"
    path.write_text("\n".join(lines) + "\n")
    stored = load_graph(path)
    assert len(stored.measurements) == 1
    assert stored.orientations == {} and stored.depth is None


def test_foreign_file_is_refused_with_its_name(tmp_path: Path) -> None:
    path = tmp_path / "plain.g2o"
    path.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match="plain.g2o"):
        load_graph(path)


def _graph() -> ViewGraph:
    g = ViewGraph()
    g.add_edge("a", "b", np.eye(3))
    return g


def test_save_is_atomic_fsynced_and_leaves_no_temporary_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    path = tmp_path / "g.g2o"
    save_graph(path, _graph())
    path.chmod(0o640)
    synced: list[int] = []
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        synced.append(fd)
        real_fsync(fd)

    monkeypatch.setattr(graph_store.os, "fsync", fsync)
    g = _graph()
    g.add_edge("b", "c", np.eye(3))
    assert save_graph(path, g) == 2
    assert len(synced) == 2  # the file, then its directory
    assert (path.stat().st_mode & 0o777) == 0o640  # permissions kept
    assert os.listdir(tmp_path) == ["g.g2o"]
    saved = path.read_text()

    def fail(src: object, dst: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(graph_store.os, "replace", fail)
    with pytest.raises(OSError, match="No space"):
        save_graph(path, _graph())
    assert path.read_text() == saved  # the old file is untouched
    assert os.listdir(tmp_path) == ["g.g2o"]  # the temporary file is gone


def test_check_writable_names_a_missing_or_unwritable_directory(tmp_path: Path) -> None:
    check_writable(tmp_path / "new.g2o")  # need not exist yet
    with pytest.raises(ValueError, match="does not exist"):
        check_writable(tmp_path / "missing" / "g.g2o")
    with pytest.raises(ValueError, match="is a directory"):
        check_writable(tmp_path)
    # /proc refuses new files even to root (a chmod'ed folder would not stop root).
    with pytest.raises(ValueError, match="not writable"):
        check_writable("/proc/rotavg_graph.g2o")
    assert os.listdir(tmp_path) == []  # the probe file is gone
