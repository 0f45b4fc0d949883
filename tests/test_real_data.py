"""Benchmarks on the shared data (skipped cleanly when ``../shared`` is absent).

Reference numbers (measured when these tests were written, CPU, seed 0):

* Ellis Island, GT cameras only (227 nodes), default options with depths=(2,):
  mean 2.270 deg, median 0.398 deg (default depths (2, 4, 6, 8) also pick depth 2 and give
  the same numbers; Table I of the paper reports 2.2 / 0.4 for filtered DMF).
* smallGrid3D (SE-Sync), default options: median 0.048 deg, mean 0.053 deg against the
  certified optimum (GTSAM chordal: median 2.09 deg).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from benchmarks.datasets import Benchmark, load_ellis_island, load_se_sync
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.solver import RotationAverager

pytestmark = pytest.mark.usefixtures("single_torch_thread")


def _require(path: Path) -> None:
    if not path.is_file():
        pytest.skip(f"benchmark file not found: {path}")


def _score(bench: Benchmark, options: SolverOptions):
    res = RotationAverager(options).solve(bench.graph)
    assert np.all(np.isfinite(res.rotations))
    np.testing.assert_allclose(np.linalg.det(res.rotations), 1.0, atol=1e-9)
    est = {k: res.rotations[idx] for idx, k in enumerate(res.node_ids)}
    return res, evaluate(est, bench.reference)


def test_ellis_island_gt_protocol(shared_dir: Path) -> None:
    _require(shared_dir / "data/1dsfm/Ellis_Island/Ellis_Island.npz")
    bench = load_ellis_island(shared_dir)
    assert bench.graph.num_nodes == 227
    assert bench.graph.edge_arrays().num_edges == 20010
    res, stats = _score(bench, SolverOptions.from_flat(depths=(2,)))
    assert stats.num_nodes == 227
    assert res.depth == 2
    assert int(res.component.max()) == 0  # one connected component
    assert 0 < res.num_filtered < 20010
    # Measured 2.270 / 0.398 deg; fail on a regression well inside the paper's band.
    assert stats.median_deg < 0.45, stats.median_deg
    assert stats.mean_deg < 2.5, stats.mean_deg


def test_small_grid_3d_se_sync(shared_dir: Path) -> None:
    _require(shared_dir / "data/se_sync_3d/smallGrid3D.g2o")
    _require(shared_dir / "reference/se_sync_3d/smallGrid3D.npz")
    bench = load_se_sync(shared_dir, "smallGrid3D")
    av = RotationAverager(SolverOptions())
    edges = bench.graph.edge_arrays()
    assert av.is_sparse(bench.graph.num_nodes, edges.num_edges)  # SLAM grid: sparse mode
    res, stats = _score(bench, SolverOptions())
    assert stats.num_nodes == bench.graph.num_nodes == 125
    # GTSAM's chordal initialisation reaches a 2.09 deg median; measured 0.048 deg.
    assert stats.median_deg < 0.5, stats.median_deg
    assert stats.mean_deg < 1.0, stats.mean_deg
