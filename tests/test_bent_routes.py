"""A route bent around a wrong step (rotavg_ros.core.robust.bent_routes)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmarks import regime_cases as rc
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.robust.bent_routes import leave_one_out_drops
from rotavg_ros.core.robust.gauss_newton import refine_least_squares, residual_angles
from rotavg_ros.core.so3 import rotation_about_axis
from rotavg_ros.core.solver import RotationAverager


def test_a_loops_misclosure_falls_alike_whichever_step_leaves_it() -> None:
    # One loop of 8 unit-weight edges, misclosed by 12 deg about z, and a pendant node on
    # a bridge. Least squares spreads the misclosure evenly (1.5 deg an edge, leverage
    # 7/8): leaving any loop edge out frees the whole sum, 8 (theta / 8)^2 = theta^2 / 8;
    # the bridge has no loop to free.
    theta = math.radians(12.0)
    loop = 8
    i = np.array(list(range(loop)) + [0])
    j = np.array([(k + 1) % loop for k in range(loop)] + [loop])
    R = np.repeat(np.eye(3)[None], loop + 1, axis=0)
    R[3] = rotation_about_axis([0.0, 0.0, 1.0], theta)
    w = np.ones(i.size)
    rot = refine_least_squares(np.repeat(np.eye(3)[None], loop + 1, axis=0), i, j, R, w,
                               iterations=30, tolerance=1e-12)
    np.testing.assert_allclose(residual_angles(rot, i, j, R)[:loop], theta / loop, rtol=1e-6)
    drops = leave_one_out_drops(rot, i, j, R, w, np.ones(i.size, bool), np.arange(i.size))
    np.testing.assert_allclose(drops[:loop], theta ** 2 / loop, rtol=1e-6)
    assert drops[loop] == 0.0


def _errors(case: rc.RegimeCase, keep: np.ndarray | None = None) -> tuple[int, float]:
    g = case.view_graph(keep)
    res = RotationAverager(SolverOptions()).solve(g)
    est = {k: res.rotations[g.index_of(k)] for k in range(case.num_nodes)}
    return res.num_distrusted_odometry, evaluate(est, dict(enumerate(case.gt))).median_deg


def _lost_track_route(seed: int, noise_model: str) -> rc.RegimeCase:
    base = rc.revisit_case("revisit/car/2x400", 400, 2, runs=8, trajectory="car", seed=seed,
                           noise_model=noise_model)
    return rc.broken_odometry_case("stress/odometry-breaks/car/revisit/2x400-clean", base,
                                   steps=1, seed=seed)


# regime_stress's lost-track car route (a route driven twice, one wrong step among the car's
# turns, jumps common), at seeds where the fit trusting the odometry bends around the step:
# - 3: no closure rejected across it (20.02 deg median before the cut; the oracle's 5.74);
# - 22: a wrong step of 108 deg among 76 jumps, 33 of 117 closures rejected. Least squares
#   without the step, from the bent fit, fitted the 84 kept closures as they were bent and
#   re-admitted none of the 33: the cut did not pay (16.2 deg median; the oracle's 3.5).
#   GNC-TLS over every edge after the cut takes them back;
# - 1: the cut lowers the truncated squares by 2.85 caps, which the break test's three caps
#   refused (7.70 deg median; the oracle's 3.91). A true turn's cut lowers them by
#   chi2_3 sigma^2: one cap but once in a thousand (BENT_CUT_PENALTY).
@pytest.mark.parametrize("seed", [3, 22, 1], ids=["no-closure-rejected", "bend-rejected-closures",
                                                  "cut-worth-one-to-three-caps"])
def test_a_route_bent_around_a_wrong_turn_is_cut_there(seed: int) -> None:
    case = _lost_track_route(seed, "folded")
    cut, median = _errors(case)
    assert cut >= 1
    assert median < 1.1 * _errors(case, case.inlier)[1]


@pytest.mark.parametrize("seed", [3, 22, 1])
def test_a_route_whose_turns_are_all_true_keeps_them(seed: int) -> None:
    # The same routes without the wrong step: no jump's cut pays for itself, at one cap.
    base = rc.revisit_case("revisit/car/2x400", 400, 2, runs=8, trajectory="car", seed=seed,
                           noise_model="folded")
    cut, median = _errors(base)
    assert cut == 0
    assert median < 1.05 * _errors(base, base.inlier)[1]

