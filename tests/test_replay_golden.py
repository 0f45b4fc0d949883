"""The sample bags replay to the same orientations as the golden files in tests/golden/."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rotavg_ros import cli
from rotavg_ros.core.so3 import geodesic_distance
from rotavg_ros.io.g2o import read_g2o_vertices

REPO = Path(__file__).resolve().parents[1]
GOLDEN = REPO / "tests" / "golden"


@pytest.mark.parametrize("bag", ["slam_false_loops", "smallgrid3d_odom"])
def test_replay_matches_golden_orientations(bag: str, tmp_path: Path) -> None:
    if not (REPO / "bags" / bag / "metadata.yaml").is_file():
        pytest.skip(f"bags/{bag} not generated (scripts/make_sample_bags.py)")
    out = tmp_path / f"{bag}.g2o"
    assert cli.main(["replay", str(REPO / "bags" / bag), "--quiet",
                     "--output-g2o", str(out)]) == 0
    ids, rots = read_g2o_vertices(out)
    gold_ids, gold_rots = read_g2o_vertices(GOLDEN / f"{bag}.g2o")
    assert list(ids) == list(gold_ids)
    # Same code, same seed: equal up to float rounding of another CPU's vector units. That
    # rounding can tip a discrete step of the fit: the same commit gave smallgrid3d_odom
    # 3.6e-4 deg apart on an AVX-512 machine and on CI's; code changes moved it 2.5e-3 deg.
    diff_deg = np.degrees(geodesic_distance(np.asarray(rots), np.asarray(gold_rots)))
    assert float(diff_deg.max()) < 1e-3, f"max difference {diff_deg.max():.2e} deg"
