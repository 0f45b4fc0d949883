"""The depth candidates' race: who is stopped, determinism, and that the choice holds."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import pytest

from rotavg_ros.core import depth_choice
from rotavg_ros.core.dmf import CandidateRace, DMFFit, FitSpec, fit_symmetric
from rotavg_ros.core.options import PROFILES, DenseFitOptions, SolverOptions
from rotavg_ros.core.result import SolveResult
from rotavg_ros.core.so3 import random_rotations, rotation_about_axis
from rotavg_ros.core.solver import RotationAverager
from rotavg_ros.core.view_graph import ViewGraph

pytestmark = pytest.mark.usefixtures("single_torch_thread")


# ------------------------------------------------------------------ the race alone
def test_a_candidate_clearly_behind_the_pace_setter_is_stopped() -> None:
    race = CandidateRace(pacer=2, ratio=0.3)
    assert not race.report(2, 400, 10.0)  # the pace-setter is never stopped
    assert not race.report(2, 500, 100.0)
    assert not race.report(4, 400, 12.9)  # within 30%
    assert race.report(6, 400, 13.1)  # 31% above depth 2
    assert race.stopped == {6: 400}


def test_an_ended_pace_setter_counts_with_its_final_cost() -> None:
    race = CandidateRace(pacer=2, ratio=0.3)
    race.report(2, 400, 10.0)
    race.finish(4, 1.0)  # only the pace-setter's end matters
    race.finish(2, 20.0)  # converged before 500: its final cost stands in
    assert not race.report(6, 400, 12.0)
    assert not race.report(6, 500, 25.9)
    assert race.report(6, 600, 26.1)
    assert race.stopped == {6: 600}


def test_a_failed_or_non_finite_pace_setter_stops_nobody() -> None:
    race = CandidateRace(pacer=2, ratio=0.3)
    race.report(2, 400, float("nan"))
    race.finish(2, None)
    assert not race.report(4, 400, 50.0)
    assert not race.report(4, 500, 1e9)
    assert race.stopped == {}


def test_a_candidate_waits_for_the_pace_setter_whatever_the_thread_timing() -> None:
    race = CandidateRace(pacer=2, ratio=0.3)
    verdict: list[bool] = []
    late = threading.Thread(target=lambda: verdict.append(race.report(4, 400, 14.0)))
    late.start()  # depth 4 reaches the checkpoint first ...
    late.join(timeout=0.2)
    assert late.is_alive() and not verdict  # ... and waits for depth 2's report
    race.report(2, 400, 10.0)
    late.join(timeout=5)
    assert verdict == [True]


# ------------------------------------------------------------------- in the fit
def test_a_monitor_returning_true_stops_the_fit() -> None:
    rng = np.random.default_rng(0)
    R = random_rotations(8, rng)
    i, j = np.triu_indices(8, 1)
    Rij = np.einsum("eab,ecb->eac", R[i], R[j])
    s = DenseFitOptions(iterations=300, tolerance=0.0)
    spec = FitSpec(depth=4, hidden_width=24, seed=0, device="cpu", cuda_graph=False)
    fit = fit_symmetric(8, i, j, Rij, np.ones(i.size), s, spec,
                        monitor=lambda step, H: step >= 100)
    assert fit.stopped and fit.iterations == 100
    assert not fit_symmetric(8, i, j, Rij, np.ones(i.size), s, spec).stopped


# --------------------------------------------------------------------- in the solve
def _graph(n: int, seed: int) -> ViewGraph:
    """A dense random graph, 2 deg noise, 10% random edges."""
    rng = np.random.default_rng(seed)
    R = random_rotations(n, rng)
    g = ViewGraph()
    for k in range(n):
        g.add_node(k)
    for a in range(n):
        for b in range(a + 1, n):
            if rng.random() < 0.6:
                Rij = (random_rotations(1, rng)[0] if rng.random() < 0.1 else
                       rotation_about_axis(rng.normal(size=3), np.radians(2.0) * rng.normal())
                       @ R[a] @ R[b].T)
                g.add_edge(a, b, Rij)
    return g


def _solve(g: ViewGraph, **flat: Any) -> SolveResult:
    # Short fits: the race from iteration 100; from a near-zero start depth 8 is far
    # behind there (the regime benchmark's long fits are far behind at 400).
    options = SolverOptions.for_profile("paper", depths=(2, 4, 6, 8), iterations=300,
                                        prune_after=100, prune_every=50, **flat)
    return RotationAverager(options).solve(g)


# Seeds where depth 8 is far behind at the checkpoint (cost 3.9x and 1.9x depth 2's against
# the ratio's 1.3x): from a near-zero start its progress by then varies with the CPU's
# rounding (seed 1: 1.22x on an AVX-512 machine, stopped on others).
@pytest.mark.parametrize("seed", [0, 5])
def test_the_race_stops_a_loser_and_changes_nothing_else(seed: int) -> None:
    g = _graph(24, seed)
    full = _solve(g, prune_ratio=None, threads=2)
    raced = _solve(g, prune_ratio=0.3, threads=2)
    assert full.pruned_depths == () and raced.pruned_depths == (8,)
    assert raced.iterations_by_depth[8] == 100 < full.iterations_by_depth[8]
    assert raced.depth == full.depth != 8
    assert raced.rotations.tobytes() == full.rotations.tobytes()
    assert set(raced.cost_by_depth) == {2, 4, 6, 8}
    for d in (2, 4, 6):
        assert raced.cost_by_depth[d] == full.cost_by_depth[d]
        assert raced.iterations_by_depth[d] == full.iterations_by_depth[d]


def test_the_race_decides_the_same_with_any_number_of_threads() -> None:
    g = _graph(24, 2)
    runs = [_solve(g, prune_ratio=0.3, threads=t) for t in (1, 2, 4, 2)]
    for r in runs[1:]:
        assert r.pruned_depths == runs[0].pruned_depths
        assert r.iterations_by_depth == runs[0].iterations_by_depth
        assert r.cost_by_depth == runs[0].cost_by_depth
        assert r.rotations.tobytes() == runs[0].rotations.tobytes()


def test_a_failing_candidate_leaves_no_other_waiting(monkeypatch: pytest.MonkeyPatch) -> None:
    real = depth_choice.fit_symmetric

    def failing(*args: Any, **kw: Any) -> DMFFit:
        if args[6].depth == 4:  # the FitSpec
            raise FloatingPointError("diverged")
        return real(*args, **kw)

    monkeypatch.setattr(depth_choice, "fit_symmetric", failing)
    g = _graph(24, 4)
    raised: list[BaseException] = []

    def solve() -> None:
        try:
            _solve(g, prune_ratio=0.3, threads=2)
        except FloatingPointError as exc:
            raised.append(exc)

    worker = threading.Thread(target=solve, daemon=True)
    worker.start()
    worker.join(timeout=120)
    assert not worker.is_alive() and len(raised) == 1


def test_a_stopped_candidate_is_never_chosen(monkeypatch: pytest.MonkeyPatch) -> None:
    """Even when its (unfinished) cost is the lowest."""
    g = _graph(12, 3)
    e = g.edge_arrays()
    truth = np.stack([np.eye(3)] * g.num_nodes)  # every edge below is identity

    def fake_fits(options: SolverOptions, n: int, *args: Any, **kw: Any) -> dict[int, DMFFit]:
        rng = np.random.default_rng(0)
        noisy = np.einsum("nab,nbc->nac", truth[:n], random_rotations(n, rng))
        return {2: DMFFit(noisy, np.ones(1), 0.0, 300),
                4: DMFFit(truth[:n].copy(), np.ones(1), 0.0, 100, stopped=True)}

    monkeypatch.setattr(depth_choice, "fit_depths", fake_fits)
    edges = (e.i, e.j, np.tile(np.eye(3), (e.num_edges, 1, 1)), np.ones(e.num_edges))
    sol = RotationAverager(SolverOptions.for_profile("paper")).solve_component(
        g.num_nodes, *edges)
    assert sol.cost_by_depth[4] < sol.cost_by_depth[2]
    assert sol.depth == 2 and sol.pruned_depths == (4,)


def test_the_paper_profile_runs_every_candidate_to_the_end() -> None:
    assert PROFILES["paper"]["prune_ratio"] is None
    assert SolverOptions.for_profile("paper").dense.prune_ratio is None
    assert SolverOptions().dense.prune_ratio is not None


def test_the_default_profile_fits_the_shallowest_and_the_deepest_candidate_only() -> None:
    """``bracket_depths``: of (2, 4, 6, 8) the default profile fits 2 and 8, each exactly as
    when every candidate runs (its own seed), and chooses between them; ``paper`` fits all."""
    g = _graph(24, 3)
    flat: dict[str, Any] = dict(depths=(2, 4, 6, 8), iterations=200, prune_ratio=None,
                                threads=1, verify=False)
    bracket = RotationAverager(SolverOptions.for_profile("default", **flat)).solve(g)
    every = RotationAverager(SolverOptions.for_profile(
        "default", bracket_depths=False, **flat)).solve(g)
    assert set(bracket.iterations_by_depth) == set(bracket.cost_by_depth) == {2, 8}
    assert set(every.cost_by_depth) == {2, 4, 6, 8}
    for d in (2, 8):
        assert bracket.cost_by_depth[d] == every.cost_by_depth[d]
    assert bracket.depth == min((2, 8), key=lambda d: every.cost_by_depth[d])
    assert SolverOptions().dense.bracket_depths
    assert not SolverOptions.for_profile("paper").dense.bracket_depths
    previous = dict(zip(bracket.node_ids, bracket.rotations, strict=True))
    warm = RotationAverager(SolverOptions.for_profile("default", **flat)).solve(
        g, initial=previous, initial_depth=bracket.depth)
    assert set(warm.cost_by_depth) == {bracket.depth}  # a warm start fits its depth only


def test_profiles_choose_the_hidden_width_and_the_loss_form() -> None:
    """``paper``: the full width 3N up to 300 nodes and the gathered loss; ``default``:
    min(3N, 64) at every size and the whole-matrix loss on small dense graphs."""
    paper, default = (SolverOptions.for_profile(p).dense for p in ("paper", "default"))
    assert [paper.width_for(n) for n in (10, 227, 300, 301, 5000)] == [30, 681, 900, 64, 64]
    assert [default.width_for(n) for n in (10, 21, 22, 227, 5000)] == [30, 63, 64, 64, 64]
    assert SolverOptions.from_flat(hidden_width=96).dense.width_for(227) == 96
    assert paper.dense_product_density is None
    assert default.dense_product_density is not None
    assert paper.reweight_floor is None  # the paper's cumulative reweighting
    assert default.reweight_floor is not None


@pytest.mark.parametrize(("field", "value"), [
    ("prune_ratio", 0.0), ("prune_ratio", float("nan")), ("prune_every", 30),
    ("prune_every", 0), ("prune_after", 410), ("prune_after", -100),
    ("dense_product_density", 1.5), ("dense_product_density", -0.1),
    ("dense_product_max_nodes", -1), ("reweight_floor", 0.0), ("reweight_floor", 1.5),
    ("reweight_floor", float("inf")),
])
def test_invalid_race_and_dense_product_options_are_refused_by_name(field: str, value: Any) -> None:
    with pytest.raises(ValueError, match=f"invalid solver option: {field} "):
        SolverOptions.from_flat(**{field: value}).validate()
