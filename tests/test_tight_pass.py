"""The tight pass's threshold: at most ``GNC_SIGMAS`` noise scales, fewer where the fitted
inlier/outlier mixture crosses below (``verify.tight_sigmas``)."""

from __future__ import annotations

import math

import numpy as np

from benchmarks import regime_cases as rc
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.robust.noise import NoiseModel, outlier_crossing
from rotavg_ros.core.robust.verify import GNC_SIGMAS, tight_sigmas
from rotavg_ros.core.solver import RotationAverager


def test_three_axes_at_a_few_degrees_keep_four_scales() -> None:
    # A uniform rotation's angle is rare near zero on three axes: the crossing lies beyond
    # 4 scales at up to 5 deg of noise, whatever the outlier share.
    for deg in (0.5, 1.0, 2.0, 5.0):
        s = math.radians(deg)
        for p in (0.5, 0.8, 0.95):
            assert tight_sigmas(s, NoiseModel(s, p, 0.0, 3)) == GNC_SIGMAS


def test_a_planar_problem_with_outliers_crosses_below_four_scales() -> None:
    s = math.radians(5.0)
    k = tight_sigmas(s, NoiseModel(s, 0.8, 0.0, 1))
    assert 2.9 < k < 3.2
    # There a half-normal inlier's density equals a uniform heading's.
    inlier = 0.8 * math.sqrt(2.0 / math.pi) / s * math.exp(-k * k / 2.0)
    outlier = 0.2 / math.pi
    assert abs(inlier / outlier - 1.0) < 0.01
    assert tight_sigmas(s, NoiseModel(s, 0.95, 0.0, 1)) > k  # fewer outliers: wider
    assert tight_sigmas(s, NoiseModel(s, 1.0, 0.0, 1)) == GNC_SIGMAS  # none: 4 scales
    # Three axes at 20 deg: a wrong edge is likely near the inliers there too.
    big = math.radians(20.0)
    assert tight_sigmas(big, NoiseModel(big, 0.8, 0.0, 3)) < 3.7
    assert outlier_crossing(s, 1.0, 1.0, 1) == 1.0
    assert outlier_crossing(0.0, 0.5, 1.0, 1) == 1.0


def _median_error(case: rc.RegimeCase, keep: np.ndarray | None = None) -> float:
    g = case.view_graph(keep)
    res = RotationAverager(SolverOptions()).solve(g)
    est = {k: res.rotations[g.index_of(k)] for k in range(case.num_nodes)}
    return evaluate(est, dict(enumerate(case.gt))).median_deg


def test_default_profile_on_a_planar_grid_walk_with_false_closures() -> None:
    # A planar robot walking a 15 x 15 grid city: 1,000 poses, 450 true closures at revisited
    # corners, 20% false, 5 deg of heading noise. At 4 noise scales (20 deg) the tight pass
    # kept false closures that the drift lets in: 8.06 deg median against the oracle's 3.56.
    base = rc.grid_walk_case("grid-walk/x", 1000, 15, closures=450, false_random=0.2, seed=0)
    case = rc.planar_case("planar/grid-walk/x", base, odo_noise_deg=5.0, loop_noise_deg=5.0,
                          seed=0)
    assert _median_error(case) < 1.15 * _median_error(case, case.inlier)
