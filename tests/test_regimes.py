"""Fast subset of the regime benchmark: generators are deterministic and correct, and our
solver runs and is scored on tiny cases (no claim that it beats the peers)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from benchmarks import regime_cases as rc
from benchmarks.regimes import ORACLE, OURS, Result, run_method, summarize
from rotavg_ros.core.so3 import rotation_angle
from rotavg_ros.core.solver import ArraySolution


def _angles_deg(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    return np.degrees(rotation_angle(A @ np.swapaxes(B, -1, -2)))


def _tiny_chain(name: str = "test/chain60") -> rc.RegimeCase:
    return rc.chain_case(name, 60, closures=4, false_random=0.2, false_grouped=0.2)


def _tiny_dense(name: str = "test/dense30") -> rc.RegimeCase:
    return rc.dense_case(name, 30, 12, outliers=0.3)


@pytest.mark.parametrize("make", [_tiny_chain, _tiny_dense])
def test_generators_are_deterministic(make: object) -> None:
    a, b = make(), make()  # type: ignore[operator]
    assert np.array_equal(a.i, b.i) and np.array_equal(a.j, b.j)
    assert np.array_equal(a.R, b.R) and np.array_equal(a.gt, b.gt)
    assert a.inlier is not None and np.array_equal(a.inlier, b.inlier)
    other = make("test/other")  # type: ignore[operator]
    assert not np.array_equal(other.gt, a.gt)


def test_noise_free_generation_is_exact() -> None:
    rng = np.random.default_rng(0)
    gt = rc.chain_trajectory(40, rng)
    i = np.arange(39)
    R = rc.perturb(rc.relative(gt, i, i + 1), 0.0, rng)
    assert np.allclose(R, gt[i] @ np.swapaxes(gt[i + 1], -1, -2), atol=1e-12)
    case = rc.dense_case("test/clean", 25, 10, outliers=0.0, noise_deg=0.0)
    assert case.inlier is not None and case.inlier.all()
    assert _angles_deg(case.R, rc.relative(case.gt, case.i, case.j)).max() < 1e-6
    # Grouped false closures with zero noise agree with each other exactly: one W.
    gi, gj, gR = rc.grouped_false_edges(gt, set(), 1, (5, 5), 10, 0.0, rng)
    W = np.swapaxes(gt[gi], -1, -2) @ gR @ gt[gj]
    assert gi.size == 5 and np.allclose(W, W[0], atol=1e-9)


@pytest.mark.parametrize("make", [_tiny_chain, _tiny_dense])
def test_false_edges_are_wrong_and_inliers_are_close(make: object) -> None:
    case = make()  # type: ignore[operator]
    assert case.inlier is not None and (~case.inlier).sum() >= 2
    err = _angles_deg(case.R, rc.relative(case.gt, case.i, case.j))
    assert err[~case.inlier].min() >= rc.MIN_FALSE_DEG - 1e-6
    assert np.median(err[case.inlier]) < 5.0  # 1.5-2 deg noise


def test_seed_and_noise_model_draw_the_same_regime_afresh() -> None:
    base = rc.dense_case("test/draw", 40, 12, outliers=0.2, noise_deg=5.0)
    again = rc.dense_case("test/draw", 40, 12, outliers=0.2, noise_deg=5.0, seed=0,
                          noise_model="folded")
    assert np.array_equal(base.R, again.R)  # the defaults are the recorded draw
    other = rc.dense_case("test/draw", 40, 12, outliers=0.2, noise_deg=5.0, seed=1)
    assert not np.array_equal(other.gt, base.gt)
    # Both noise models give an RMS error angle of sigma; only the folded one peaks at 0.
    rng = np.random.default_rng(3)
    eye = np.tile(np.eye(3), (20000, 1, 1))
    folded = _angles_deg(rc.perturb(eye, 5.0, rng, "folded"), eye)
    tangent = _angles_deg(rc.perturb(eye, 5.0, rng, "tangent"), eye)
    for err in (folded, tangent):
        assert abs(np.sqrt(np.mean(err ** 2)) - 5.0) < 0.1
    assert np.mean(folded < 1.0) > 5 * np.mean(tangent < 1.0)
    with pytest.raises(ValueError, match="noise model"):
        rc.perturb(eye[:2], 1.0, rng, "laplace")
    with pytest.raises(ValueError, match="noise model"):
        rc.all_cases(0, "laplace")
    assert list(rc.all_cases(1, "tangent")) == list(rc.all_cases())


def test_weighted_case_measures_odometry_and_closures_at_their_own_noise() -> None:
    """A front end's report: true odometry at its own noise, true closures at theirs, the
    false closures as they were, and each edge weighted by ``1 / sigma^2``."""
    base = rc.chain_case("test/chain300", 300, closures=30, false_random=0.2,
                         odo_noise_deg=0.0, loop_noise_deg=0.0)
    case = rc.weighted_case("test/weighted", base, odo_noise_deg=0.5, loop_noise_deg=3.0)
    assert case.inlier is not None and base.inlier is not None
    assert np.array_equal(case.gt, base.gt) and np.array_equal(case.inlier, base.inlier)
    odo, true = case.odometry, case.inlier
    assert case.weight is not None
    np.testing.assert_allclose(case.weight[odo], 1.0 / np.radians(0.5) ** 2)
    np.testing.assert_allclose(case.weight[~odo], 1.0 / np.radians(3.0) ** 2)
    assert np.array_equal(case.R[~true], base.R[~true])
    err = _angles_deg(case.R, rc.relative(case.gt, case.i, case.j))
    rms = [float(np.sqrt(np.mean(err[m] ** 2))) for m in (odo & true, ~odo & true)]
    assert 0.4 < rms[0] < 0.6 and 2.0 < rms[1] < 4.0  # folded noise: RMS angle sigma
    again = rc.weighted_case("test/weighted", base, odo_noise_deg=0.5, loop_noise_deg=3.0)
    assert np.array_equal(again.R, case.R)


def test_heteroscedastic_and_near_false_cases_draw_what_they_say() -> None:
    """Heteroscedastic: each true edge at its own lognormal noise level, false edges as they
    were, no weights; one level per edge draws as one level does where they are equal.
    Near: every false edge redrawn 5-30 deg off the truth, the true ones as they were."""
    base = rc.chain_case("test/chain300", 300, closures=30, false_random=0.2,
                         odo_noise_deg=0.0, loop_noise_deg=0.0)
    assert base.inlier is not None
    true = base.inlier
    case = rc.heteroscedastic_case("test/hetero", base, sigma_deg=2.0)
    assert case.weight is None and case.inlier is not None
    assert np.array_equal(case.inlier, true)
    assert np.array_equal(case.R[~true], base.R[~true])
    err = _angles_deg(case.R, rc.relative(case.gt, case.i, case.j))[true]
    # lognormal(0.7) levels: a heavier tail than one level's folded noise (its 99th
    # percentile 3.8 x its median; here 8.3 x)
    assert 1.0 < np.median(err) < 2.5 and np.percentile(err, 99) > 6.0 * np.median(err)
    eye = np.tile(np.eye(3), (50, 1, 1))
    for model in rc.NOISE_MODELS:
        one = rc.perturb(eye, 3.0, np.random.default_rng(5), model)
        each = rc.perturb(eye, np.full(50, 3.0), np.random.default_rng(5), model)
        assert np.array_equal(one, each)
    near = rc.near_false_case("test/near", base)
    err = _angles_deg(near.R, rc.relative(near.gt, near.i, near.j))
    assert np.array_equal(near.R[true], base.R[true]) and near.name == "test/near"
    assert 5.0 - 1e-6 <= err[~true].min() and err[~true].max() <= 30.0 + 1e-6


def test_identity_and_reversed_cases_draw_what_they_say() -> None:
    """Identity: every false edge is the identity, the true ones as they were. Reversed:
    about half the edges given as ``(j, i, R_ij^T)``, the same measurements, so the same
    graph."""
    base = rc.chain_case("test/chain300", 300, closures=30, false_random=0.2)
    assert base.inlier is not None
    true = base.inlier
    ident = rc.identity_false_case("test/identity", base)
    assert np.array_equal(ident.R[true], base.R[true])
    assert np.allclose(ident.R[~true], np.eye(3), atol=0)
    flipped = rc.reversed_case("test/reversed", base)
    turned = flipped.i != base.i
    assert 0.4 < turned.mean() < 0.6
    assert np.array_equal(flipped.i[turned], base.j[turned])
    assert np.array_equal(flipped.R[turned], np.swapaxes(base.R[turned], 1, 2))
    a, b = base.view_graph().edge_arrays(), flipped.view_graph().edge_arrays()
    assert np.array_equal(a.i, b.i) and np.array_equal(a.j, b.j)
    assert np.allclose(a.R, b.R, atol=1e-15)


def test_biased_odometry_case_turns_every_step_the_same_way() -> None:
    """Each odometry measurement turned by the bias about its frame's z axis, the closures
    and the true / false split as they were."""
    base = rc.chain_case("test/chain300", 300, closures=30, false_random=0.2)
    biased = rc.biased_odometry_case("test/biased", base, bias_deg=0.5)
    step = np.abs(base.i - base.j) == 1
    assert np.array_equal(biased.R[~step], base.R[~step])
    assert biased.inlier is not None and base.inlier is not None
    assert np.array_equal(biased.inlier, base.inlier)
    turn = biased.R[step] @ np.swapaxes(base.R[step], 1, 2)  # Rz(bias), every step
    angle = np.degrees(np.arctan2(turn[:, 1, 0], turn[:, 0, 0]))
    assert np.allclose(angle, 0.5) and np.allclose(turn[:, 2, 2], 1.0)


def test_chain_has_no_triangles_and_odometry() -> None:
    case = _tiny_chain()
    assert rc.triangle_count(case.num_nodes, case.i, case.j) == 0
    assert case.odometry.sum() == case.num_nodes - 1 and case.has_odometry
    assert (case.i < case.j).all()
    pairs = set(zip(case.i.tolist(), case.j.tolist(), strict=True))
    assert len(pairs) == case.num_edges


def test_lattice_case_is_grid3ds_topology() -> None:
    """The lattice's snake is the odometry (every step one lattice edge), every other
    lattice neighbour a closure, the share of false closures as asked, no triangle."""
    case = rc.lattice_case("test/lattice", 5, random_false=0.2)
    assert case.num_nodes == 125 and case.num_edges == 3 * 5 * 5 * 4  # smallGrid3D's 300
    assert case.odometry.sum() == case.num_nodes - 1 and case.has_odometry
    assert rc.triangle_count(case.num_nodes, case.i, case.j) == 0
    assert case.inlier is not None and case.inlier[case.odometry].all()
    closures = ~case.odometry
    assert np.count_nonzero(~case.inlier) == round(0.2 * closures.sum())
    err = np.degrees(rotation_angle(case.R @ np.swapaxes(rc.relative(
        case.gt, case.i, case.j), 1, 2)))
    assert err[case.inlier].max() < 6.0 and err[~case.inlier].min() >= rc.MIN_FALSE_DEG


def test_grid_walk_case_closes_loops_at_revisited_corners() -> None:
    """The walk's true closures join poses at least 6 steps apart, the false ones extra
    pairs at least 20 apart, their share as asked; a city too small for the closures asked
    says so."""
    case = rc.grid_walk_case("test/grid-walk", 400, 8, closures=60, false_random=0.25)
    assert case.odometry.sum() == case.num_nodes - 1 and case.has_odometry
    assert case.inlier is not None and case.family == "slam"
    closures = ~case.odometry
    assert np.count_nonzero(closures & case.inlier) == 60
    assert np.count_nonzero(~case.inlier) == 20  # 25% of 80 closures
    assert np.all(np.abs(case.i - case.j)[closures & case.inlier] > 5)
    assert np.all(np.abs(case.i - case.j)[~case.inlier] >= 20)
    pairs = set(zip(case.i.tolist(), case.j.tolist(), strict=True))
    assert len(pairs) == case.num_edges
    with pytest.raises(ValueError, match="revisits"):
        rc.grid_walk_case("test/grid-walk", 30, 8, closures=500)


def test_survey_case_is_a_strip_flight_with_random_or_grouped_false_matches() -> None:
    """Every image matches its strip neighbours and the next strip (consecutive ids are
    true matches), the false share as asked, no pair twice; grouped false matches come in
    runs of five that agree with each other (their 4-cycles close) and not with the
    truth."""
    case = rc.survey_case("test/survey", 6, 30, false=0.3)
    assert case.num_nodes == 180 and case.family == "sfm" and case.inlier is not None
    assert np.all(case.inlier[np.abs(case.i - case.j) == 1])
    assert 12.0 < 2 * np.count_nonzero(case.inlier) / case.num_nodes < 16.0
    assert abs(np.count_nonzero(~case.inlier) / case.num_edges - 0.3) < 0.01
    assert len(set(zip(case.i.tolist(), case.j.tolist(), strict=True))) == case.num_edges
    grouped = rc.survey_case("test/survey", 6, 30, false=0.2, grouped=True, noise_deg=0.0)
    assert grouped.inlier is not None
    false = np.flatnonzero(~grouped.inlier)
    assert false.size % 5 == 0 and abs(false.size / grouped.num_edges - 0.2) < 0.01
    measured = {(a, b): R for a, b, R in zip(grouped.i.tolist(), grouped.j.tolist(),
                                             grouped.R, strict=True)}
    for start in false[::5].tolist():
        a, b = int(grouped.i[start]), int(grouped.j[start])
        assert b - a >= 30 and (a + 4, b + 4) in measured
        cycle = (measured[a, b] @ rc.relative(grouped.gt, np.array([b]), np.array([b + 1]))[0]
                 @ measured[a + 1, b + 1].T
                 @ rc.relative(grouped.gt, np.array([a + 1]), np.array([a]))[0])
        assert np.degrees(rotation_angle(cycle)) < 1e-6
        off = measured[a, b] @ rc.relative(grouped.gt, np.array([a]), np.array([b]))[0].T
        assert np.degrees(rotation_angle(off)) >= rc.MIN_FALSE_DEG



def test_city10000_case_reads_headings_and_picks_each_hypothesis_by_the_truth(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A five-pose file in City10000's format: headings become rotations about z with
    ``R_i R_j^T`` the measured turn ``theta_j - theta_i``; at the two-hypothesis step the
    case takes the one the truth agrees with (here the second), or with
    ``wrong_hypotheses`` the other, marked false; without gtsam's data the suite leaves the
    two City10000 cases out."""
    truth = np.array([0.0, 0.1, 1.6, 1.5, -3.0])
    lines = ["EDGE2 0 1 1 0 1 1.0 0.0 0.1", "EDGE2 1 1 2 0 2 1.0 0.0 0.9 1.0 0.0 1.5",
             "EDGE2 2 1 3 0 1 1.0 0.0 -0.1", "EDGE2 3 1 4 0 1 1.0 0.0 1.78318531",
             "EDGE2 0 1 3 0 1 1.0 0.0 1.5"]
    (tmp_path / "T1_city10000_04.txt").write_text("\n".join(lines) + "\n")
    (tmp_path / "ISAM2_GT_city10000.txt").write_text(
        "\n".join(f"{k} 0 {t}" for k, t in enumerate(truth)) + "\n")
    case = rc.city10000_case("real/city10000", tmp_path)
    assert case.family == "real" and case.inlier is None and case.num_edges == 5
    assert np.max(_angles_deg(case.R, rc.relative(case.gt, case.i, case.j))) < 1e-6
    assert np.allclose(case.gt[:, 2, 2], 1.0) and case.has_odometry
    wrong = rc.city10000_case("slam/city10000/lost-track", tmp_path, wrong_hypotheses=True)
    assert wrong.family == "slam" and wrong.inlier is not None
    assert wrong.inlier.tolist() == [True, False, True, True, True]
    assert abs(np.degrees(rotation_angle(wrong.R[1])) - np.degrees(0.9)) < 1e-6
    monkeypatch.setattr(rc, "find_gtsam_data", lambda: tmp_path)
    assert "slam/city10000/lost-track200" in rc.all_cases()
    monkeypatch.setattr(rc, "find_gtsam_data", lambda: None)
    assert not any("city10000" in name for name in rc.all_cases())

def test_city10000_regenerated_case_keeps_the_topology_and_draws_false_closures(
        tmp_path: Path) -> None:
    """A 120-pose file in City10000's format, headings regenerated without noise: every
    true edge is exactly the truth's turn, the random false closures (never odometry) are
    at least ``MIN_FALSE_DEG`` off, each run of grouped closures joins two stretches 50
    ids apart or more, all its closures off by one turn of 20 deg or more; the same seed
    draws the same case."""
    rng = np.random.default_rng(3)
    truth = np.cumsum(rng.normal(0.0, 0.1, 120))
    pairs = [(k, k + 1) for k in range(119)] + [(k, k + 60) for k in range(40)]
    (tmp_path / "T1_city10000_04.txt").write_text("".join(
        f"EDGE2 {a} 1 {b} 0 1 1.0 0.0 {truth[b] - truth[a]}\n" for a, b in pairs))
    (tmp_path / "ISAM2_GT_city10000.txt").write_text(
        "\n".join(f"{k} 0 {t}" for k, t in enumerate(truth)) + "\n")
    case = rc.city10000_regenerated_case("test/city", tmp_path, noise_deg=0.0,
                                         random_false=0.25, groups=2)
    assert case.family == "slam" and case.inlier is not None and case.num_nodes == 120
    off = _angles_deg(case.R, rc.relative(case.gt, case.i, case.j))
    assert off[case.inlier].max() < 1e-6
    random_false = ~case.inlier[:len(pairs)]
    assert random_false.sum() == 10 and not random_false[:119].any()
    assert off[:len(pairs)][random_false].min() >= rc.MIN_FALSE_DEG
    gi, gj = case.i[len(pairs):], case.j[len(pairs):]
    assert not case.inlier[len(pairs):].any() and 10 <= gi.size <= 20
    starts = np.flatnonzero(np.r_[True, np.diff(gi) != 1])
    assert starts.size == 2  # two runs (k, k + gap), each of consecutive ids
    for lo, hi in zip(starts, np.r_[starts[1:], gi.size], strict=True):
        assert 5 <= hi - lo <= 10 and np.all(np.diff(gj[lo:hi]) == 1)
        assert np.all(gj[lo:hi] - gi[lo:hi] > 50)
        turns = off[len(pairs) + lo:len(pairs) + hi]
        assert turns.min() >= 20.0 and np.ptp(turns) < 1e-6
    again = rc.city10000_regenerated_case("test/city", tmp_path, noise_deg=0.0,
                                          random_false=0.25, groups=2)
    assert np.array_equal(again.R, case.R) and np.array_equal(again.i, case.i)


def test_manhattan_regenerated_case_reads_the_file_and_keeps_its_topology(
        tmp_path: Path) -> None:
    """A 40-pose file in the Manhattan world's format (``VERTEX2`` rows, ``EDGE2 i j x y
    theta`` and an information matrix, ``EQUIV`` rows): the vertices' headings are the
    truth, every ``EDGE2`` row an edge in the file's direction, ``EQUIV`` rows none; headings
    regenerated without noise fit the truth exactly; vertex ids with a gap are refused."""
    rng = np.random.default_rng(4)
    truth = np.cumsum(rng.normal(0.0, 0.5, 40))
    pairs = [(k + 1, k) for k in range(39)] + [(k + 20, k) for k in range(15)]
    text = "".join(f"VERTEX2 {k} {k} 0 {t}\n" for k, t in enumerate(truth))
    text += "".join(f"EDGE2 {a} {b} 1 0 0.3 1 0 1 1 0 0\n" for a, b in pairs)
    (tmp_path / "w10000.graph").write_text(text + "EQUIV 21 1\n")
    case = rc.manhattan_regenerated_case("test/manhattan", tmp_path, noise_deg=0.0,
                                         random_false=0.2)
    assert case.num_nodes == 40 and case.num_edges == len(pairs)
    assert case.inlier is not None
    assert list(zip(case.i.tolist(), case.j.tolist(), strict=True)) == pairs
    assert np.allclose(case.gt[:, 2, 2], 1.0)
    off = _angles_deg(case.R, rc.relative(case.gt, case.i, case.j))
    assert off[case.inlier].max() < 1e-6 and (~case.inlier).sum() == 3
    assert not (~case.inlier[:39]).any()  # odometry never false
    (tmp_path / "w10000.graph").write_text(text.replace("VERTEX2 7 ", "VERTEX2 70 "))
    with pytest.raises(ValueError, match="vertex ids"):
        rc.manhattan_regenerated_case("test/manhattan", tmp_path, noise_deg=0.0)


def test_car_trajectory_drives_straight_and_turns_sharply() -> None:
    """Most steps small (straight runs), about one in ten at least 10 deg (the turns), none
    much above 90 deg; rotations proper; pitch and roll small; the same draw twice; the chain and
    route generators take it by name and keep the smooth walk by default."""
    from rotavg_ros.core.so3 import rotation_angle

    gt = rc.car_trajectory(2000, np.random.default_rng(0))
    steps = np.degrees(rotation_angle(gt[1:] @ np.swapaxes(gt[:-1], 1, 2)))
    assert np.median(steps) < 1.0 and 0.05 < np.mean(steps > 10.0) < 0.2
    assert steps.max() < 91.0  # (180 deg over 2 keyframes, plus the slopes)
    assert np.allclose(gt @ np.swapaxes(gt, 1, 2), np.eye(3)) and np.all(np.linalg.det(gt) > 0)
    assert np.degrees(np.arccos(np.clip(gt[:, 2, 2], -1.0, 1.0))).max() < 10.0  # tilt
    assert np.array_equal(gt, rc.car_trajectory(2000, np.random.default_rng(0)))
    car = rc.chain_case("test/car", 300, closures=10, trajectory="car")
    smooth = rc.chain_case("test/car", 300, closures=10)
    assert not np.allclose(car.gt, smooth.gt)
    assert np.array_equal(smooth.gt, rc.chain_case("test/car", 300, closures=10,
                                                   trajectory="smooth").gt)
    route = rc.revisit_case("test/car-route", 100, 2, runs=3, trajectory="car")
    assert route.num_nodes == 200


def test_large_graphs_are_as_large_as_they_say_and_deterministic() -> None:
    """``benchmarks.large_graphs``: five distinct graphs of 2,000 nodes or more, each with
    its true edges known (the oracle's) and false edges in it, drawn the same twice."""
    from benchmarks.large_graphs import large_cases

    cases = [build() for build in large_cases(0)]
    assert len({c.name for c in cases}) == 5
    for c in cases:
        assert c.num_nodes >= 2000 and c.inlier is not None
        assert 50 <= np.count_nonzero(~c.inlier) < 0.35 * c.num_edges
    again = large_cases(0)[0]()
    assert np.array_equal(again.R, cases[0].R) and np.array_equal(again.i, cases[0].i)


def test_ours_runs_and_is_scored() -> None:
    case = _tiny_dense()
    # spawn: this test process may already run torch's thread pools, which a fork inherits
    # in an unusable state.
    ours = run_method(case, OURS, timeout=120.0, start_method="spawn")
    oracle = run_method(case, ORACLE, timeout=120.0, start_method="spawn")
    for r in (ours, oracle):
        assert r.status == "ok", r.note
        assert r.errors is not None and len(r.errors) == case.num_nodes
        assert 0.0 <= r.median_deg <= r.p95_deg and np.isfinite(r.mean_deg)
    assert oracle.median_deg < 3.0  # 2 deg noise, true edges only
    line = summarize([ours, oracle])
    assert "ours/oracle median ratio over 1 generated cases" in line


def test_summary_counts() -> None:
    def row(method: str, mean: float, med: float) -> Result:
        return Result("c", "sfm", 3, 3, method, "ok", mean, med, med, 0.1)

    text = summarize([row(OURS, 3.0, 1.0), row("gtsam_chordal", 1.0, 0.96)])
    assert "within 10% (or 0.05°) of the best peer's median on 1/1" in text
    assert "best peer's mean on 1/1" in text


def test_summary_compares_with_the_better_gnc_variant() -> None:
    def row(case: str, method: str, med: float, wall: float, false: int = 5) -> Result:
        return Result(case, "chain", 9, 9, method, "ok", med, med, med, wall,
                      false_edges=false)

    text = summarize([
        row("a", OURS, 1.0, 1.0), row("a", "gtsam_gnc_tls", 2.0, 2.0),
        row("a", "gtsam_gnc_tls+odo", 0.9, 8.0),  # the better variant: lower median
        row("b", OURS, 1.0, 1.0), row("b", "gtsam_gnc_tls", 1.5, 4.0),
        row("c", OURS, 1.0, 1.0, false=0), row("c", "gtsam_gnc_tls", 9.0, 9.0),  # clean
    ])
    assert ("median lower than the better variant's on 1/2, equal (within 0.5%) on 0/2, "
            "higher on 1/2; time at most a quarter of its time on 2/2") in text
    assert "| a | 1.000 | gtsam_gnc_tls+odo: 0.900 | 1.00 | 8.00 | 0.12 |" in text


def test_stress_summary_counts_each_target_and_names_each_miss(tmp_path: Path) -> None:
    from benchmarks.regime_stress import read_results, stress_summary, write_results

    def row(case: str, method: str, mean: float, med: float, status: str = "ok") -> Result:
        return Result(case, "chain", 9, 9, method, status, mean, med, med, 0.1)

    results = [
        row("good", OURS, 1.0, 1.0), row("good", ORACLE, 1.0, 0.9),
        row("good", "gtsam_chordal", 1.2, 1.1),
        row("far", OURS, 9.0, 2.0), row("far", ORACLE, 1.0, 1.0),
        row("far", "gtsam_gnc_tls", 3.0, 1.9),  # median within 10%, mean 3x
        row("miss", OURS, 2.0, 2.0), row("miss", "gtsam_shonan_huber", 2.0, 1.5),
        row("no peer", OURS, 1.0, 1.0), row("no peer", ORACLE, 1.0, 1.0),
        row("failed", OURS, float("nan"), float("nan"), "error"),
        row("failed", "gtsam_chordal", 1.0, 1.0),
    ]
    path = tmp_path / "run.json"
    write_results(str(path), results)
    lines = stress_summary(read_results(str(path)))
    assert lines[0] == ("Summary (ours): median within 10% (or 0.05 deg) of the best peer's "
                        "on 2 / 3 variants; mean above 1.5x the best peer's on 1 / 3; median "
                        "within 1.5x of the oracle's on 2 / 3")
    assert sorted(lines[1:]) == sorted([
        "  beyond 1.5x the oracle: far: 2.000 against 1.000 median",
        "  OK MEAN>1.5x: far: ours 9.000 / 2.000, best peer mean 3.000, median 1.900",
        "  MISS: miss: ours 2.000 / 2.000, best peer mean 2.000, median 1.500",
    ])


def test_gnc_peer_with_known_inliers_runs() -> None:
    from benchmarks import peers
    from benchmarks.regimes import GNC_ODO, methods_for

    case = _tiny_chain()
    avail = peers.available_peers()
    methods = dict(methods_for(case, avail))
    assert GNC_ODO in methods and ORACLE in methods
    if not avail.get("gtsam_gnc_tls"):
        pytest.skip("gtsam not installed")
    r = run_method(case, GNC_ODO, timeout=120.0, start_method="spawn")
    assert r.status == "ok", r.note
    assert f"{case.num_nodes - 1} known inliers" in r.note
    assert r.errors is not None and len(r.errors) == case.num_nodes


def test_default_profile_places_every_node_of_a_dense_graph_with_half_outliers() -> None:
    """Half the edges random: the verification's relocalization leaves no node far off, and
    the error is the oracle's (our solve on the true edges)."""
    from rotavg_ros.core.metrics import evaluate
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.solver import average_rotations

    case = rc.dense_case("sfm/dense100/out50", 100, 50, outliers=0.5)
    assert case.inlier is not None
    w = np.ones(case.num_edges)

    def node_errors(rot: np.ndarray) -> np.ndarray:
        return evaluate(dict(enumerate(rot)), dict(enumerate(case.gt))).errors

    default = average_rotations(case.num_nodes, case.i, case.j, case.R, w,
                                SolverOptions.for_profile("default"))
    t = case.inlier
    oracle = average_rotations(case.num_nodes, case.i[t], case.j[t], case.R[t], w[t],
                               SolverOptions.for_profile("default"))
    ours, best = node_errors(default.rotations), node_errors(oracle.rotations)
    assert ours.max() < 5.0
    assert ours.mean() < 1.25 * best.mean()


def default_and_oracle_errors(case: rc.RegimeCase) -> tuple[ArraySolution, np.ndarray,
                                                              np.ndarray]:
    """``(solution, ours, oracle)``: the default profile's solution and per-node errors (deg)
    on ``case``, and the per-node errors of the same solve on its true edges only."""
    from rotavg_ros.core.metrics import evaluate
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.solver import average_rotations

    assert case.inlier is not None
    w = np.ones(case.num_edges)
    t = case.inlier
    default = average_rotations(case.num_nodes, case.i, case.j, case.R, w,
                                SolverOptions.for_profile("default"))
    oracle = average_rotations(case.num_nodes, case.i[t], case.j[t], case.R[t], w[t],
                               SolverOptions.for_profile("default"))
    ours = evaluate(dict(enumerate(default.rotations)), dict(enumerate(case.gt))).errors
    best = evaluate(dict(enumerate(oracle.rotations)), dict(enumerate(case.gt))).errors
    return default, ours, best


@pytest.mark.parametrize("seed", [1, 2])
def test_default_profile_places_the_nodes_of_a_sparse_random_graph_with_false_edges(
        seed: int) -> None:
    """Mean degree 10, 30% of the edges random (the suite's sfm/sparse200/out30 drawn with
    seeds 1 and 2): nodes left on a false edge move back (the relocalization's far moves
    that explain more edges). Seed 2: nine nodes stayed up to 170 deg off before those moves.
    Seed 1: two nodes with 2-3 true edges of 5-7 stayed 140-164 deg off (2.09 deg mean;
    three and 2.97 deg with a chordal start beside the filter's tree) until far moves were
    judged by truncated squares and the mean of agreeing predictions was a hypothesis."""
    case = rc.dense_case("sfm/sparse200/out30", 200, 10, outliers=0.3, seed=seed)
    _, ours, best = default_and_oracle_errors(case)
    assert ours.max() < 5.0
    assert ours.mean() < 1.25 * best.mean()


def test_default_profile_rejects_groups_of_consistent_false_closures_on_a_chain() -> None:
    """A 2,000-keyframe chain, 60 true loop closures and 40 false ones in mutually consistent
    groups of 4-8 (regime_stress's chain/2000/grouped40, seed 0). Before the pairwise
    closure test's starts, the re-solve kept 17 false closures, bent the odometry, and
    ended at 9.25 deg mean against the oracle's 4.13."""
    case = rc.chain_case("stress/chain/2000/grouped40", 2000, closures=60,
                         false_grouped=0.40, seed=0)
    assert case.inlier is not None
    default, ours, best = default_and_oracle_errors(case)
    assert np.count_nonzero(default.kept & ~case.inlier) <= 2
    assert ours.mean() < 1.1 * best.mean()


def test_default_profile_reads_the_pairwise_tests_scale_from_the_loops() -> None:
    """A 1,000-keyframe chain, 36 true loop closures and 24 random false ones (the regime
    benchmark's chain/1000/rand40 at draw 14, folded noise). The false closures bent step
    3's fit until it cut odometry: its noise scale read 10.5 deg per axis (the odometry's is
    0.87), and the pairwise test, run at that scale and at a half and a quarter of it, kept
    9 false closures at best. Every false closure stayed in, 14 true ones went out: 22.8
    deg mean against the oracle's 3.4. The closures' own loops over the odometry read 0.88
    deg (closure_consistency.loop_noise_scale), and the test at that scale keeps exactly
    the true ones."""
    case = rc.chain_case("chain/1000/rand40", 1000, closures=36, false_random=0.40, seed=14)
    assert case.inlier is not None
    default, ours, best = default_and_oracle_errors(case)
    assert np.array_equal(default.kept, case.inlier)
    assert ours.mean() < 1.05 * best.mean()


@pytest.mark.parametrize("name, kind, seed, model", [
    ("short/100/rand2", "false_random", 102, "tangent"),
    ("short/50/grouped7", "false_grouped", 107, "folded"),
    ("short/50/grouped7", "false_grouped", 113, "tangent"),
    ("short/50/grouped7", "false_grouped", 162, "folded"),
])
def test_default_profile_rejects_false_closures_that_bend_a_short_chain(
        name: str, kind: str, seed: int, model: str) -> None:
    """The issue's new-user graphs: short chains with 8 true loop closures and a few false
    ones. 100 keyframes and 2 random false closures (seed 102): they bent the first
    re-solve's fit until every residual was inside, its noise scale read 7.1 deg per axis
    (the odometry's is about 1.4), no outlier, so the tight pass with the pairwise closure
    test did not run: 9.9 deg mean against the oracle's 2.2. 50 keyframes and a group of 7
    consistent false closures (seed 107): step 3 found three outliers but read 8.2 deg,
    above which the tight pass did not run either: four of the group kept, 20.7 deg mean
    against the oracle's 1.8. The same at seed 113: step 3 left out four of the group, the
    three kept lifted the inliers' redundancy to 0.18, above the chain bound 0.15, and the
    tight GNC's starts agreed, so the pairwise test did not run: 15.0 deg mean against the
    oracle's 2.0. It now runs wherever the closures are few. The same at seed 162: step 3
    left out none (the group lifted the redundancy of every edge to 0.23), so the tight pass
    did not run at all: 11.1 deg mean against the oracle's 1.8. It now runs wherever the
    closures are few, whatever step 3 found."""
    share: dict[str, Any] = {kind: 2 / 10 if kind == "false_random" else 7 / 15}
    case = rc.chain_case(name, int(name.split("/")[1]), closures=8, seed=seed,
                         noise_model=model, **share)
    assert case.inlier is not None
    default, ours, best = default_and_oracle_errors(case)
    assert np.array_equal(default.kept, case.inlier)
    assert ours.mean() < 1.05 * best.mean()


def test_chain_generator_says_when_its_closures_cannot_be_placed() -> None:
    """Too many closures for the placement rules on a short chain: a clear error, not a loop
    that never ends (a 50-keyframe chain with a group of 7 false closures at this draw)."""
    with pytest.raises(ValueError, match="could not place"):
        rc.chain_case("short/50/grouped7", 50, closures=8, false_grouped=7 / 15, seed=103)
    with pytest.raises(ValueError, match="could not place"):
        rc.chain_case("crowded", 30, closures=200)


def test_default_profile_leaves_out_runs_of_false_closures_the_pairwise_test_keeps(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A 500-keyframe chain at 3 deg per edge, 30 true loop closures and 20 false ones in
    consistent runs (seed 1). At this noise the odometry between a run and the true closures
    excuses it in the pairwise test: before the runs were judged as wholes, the re-solve kept
    a run of 5 false closures and ended at 7.01 deg mean against the oracle's 5.06. (The
    tight pass at a consistent fit's noise scale now rejects those runs first: the runs test
    is checked with that pass off, and the default must end at the oracle too.)"""
    case = rc.chain_case("sweep/chain/500/grouped40-noise3", 500, closures=30,
                         false_grouped=0.40, odo_noise_deg=3.0, loop_noise_deg=3.0, seed=1)
    assert case.inlier is not None
    default, ours, best = default_and_oracle_errors(case)
    assert np.count_nonzero(default.kept & ~case.inlier) == 0
    assert ours.mean() < 1.05 * best.mean()
    from rotavg_ros.core.robust import verify

    monkeypatch.setattr(verify, "RESCALE_BELOW", 0.0)
    default, ours, best = default_and_oracle_errors(case)
    assert np.count_nonzero(default.kept & ~case.inlier) == 0
    assert default.runs_left_out >= 1
    assert ours.mean() < 1.05 * best.mean()
    # The graph interface reports it (the node's diagnostics: closure_runs_left_out).
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.solver import RotationAverager

    said: list[str] = []
    result = RotationAverager(SolverOptions.for_profile(
        "default", progress=said.append)).solve(case.view_graph())
    assert result.num_runs_left_out == default.runs_left_out
    assert any(f"{default.runs_left_out} runs of loop closures left out" in line
               for line in said)


def test_default_profile_judges_closures_at_the_scale_of_a_consistent_fit() -> None:
    """A planar robot (headings only) on the suite's chain/1000/rand40 edges, drawn with
    seed 4: 36 true loop closures and 24 false ones off by 10-180 deg in heading, which the
    odometry's drift can partly explain. False closures bent step 3's fit and its noise
    scale (3.4 deg per axis against about 1), and at that scale the bent fit had the lowest
    truncated squares: 18.9 deg mean, 17.5 deg median against the oracle's 3.4 / 2.7.
    A pairwise-consistent start fits its own edges at a clearly lower scale, and the tight
    pass runs again there."""
    base = rc.chain_case("chain/1000/rand40", 1000, closures=36, false_random=0.40, seed=4)
    case = rc.planar_case("planar-test", base, odo_noise_deg=1.5, loop_noise_deg=2.0, seed=4,
                          min_false_deg=10.0)
    assert case.inlier is not None
    default, ours, best = default_and_oracle_errors(case)
    assert np.median(ours) < 1.1 * np.median(best)
    assert ours.mean() < 1.1 * best.mean()


def test_default_profile_keeps_a_chain_with_dropped_odometry_in_one_piece() -> None:
    """1,000 keyframes, 3% of the odometry dropped (28 pieces that short closures across
    each gap and 40 random true closures join), 29 random false closures (seed 1). The
    truncated L1 cost rewards a fit that cuts the closures joining the pieces: each piece
    then fits its own odometry exactly. Compared by their truncated squares (the GNC's own
    objective) the re-solve's candidates keep the pieces joined: before, 33.5 deg mean
    against the oracle's 3.8 (a block of pieces turned)."""
    case = rc.pieces_case("stress/chain/1000/gaps3-rand25", 1000, dropped_odometry=0.03,
                          closures=40, false_random=0.25, seed=1)
    assert case.inlier is not None
    default, ours, best = default_and_oracle_errors(case)
    assert np.count_nonzero(default.kept & ~case.inlier) == 0
    assert np.count_nonzero(~default.kept & case.inlier) <= 1
    assert ours.mean() < 1.05 * best.mean()


def test_default_profile_takes_least_squares_on_a_route_of_low_redundancy_cold_and_warm() -> None:
    """A route of 400 keyframes driven three times, its 121 true closures in 12 runs, no
    false ones (the stress variant, seed 2): 1,320 edges on 1,200 nodes, redundancy 0.09.
    The re-solve's residuals of folded noise do not look Gaussian, and the DMF fitted on
    its inliers stood on its L1 cost at 5.18 deg median against least squares' 4.44 (GTSAM
    chordal: 4.41). Below ``least_squares_below_redundancy`` the re-solve is the answer,
    cold and warm."""
    from rotavg_ros.core.chordal_init import chordal_rotations
    from rotavg_ros.core.metrics import evaluate
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.robust.gauss_newton import refine_least_squares
    from rotavg_ros.core.solver import average_rotations

    case = rc.revisit_case("stress/revisit/3x400-clean", 400, 3, runs=12, seed=2)
    n, i, j, R, w = case.num_nodes, case.i, case.j, case.R, np.ones(case.num_edges)
    said: list[str] = []
    res = average_rotations(n, i, j, R, w, SolverOptions.for_profile("default",
                                                                     progress=said.append))
    least_squares = refine_least_squares(chordal_rotations(n, i, j, R, w), i, j, R, w)

    def median(rot: np.ndarray) -> float:
        return evaluate(dict(enumerate(rot)), dict(enumerate(case.gt))).median_deg

    assert any("no DMF fit: redundancy 0.09" in line for line in said)
    assert median(res.rotations) < 1.02 * median(least_squares)
    # The node's next solve starts warm from this one and fits the DMF first: its L1 cost
    # was 18% below the re-solve's, and it stood (5.17 deg). By their truncated squares the
    # re-solve stands, and no DMF refit replaces it.
    warm = average_rotations(n, i, j, R, w, SolverOptions.for_profile("default"),
                             initial=res.rotations)
    assert warm.verification == "robust"
    assert median(warm.rotations) < 1.02 * median(least_squares)


def test_default_profile_leaves_out_runs_of_false_closures_on_parking_garage(
        shared_dir: Path) -> None:
    """parking-garage at 3 deg per edge with 8 runs of consistent false closures (the stress
    variant, seed 4): two runs of 9 survived every other test and turned the graph 24 deg
    (23.6 deg mean against the oracle's 4.7)."""
    case = rc.slam_case("stress/parking-garage/noise3+grouped", shared_dir, "parking-garage",
                        noise_deg=3.0, groups=8, seed=4)
    assert case.inlier is not None
    default, ours, best = default_and_oracle_errors(case)
    assert np.count_nonzero(default.kept & ~case.inlier) == 0
    assert ours.mean() < 1.1 * best.mean()


def test_default_profile_reads_information_weights_on_a_front_ends_pose_graph(
        shared_dir: Path) -> None:
    """smallGrid3D with 10% false closures as a front end reports it (odometry at 0.5 deg,
    closures at 3 deg, weights 1 / sigma^2; the stress variant, seed 0): least squares on
    the true edges, with their weights, reaches 0.70 deg median; the L1 choice weighted
    residuals by ``w`` instead of ``sqrt(w)`` and gave 1.24 deg (now 0.68)."""
    from rotavg_ros.core.metrics import evaluate
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.robust.gauss_newton import refine_least_squares
    from rotavg_ros.core.solver import average_rotations

    base = rc.slam_case("slam/smallGrid3D/rand10", shared_dir, "smallGrid3D",
                        random_false=0.10)
    case = rc.weighted_case("stress/weighted/smallGrid3D/rand10", base, odo_noise_deg=0.5,
                            loop_noise_deg=3.0)
    assert case.inlier is not None and case.weight is not None
    t, w = case.inlier, case.weight
    solved = average_rotations(case.num_nodes, case.i, case.j, case.R, w,
                               SolverOptions.for_profile("default"))
    ls = refine_least_squares(case.gt, case.i[t], case.j[t], case.R[t], w[t], iterations=30)
    truth = dict(enumerate(case.gt))
    ours = evaluate(dict(enumerate(solved.rotations)), truth).median_deg
    assert ours < 1.1 * evaluate(dict(enumerate(ls)), truth).median_deg


def test_default_profile_takes_hubers_fit_over_its_dmf_fit_under_heteroscedastic_noise(
        shared_dir: Path) -> None:
    """parking-garage clean, each true edge at its own noise level (3 deg x lognormal(0.7)),
    sent unweighted (the stress variant, seed 0). The cross-validation says Huber; the kept
    DMF fit, least squares in the bulk, stood until 86d0e26 at 5.58 deg median. Huber's fit
    of the inliers in its place: 3.48 deg (GNC-TLS 3.91; least squares on every edge, all
    true, from the truth 5.86)."""
    from rotavg_ros.core.metrics import evaluate
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.solver import average_rotations

    base = rc.slam_case("slam/parking-garage/noise1", shared_dir, "parking-garage")
    case = rc.heteroscedastic_case("stress/heteroscedastic/parking-garage/clean", base,
                                   sigma_deg=3.0)
    solved = average_rotations(case.num_nodes, case.i, case.j, case.R,
                               np.ones(case.num_edges), SolverOptions.for_profile("default"))
    assert solved.verification.endswith("+huber")
    median = evaluate(dict(enumerate(solved.rotations)), dict(enumerate(case.gt))).median_deg
    assert median < 4.0


def test_default_profile_starts_its_re_solve_from_the_relaxation_on_a_planar_graph(
        shared_dir: Path) -> None:
    """sphere2500's edges on a planar robot at 20 deg of heading noise, no false edge (the
    stress variant, seed 0). The chordal solution shows outliers (the heading noise's tail),
    so the robust re-solve runs first; from the odometry chain and the filter's tree alone
    its GNC ended in another least-squares basin: 45.7 deg mean against the least-squares
    optimum's 12.5 (from the relaxation, 15.9)."""
    from rotavg_ros.core.chordal_init import chordal_rotations
    from rotavg_ros.core.metrics import evaluate
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.robust.gauss_newton import refine_least_squares
    from rotavg_ros.core.solver import average_rotations

    base = rc.slam_case("slam/sphere2500/noise1", shared_dir, "sphere2500")
    case = rc.planar_case("stress/planar/sphere2500/noise20", base, odo_noise_deg=20.0,
                          loop_noise_deg=20.0)
    w = np.ones(case.num_edges)
    solved = average_rotations(case.num_nodes, case.i, case.j, case.R, w,
                               SolverOptions.for_profile("default"))
    start = chordal_rotations(case.num_nodes, case.i, case.j, case.R, w)
    ls = refine_least_squares(start, case.i, case.j, case.R, w, iterations=30)
    truth = dict(enumerate(case.gt))
    ours = evaluate(dict(enumerate(solved.rotations)), truth).mean_deg
    assert ours < 1.5 * evaluate(dict(enumerate(ls)), truth).mean_deg


def test_default_profile_keeps_least_squares_where_the_filter_cut_gaussian_inliers(
        shared_dir: Path) -> None:
    """parking-garage's edges at 5 deg of Gaussian noise three times larger about one axis
    (the record's clean noise5 case, ``anisotropic``): the filter removes 1,215 true edges,
    the re-solve's whitened residuals look Gaussian and it wins the choice; the cold,
    filtered DMF refit on its inliers then won the L1 cost at 12.66 / 11.84 deg mean /
    median. Least squares stands: the least-squares optimum's accuracy."""
    from rotavg_ros.core.metrics import evaluate
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.robust.gauss_newton import refine_least_squares
    from rotavg_ros.core.solver import average_rotations

    case = rc.slam_case("slam/parking-garage/noise5", shared_dir, "parking-garage",
                        noise_deg=5.0, noise_model="anisotropic")
    w = np.ones(case.num_edges)
    solved = average_rotations(case.num_nodes, case.i, case.j, case.R, w,
                               SolverOptions.for_profile("default"))
    ls = refine_least_squares(case.gt, case.i, case.j, case.R, w, iterations=30)
    truth = dict(enumerate(case.gt))
    ours = evaluate(dict(enumerate(solved.rotations)), truth)
    best = evaluate(dict(enumerate(ls)), truth)
    assert ours.median_deg < 1.05 * best.median_deg
    assert ours.mean_deg < 1.05 * best.mean_deg


def test_default_profile_refits_a_dmf_solution_of_part_of_its_inliers_on_all_of_them(
        shared_dir: Path) -> None:
    """Clean parking-garage at 5 deg of folded noise, held-out draw 16: the filter removes
    1,032 true edges, the DMF on the rest is kept, and the verification re-admits 1,027. Its
    refit on every inlier (6.90 deg median) was rejected for a truncated L1 cost 2.4%
    above the fit of the part (9.10 deg): two fits of different edges, not a failed refit.
    The refit stands: within 1.1x of least squares from the truth (GNC-TLS's 6.82)."""
    from rotavg_ros.core.metrics import evaluate
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.robust.gauss_newton import refine_least_squares
    from rotavg_ros.core.solver import average_rotations

    case = rc.slam_case("slam/parking-garage/noise5", shared_dir, "parking-garage",
                        noise_deg=5.0, seed=16)
    w = np.ones(case.num_edges)
    solved = average_rotations(case.num_nodes, case.i, case.j, case.R, w,
                               SolverOptions.for_profile("default"))
    ls = refine_least_squares(case.gt, case.i, case.j, case.R, w, iterations=30)
    truth = dict(enumerate(case.gt))
    ours = evaluate(dict(enumerate(solved.rotations)), truth).median_deg
    assert ours < 1.1 * evaluate(dict(enumerate(ls)), truth).median_deg


def test_choice_prefers_least_squares_where_the_residuals_look_gaussian() -> None:
    # A dense graph, 10% outliers, 2 deg noise. Gaussian tangent noise: the re-solve's
    # residuals look Gaussian, so its least-squares solution is kept (without that test the
    # DMF's L1 fit stood on its L1 cost at 0.48 deg median). The same with Gaussian noise
    # three times larger about one axis: its angles alone look peaked, its whitened residual
    # vectors Gaussian (by the angles the DMF stood: 0.372 deg median). Folded-normal angles
    # peak at zero: the DMF's L1 fit stands, and is the more accurate.
    from rotavg_ros.core.metrics import evaluate
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.solver import RotationAverager

    medians = {}
    for model in ("tangent", "anisotropic", "folded"):
        case = rc.dense_case("test/shape100", 100, 50, outliers=0.1, noise_deg=2.0,
                             noise_model=model)
        res = RotationAverager(SolverOptions.for_profile("default")).solve(case.view_graph())
        medians[model] = evaluate(dict(zip(res.node_ids, res.rotations, strict=True)),
                                  dict(enumerate(case.gt))).median_deg
        assert res.verification == ("dmf" if model == "folded" else "robust"), model
    assert medians["tangent"] < 0.35
    assert medians["anisotropic"] < 0.3
    assert medians["folded"] < 0.15


def test_a_dense_fit_on_few_of_its_inliers_is_fitted_again_on_them() -> None:
    # The seed-3 draw of sfm/dense100/out50: the filter removes most of the true edges and
    # the verification re-admits them, so most of the kept DMF solution's inliers were not
    # in its fit. With ``refit_readmitted`` a short warm fit on them replaces it, at the
    # oracle's accuracy. (Without it, on the 2-core machine, the DMF on the filter's edges
    # placed part of the graph wrong and the kept solution had 0.29 deg median against the
    # oracle's 0.19; with other thread counts that fit can land well, so only the refit's
    # own result is asserted.)
    from rotavg_ros.core.metrics import evaluate
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.solver import RotationAverager

    case = rc.dense_case("sfm/dense100/out50", 100, 50, outliers=0.5, seed=3)

    def solve(refit: bool, keep: np.ndarray | None = None) -> tuple[float, list[str]]:
        g = case.view_graph(keep)
        said: list[str] = []
        res = RotationAverager(SolverOptions.for_profile(
            "default", refit_readmitted=refit, progress=said.append)).solve(g)
        rot = {k: res.rotations[g.index_of(k)] for k in range(case.num_nodes)}
        return evaluate(rot, dict(enumerate(case.gt))).median_deg, said

    oracle, _ = solve(True, case.inlier)
    median, said = solve(True)
    assert any("DMF refit" in line and "replaces the solution" in line for line in said)
    assert median < 1.1 * oracle
    _, said = solve(False)
    assert not any("DMF refit" in line for line in said)


def test_a_dense_fit_on_two_thirds_of_its_inliers_is_fitted_again_on_them() -> None:
    """150 nodes, mean degree 20, 5 deg folded noise, no false edge (seed 0). The filter
    keeps 1,117 of the 1,647 edges; the DMF on them stands, and the verification calls every
    edge an inlier: 32% of them were not in the fit, under the third that set off the refit
    before (0.71 deg median). Above ``DENSE_UNFITTED_SHARE`` (a quarter) the refit runs."""
    from rotavg_ros.core.metrics import evaluate
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.solver import RotationAverager

    case = rc.dense_case("test/dense-clean", 150, 20, outliers=0.0, noise_deg=5.0, seed=0)

    def solve(refit: bool) -> tuple[float, list[str]]:
        said: list[str] = []
        res = RotationAverager(SolverOptions.for_profile(
            "default", refit_readmitted=refit, progress=said.append)).solve(case.view_graph())
        rot = dict(zip(res.node_ids, res.rotations, strict=True))
        return evaluate(rot, dict(enumerate(case.gt))).median_deg, said

    median, said = solve(True)
    assert any("dense mode: 150 nodes, 1117 edges" in line for line in said)
    assert any("DMF refit on 1647 inliers replaces the solution" in line for line in said)
    without, said = solve(False)
    assert not any("DMF refit" in line for line in said)
    assert median < 0.85 * without  # measured 0.479 against 0.707 deg


def test_a_dense_graph_whose_re_solve_stands_is_fitted_again_from_it() -> None:
    """100 nodes, mean degree 20, 5 deg folded noise, no false edge (seed 3). The filter's
    fixed threshold removes 39% of the true edges and the least-squares re-solve of all of
    them beats the DMF on the rest. A DMF refit filtered from its own start lost to it again
    (the answer was least squares', 1.00 / 1.01 deg mean / median). Where the re-solve's
    residuals do not look Gaussian the refit starts from the re-solve on its inliers,
    unfiltered, in dense mode as in sparse mode (0.54 / 0.45 deg)."""
    from rotavg_ros.core.chordal_init import chordal_rotations
    from rotavg_ros.core.metrics import evaluate
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.robust.gauss_newton import refine_least_squares
    from rotavg_ros.core.solver import RotationAverager

    case = rc.dense_case("test/dense-clean", 100, 20, outliers=0.0, noise_deg=5.0, seed=3)
    said: list[str] = []
    res = RotationAverager(SolverOptions.for_profile("default", progress=said.append)).solve(
        case.view_graph())
    n, i, j, R, w = case.num_nodes, case.i, case.j, case.R, np.ones(case.num_edges)
    least_squares = refine_least_squares(chordal_rotations(n, i, j, R, w), i, j, R, w)

    def errors(rot: np.ndarray) -> np.ndarray:
        return evaluate(dict(enumerate(rot)), dict(enumerate(case.gt))).errors

    ours = errors(np.stack([res.rotations[k] for k in range(n)]))
    assert any("dense mode" in line for line in said)
    assert any("DMF refit on 1082 inliers replaces the solution" in line for line in said)
    assert res.verification == "dmf_refit"
    assert np.median(ours) < 0.75 * np.median(errors(least_squares))
    assert ours.mean() < 0.75 * errors(least_squares).mean()


def test_a_sparse_fit_that_missed_many_of_its_inliers_is_fitted_again_on_them(
        shared_dir: Path) -> None:
    # The seed-2 draw of parking-garage at 5 deg per edge (clean): the filter removes 1,080
    # true edges (17%), and the DMF on the other 5,195 stands against the least-squares
    # re-solve of all 6,275 within the choice's margin, at 9.3 / 7.8 deg mean / median
    # against least squares' 7.6 / 6.0. The verification re-admits every removed edge, more
    # than ``READMITTED_SHARE`` of the fit's, and the refit on them replaces it. (The
    # cross-validation off: it says Huber here, and Huber's fit of the inliers replaces
    # either fit; the default ends there, 5.47 deg.)
    from rotavg_ros.core.metrics import evaluate
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.solver import RotationAverager

    case = rc.all_cases(2)["slam/parking-garage/noise5"](shared_dir)

    def solve(refit: bool) -> tuple[float, list[str]]:
        g = case.view_graph()
        said: list[str] = []
        res = RotationAverager(SolverOptions.for_profile(
            "default", refit_readmitted=refit, l1_by_cross_validation=False,
            progress=said.append)).solve(g)
        rot = {k: res.rotations[g.index_of(k)] for k in range(case.num_nodes)}
        return evaluate(rot, dict(enumerate(case.gt))).median_deg, said

    median, said = solve(True)
    assert any("DMF refit on 6275 inliers replaces the solution" in line for line in said)
    assert median < 6.2
    without, said = solve(False)
    assert not any("DMF refit" in line for line in said)
    assert without > 1.2 * median


def test_default_profile_leaves_the_central_anchors_local_minimum_on_a_planar_torus(
        shared_dir: Path) -> None:
    """torus3D's edges on a planar robot at 17 deg of heading noise, no false edge (the
    stress variant, folded seed 20). The relaxation anchored at the central node read
    57.9 deg median and least squares from it ended in a local minimum: ours 60.0 deg
    against GNC-TLS's 9.7. Anchored also a quarter and three quarters along the same path,
    the lowest chordal cost picks the three-quarter point, and least squares reaches the
    optimum (9.5 deg)."""
    from rotavg_ros.core.metrics import evaluate
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.solver import average_rotations

    base = rc.slam_case("slam/torus3D/noise1", shared_dir, "torus3D", seed=20)
    case = rc.planar_case("stress/planar/torus3D/noise17", base, odo_noise_deg=17.0,
                          loop_noise_deg=17.0, seed=20)
    solved = average_rotations(case.num_nodes, case.i, case.j, case.R,
                               np.ones(case.num_edges), SolverOptions.for_profile("default"))
    median = evaluate(dict(enumerate(solved.rotations)), dict(enumerate(case.gt))).median_deg
    assert median < 12.0


def test_short_chains_tell_a_wrong_step_only_where_two_ways_of_true_closures_join_its_pieces(
) -> None:
    """``short_chains``' tellability: the edge-disjoint ways of true closures between the two
    odometry pieces a wrong step separates. Closures that cross both of two wrong steps
    leave the block between them unreached (0 ways), however many cross; two closures
    from different places to one piece are two ways, one closure is one."""
    from benchmarks.short_chains import _true_joins

    n = 40
    steps = [(k, k + 1) for k in range(n - 1)]

    def chain(closures: list[tuple[int, int]], wrong: list[int]) -> rc.RegimeCase:
        edges = np.array(steps + closures, np.int64)
        i, j = edges[:, 0], edges[:, 1]
        inlier = np.ones(i.size, bool)
        inlier[wrong] = False  # step k joins k, k + 1
        gt = np.repeat(np.eye(3)[None], n, axis=0)
        return rc.RegimeCase("t", "chain", n, i, j, rc.relative(gt, i, j), gt, inlier=inlier)

    around = [(2, 30), (3, 31), (4, 35), (1, 38)]  # each crosses steps 10 and 15
    assert _true_joins(chain(around, [10, 15])) == 0
    assert _true_joins(chain(around + [(12, 20)], [10, 15])) == 1
    assert _true_joins(chain(around + [(12, 20), (13, 25)], [10, 15])) == 2
    assert _true_joins(chain(around, [10])) == 4
    assert _true_joins(chain([(5, 30)], [20])) == 1
    assert _true_joins(chain([(5, 30), (12, 35)], [20])) == 2
