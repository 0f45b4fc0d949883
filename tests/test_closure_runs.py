"""Runs of loop closures and the test that leaves a whole run out (closure_runs)."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks import regime_cases as rc
from rotavg_ros.core.robust import closure_runs as closure_runs_module
from rotavg_ros.core.robust.closure_runs import (
    REMEMBERED_RUN_LEVERAGES,
    closure_runs,
    remembered_run_leverages,
    run_pull,
    suspect_runs,
)
from rotavg_ros.core.robust.gauss_newton import refine_least_squares
from rotavg_ros.core.so3 import exp_map


def test_runs_join_closures_between_the_same_two_stretches() -> None:
    # Forward run 10-50 .. 13-53 (with one keyframe skipped), a backward run 80-20 .. 82-18,
    # a lone closure, and two odometry edges (not closures).
    i = np.array([10, 11, 13, 80, 81, 82, 60, 0, 1])
    j = np.array([50, 51, 53, 20, 19, 18, 5, 1, 2])
    closures = np.array([True] * 7 + [False] * 2)
    runs = sorted(sorted(r.tolist()) for r in closure_runs(i, j, closures))
    assert runs == [[0, 1, 2], [3, 4, 5]]
    assert closure_runs(i, j, np.zeros(9, bool)) == []


def chain_with_runs(false_deg: float, true_runs: int, seed: int = 5,
                    ) -> tuple[rc.RegimeCase, np.ndarray]:
    """A 400-keyframe chain with 16 lone true closures, ``true_runs`` true runs of 4 and a
    run of 6 closures that all carry the same wrong world rotation of ``false_deg`` (the
    generator's grouped false closures); Gaussian tangent noise of 1 deg (per-axis
    ``1 / sqrt(3)`` deg). Returns the case and the false run's mask."""
    rng = np.random.default_rng(seed)
    n = 400
    gt = rc.chain_trajectory(n, rng)
    starts = rng.choice(np.arange(0, 160, 8), size=true_runs, replace=False)
    closures_i = np.concatenate([rng.integers(0, 150, 16), *(s + np.arange(4) for s in starts)])
    closures_j = np.concatenate([closures_i[:16] + rng.integers(100, 240, 16),
                                 *(s + 190 + np.arange(4) for s in starts)])
    run_i, run_j = np.arange(300, 306), np.arange(40, 46)
    i = np.concatenate([np.arange(n - 1), closures_i, run_i])
    j = np.concatenate([np.arange(1, n), closures_j, run_j])
    R = rc.relative(gt, i, j)
    W = exp_map(np.radians(false_deg) * np.array([[0.0, 0.6, 0.8]]))[0]
    false = np.zeros(i.size, bool)
    false[-6:] = True
    R[false] = gt[run_i] @ W @ np.swapaxes(gt[run_j], 1, 2)
    R = rc.perturb(R, 1.0, np.random.default_rng(seed + 1), "tangent")
    return rc.RegimeCase("test/runs", "chain", n, i, j, R, gt, inlier=~false), false


SIGMA = np.radians(1.0) / np.sqrt(3.0)  # chain_with_runs' noise per axis


def test_the_pull_of_true_runs_follows_its_chi_square() -> None:
    # Under the noise alone a run's T_S / sigma^2 is chi-square with 3 degrees of freedom:
    # mean 3. Pooled over the true runs of several draws, the false run left out.
    values = []
    for seed in range(6):
        case, false = chain_with_runs(40.0, true_runs=12, seed=seed)
        w = (~false).astype(float)
        fit = refine_least_squares(case.gt, case.i, case.j, case.R, w, iterations=20)
        runs = closure_runs(case.i, case.j, ~case.odometry & ~false)
        values.append(run_pull(fit, case.i, case.j, case.R, w, runs) / SIGMA ** 2)
    pooled = np.concatenate(values)
    assert pooled.size >= 60
    assert 2.4 < pooled.mean() < 3.6


def test_a_run_that_bent_the_fit_is_the_most_suspect_and_the_rest_is_not() -> None:
    # The bent fit strains the true runs too (they pull against it), but the false run
    # pulls hardest; once it is out, no run is suspect.
    case, false = chain_with_runs(40.0, true_runs=12)
    w = np.ones(case.num_edges)
    everything = np.ones(case.num_edges, bool)
    fit = refine_least_squares(case.gt, case.i, case.j, case.R, w, iterations=20)
    closures = ~case.odometry
    suspects = suspect_runs(fit, case.i, case.j, case.R, w, everything, closures, SIGMA)
    assert sorted(suspects[0].tolist()) == np.flatnonzero(false).tolist()
    # Without it the rest is consistent: nothing is suspect.
    rest = refine_least_squares(fit, case.i, case.j, case.R, w * ~false, iterations=20)
    assert suspect_runs(rest, case.i, case.j, case.R, w, ~false, closures, SIGMA) == []


def test_remembered_leverages_follow_the_fit_exactly_with_few_solves(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Within ``remembered_run_leverages`` the runs' leverages of a fit that differs from the
    last by a few edges come from the Woodbury update, not from a solve per run: the same
    ``T_S`` as without (to rounding), and only new runs solved for directly."""
    case, false = chain_with_runs(40.0, true_runs=12)
    closures = ~case.odometry
    solved: list[int] = []
    direct = closure_runs_module._leverages

    def counting(laplacian, row, i, j, w, runs):  # type: ignore[no-untyped-def]
        solved.append(len(runs))
        return direct(laplacian, row, i, j, w, runs)

    monkeypatch.setattr(closure_runs_module, "_leverages", counting)
    fits = [~false, ~false, ~false & (np.arange(case.num_edges) != 405),  # one lone closure out
            ~false & ~np.isin(np.arange(case.num_edges), [405, 420]),  # a run loses one
            ~false,  # that run whole again
            np.ones(case.num_edges, bool)]  # the false run in: a new run
    expected, got = [], []
    for fit in fits:
        w = fit.astype(float)
        rot = refine_least_squares(case.gt, case.i, case.j, case.R, w, iterations=5)
        runs = closure_runs(case.i, case.j, closures & fit)
        expected.append(run_pull(rot, case.i, case.j, case.R, w, runs))
    solved.clear()
    with remembered_run_leverages():
        for fit in fits:
            w = fit.astype(float)
            rot = refine_least_squares(case.gt, case.i, case.j, case.R, w, iterations=5)
            runs = closure_runs(case.i, case.j, closures & fit)
            got.append(run_pull(rot, case.i, case.j, case.R, w, runs))
    for e, g in zip(expected, got, strict=True):
        assert np.allclose(e, g, rtol=1e-9, atol=0.0, equal_nan=True)
    counts = [closure_runs(case.i, case.j, closures & fit) for fit in fits]
    # All runs solved at first; then none (the same fit, one lone closure out), the run
    # that lost a closure (a new run), that run whole again, and the false run.
    assert solved == [len(counts[0]), 1, 1, 1]
    assert REMEMBERED_RUN_LEVERAGES.get() is None
