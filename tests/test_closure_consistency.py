"""Pairwise consistency of loop closures over an odometry chain (closure_consistency)."""

from __future__ import annotations

import numpy as np

from benchmarks import regime_cases as rc
from rotavg_ros.core.robust.closure_consistency import (
    CHI2_3_Q25,
    LOOP_BOUND_CONFIDENCE,
    LOOP_BOUND_Z,
    LOOP_QUANTILE,
    ClosureLoops,
    _mutually_consistent,
    closure_loops,
    consistent_closures,
    loop_noise_scale,
    neighbour_supported,
)
from rotavg_ros.core.robust.odometry_start import odometry_rotations
from rotavg_ros.core.so3 import rotation_about_axis


def test_odometry_rotations_compose_the_chain_and_split_at_gaps() -> None:
    rng = np.random.default_rng(0)
    gt = rc.chain_trajectory(6, rng)
    i = np.array([0, 1, 3, 4, 0])
    j = np.array([1, 2, 4, 5, 3])
    R = rc.relative(gt, i, j)
    odometry = np.array([True, True, True, True, False])  # 2 -- 3 missing: two pieces
    Q, piece = odometry_rotations(6, i, j, R, odometry)
    assert piece.tolist() == [0, 0, 0, 1, 1, 1]
    for k in (1, 2):  # R_k R_0^T exactly, within the first piece
        assert np.allclose(Q[k], gt[k] @ gt[0].T)
    assert np.allclose(Q[3], np.eye(3))
    assert np.allclose(Q[5], gt[5] @ gt[3].T)


def test_a_group_of_consistent_false_closures_is_dropped_and_the_true_ones_kept() -> None:
    # 600 keyframes, 20 true closures and 14 false ones in groups of 4-8 that agree with
    # each other: every false closure goes, at most one true one with it.
    case = rc.chain_case("test/pcm", 600, closures=20, false_grouped=0.4, seed=3)
    assert case.inlier is not None
    odometry = case.odometry
    w = np.ones(case.num_edges)
    sigma = np.radians(1.5) / np.sqrt(3.0)  # the generator's noise, per axis
    keep = consistent_closures(case.num_nodes, case.i, case.j, case.R, w, odometry,
                               [sigma])[0]
    assert keep[odometry].all()
    assert not keep[~case.inlier].any()
    assert np.count_nonzero(~keep & case.inlier) <= 1


def test_chi2_3_q25_is_the_loop_quantile_of_chi_square_with_3_dof() -> None:
    from scipy import stats

    assert abs(CHI2_3_Q25 - stats.chi2.ppf(LOOP_QUANTILE, 3)) < 1e-3


def test_the_loops_noise_scale_is_the_odometrys_despite_many_false_closures() -> None:
    """The closures' loops over the odometry read the generator's noise (1.5 deg angles,
    0.87 deg per axis) with 40% random false closures, whatever a fit says (36 true
    closures: over 12 draws 0.70-1.49 deg, 0.58-1.34 from the true closures alone); without
    odometry, or with too few closures, there is no answer."""
    true_sigma = np.radians(1.5) / np.sqrt(3.0)
    for seed in (0, 1):
        case = rc.chain_case("test/loops", 1000, closures=36, false_random=0.4, seed=seed)
        w = np.ones(case.num_edges)
        sigma = loop_noise_scale(case.num_nodes, case.i, case.j, case.R, w, case.odometry)
        assert 0.5 * true_sigma < sigma < 2.0 * true_sigma
        # Information weights 4x (a quarter of the variance): the scale of a unit-weight
        # edge doubles.
        doubled = loop_noise_scale(case.num_nodes, case.i, case.j, case.R, 4.0 * w,
                                   case.odometry)
        assert abs(doubled - 2.0 * sigma) < 1e-9
    none = np.zeros(case.num_edges, bool)
    assert np.isnan(loop_noise_scale(case.num_nodes, case.i, case.j, case.R, w, none))
    few = case.odometry | (np.cumsum(~case.odometry) <= 3)
    assert np.isnan(loop_noise_scale(case.num_nodes, case.i[few], case.j[few], case.R[few],
                                     w[few], case.odometry[few]))


def test_the_loops_upper_bound_is_the_order_statistic_of_its_rank() -> None:
    """Eight closures, each on its own stretch of odometry of unit variance: the bound is
    the 6th lowest ratio (squared loop angle over 2, its variance), the point estimate the
    25% quantile, each over chi-square's 25% quantile."""
    angles = np.radians([0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0])
    E = rotation_about_axis(np.array([0.0, 0.0, 1.0]), angles)
    pa = np.arange(8, dtype=float) * 10.0
    loops = ClosureLoops(np.arange(8), np.arange(8), np.zeros(8, np.int64), E, pa, pa + 1.0,
                         np.ones(8))
    none = np.zeros(0)
    args = (8, none.astype(np.int64), none.astype(np.int64), np.zeros((0, 3, 3)), none,
            np.zeros(0, bool), loops)
    ratio = angles ** 2 / 2.0
    assert np.isclose(loop_noise_scale(*args, upper=True) ** 2 * CHI2_3_Q25, ratio[5])
    assert np.isclose(loop_noise_scale(*args) ** 2 * CHI2_3_Q25,
                      np.quantile(ratio, LOOP_QUANTILE))


def test_loop_bound_z_is_the_normal_quantile_at_its_confidence() -> None:
    from scipy import stats

    assert abs(LOOP_BOUND_Z - stats.norm.ppf(LOOP_BOUND_CONFIDENCE)) < 1e-3


def test_the_loops_upper_bound_is_looser_with_few_closures() -> None:
    """Further above the point estimate with 8 closures than with 40, and with 40 about
    the generator's scale (Gaussian noise, 12 draws: 0.82-2.01 times it; the loops share
    odometry, so their ratios are not independent and the bound no sure 99% one: 3 of
    the 12 were below the true scale)."""
    true_sigma = np.radians(1.5) / np.sqrt(3.0)  # tangent noise: 1.5 / sqrt(3) per axis
    spread: dict[int, list[float]] = {8: [], 40: []}
    for closures in (8, 40):
        for seed in range(12):
            case = rc.chain_case("test/bound", 500, closures=closures, seed=seed,
                                 odo_noise_deg=1.5, loop_noise_deg=1.5,
                                 noise_model="tangent")
            w = np.ones(case.num_edges)
            args = (case.num_nodes, case.i, case.j, case.R, w, case.odometry)
            scale, bound = loop_noise_scale(*args), loop_noise_scale(*args, upper=True)
            if closures == 40:
                assert 0.6 * true_sigma < bound < 2.5 * true_sigma
            spread[closures].append(bound / scale)
    assert np.median(spread[8]) > 1.1 * np.median(spread[40])


def test_nothing_is_dropped_without_odometry_or_a_noise_scale() -> None:
    case = rc.chain_case("test/pcm", 300, closures=10, false_grouped=0.4, seed=1)
    w = np.ones(case.num_edges)
    none = np.zeros(case.num_edges, bool)
    assert consistent_closures(case.num_nodes, case.i, case.j, case.R, w, none, [0.01])[0].all()
    assert consistent_closures(case.num_nodes, case.i, case.j, case.R, w, case.odometry,
                               [float("nan")])[0].all()


def _greedy_reference(conflict: np.ndarray) -> np.ndarray:
    """The rule as written: drop the member in the most conflicts (lowest index on ties),
    remove its conflicts, repeat."""
    conflict = conflict.copy()
    alive = np.ones(conflict.shape[0], bool)
    while conflict.any():
        worst = int(np.argmax(conflict.sum(axis=1)))
        alive[worst] = False
        conflict[worst] = False
        conflict[:, worst] = False
    return alive


def test_the_greedy_set_follows_its_rule_and_has_no_conflict() -> None:
    rng = np.random.default_rng(3)
    for _ in range(200):
        n = int(rng.integers(1, 40))
        conflict = rng.random((n, n)) < rng.random()
        conflict |= conflict.T
        np.fill_diagonal(conflict, False)
        alive = _mutually_consistent(conflict)
        assert not conflict[np.ix_(alive, alive)].any()
        np.testing.assert_array_equal(alive, _greedy_reference(conflict))


def _supported_closures(case: rc.RegimeCase, R: np.ndarray) -> np.ndarray:
    """Per edge of ``case`` (measurements ``R``): whether a neighbouring closure supports
    it (False for odometry and untestable closures)."""
    w = np.ones(case.num_edges)
    loops = closure_loops(case.num_nodes, case.i, case.j, R, w, case.odometry)
    assert loops is not None
    sigma = loop_noise_scale(case.num_nodes, case.i, case.j, R, w, case.odometry, loops)
    out = np.zeros(case.num_edges, bool)
    out[loops.testable[neighbour_supported(case.num_nodes, case.i, case.j, loops, sigma)[0]]] = True
    return out


def test_runs_of_true_closures_support_each_other_and_random_false_ones_have_no_support(
) -> None:
    """A route driven three times, its true closures in runs (every second keyframe, the
    same place give or take 2) and 30% random false closures: every true closure but a
    few at the runs' ends is supported, no false one; one closure of a run turned 40 deg
    off loses its support, and its neighbours keep theirs from the rest of the run."""
    case = rc.revisit_case("test/support", 300, 3, runs=10, false_random=0.3, seed=0)
    assert case.inlier is not None
    closures = ~case.odometry
    supported = _supported_closures(case, case.R)
    assert not supported[~case.inlier].any()
    assert np.count_nonzero(supported & case.inlier & closures) >= 0.9 * np.count_nonzero(
        case.inlier & closures)
    true_closures = np.flatnonzero(case.inlier & closures & supported)
    middle = int(true_closures[len(true_closures) // 2])
    R = case.R.copy()
    R[middle] = rotation_about_axis(np.array([0.0, 0.0, 1.0]), np.radians(40.0))[0] @ R[middle]
    again = _supported_closures(case, R)
    assert not again[middle]
    assert np.array_equal(np.delete(again, middle), np.delete(supported, middle))


def test_no_closure_is_supported_without_neighbours_or_a_noise_scale() -> None:
    """Closures far apart from each other (a chain's sparse ones) have no neighbour; a NaN
    scale supports nothing."""
    case = rc.chain_case("test/sparse", 600, closures=12, seed=1)
    assert not _supported_closures(case, case.R).any()
    w = np.ones(case.num_edges)
    loops = closure_loops(case.num_nodes, case.i, case.j, case.R, w, case.odometry)
    assert loops is not None
    assert not neighbour_supported(case.num_nodes, case.i, case.j, loops, float("nan"))[0].any()
