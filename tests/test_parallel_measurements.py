"""Parallel measurements of one node pair that disagree (``core.robust.parallel_measurements``,
option ``settle_parallel``): a false twin of a true edge set aside, true twins merged as
before, a pair the solution cannot judge counted and warned about."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rotavg_ros.msg_adapters.outputs import Level

from benchmarks import regime_cases as rc
from rotavg_ros.app.accumulator import AccumulatorStats
from rotavg_ros.app.diagnostics import diagnostic_values
from rotavg_ros.app.parameters import settings_from_parameters
from rotavg_ros.app.session import SolveBookkeeping
from rotavg_ros.cli import main
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.result import SolveResult, parallel_warning
from rotavg_ros.core.so3 import matrix_to_quat
from rotavg_ros.core.solver import RotationAverager
from rotavg_ros.core.types import FloatArray, IntArray
from rotavg_ros.core.view_graph import ViewGraph


def _solve(case: rc.RegimeCase, i: IntArray, j: IntArray, R: FloatArray,
           settle: bool = True) -> tuple[SolveResult, float]:
    g = ViewGraph()
    for k in range(case.num_nodes):
        g.add_node(k)
    g.add_edges(i.tolist(), j.tolist(), R)
    res = RotationAverager(SolverOptions.for_profile("default", seed=0,
                                                     settle_parallel=settle)).solve(g)
    return res, evaluate(dict(enumerate(res.rotations)), dict(enumerate(case.gt))).median_deg


def _lattice_with_twins(true_twins: bool) -> tuple[rc.RegimeCase, IntArray, IntArray,
                                                   FloatArray, int]:
    """A clean 5^3 lattice pose graph; a third of its loop closures sent a second time,
    as a false rotation (or a true one with fresh noise), after every first measurement."""
    case = rc.lattice_case("test/lattice/twins", 5, noise_deg=1.0, seed=3)
    rng = np.random.default_rng(5)
    loops = np.flatnonzero(np.abs(case.i - case.j) != 1)
    pick = rng.choice(loops, loops.size // 3, replace=False)
    truth = rc.relative(np.asarray(case.gt), case.i[pick], case.j[pick])
    twins = (rc.perturb(truth, 1.0, rng) if true_twins else rc.false_rotations(truth, rng))
    return (case, np.r_[case.i, case.i[pick]], np.r_[case.j, case.j[pick]],
            np.concatenate([case.R, twins]), pick.size)


def test_a_false_twin_of_a_loop_closure_is_set_aside() -> None:
    # Merged, each false twin drags its pair's edge halfway to a random rotation: the
    # verification rejects it, and the true measurement goes with it. Settled, each pair's
    # edge is its true measurement again: the solve as if the twins had never come.
    case, i, j, R, twins = _lattice_with_twins(true_twins=False)
    _, alone = _solve(case, case.i, case.j, case.R)
    merged, merged_median = _solve(case, i, j, R, settle=False)
    settled, settled_median = _solve(case, i, j, R)
    assert merged.num_parallel_set_aside == 0 and merged_median > 1.05 * alone
    assert settled.num_parallel_set_aside == twins and settled.num_parallel_undecided == 0
    assert abs(settled_median - alone) <= 0.01 * alone


def test_true_twins_are_merged_as_before() -> None:
    case, i, j, R, _ = _lattice_with_twins(true_twins=True)
    merged, merged_median = _solve(case, i, j, R, settle=False)
    settled, settled_median = _solve(case, i, j, R)
    assert settled.num_parallel_set_aside == 0 and settled.num_parallel_undecided == 0
    assert settled_median == merged_median
    np.testing.assert_array_equal(settled.rotations, merged.rotations)


def test_wrong_twins_of_odometry_steps_are_withheld_then_set_aside() -> None:
    # Six trusted odometry steps of a clean 5^3 lattice also sent 60 deg off. Merged, each
    # step bends the solution onto itself (28 deg median), so against the first solve
    # neither of a pair's measurements agrees: the pairs are withheld, the graph solved
    # without them, and there the right one of each agrees and the wrong one is set aside.
    case = rc.lattice_case("test/lattice/step", 5, noise_deg=1.0, seed=1)
    rng = np.random.default_rng(1)
    steps = rng.choice(np.flatnonzero(np.abs(case.i - case.j) == 1), 6, replace=False)
    wrong = case.R[steps] @ rc.rotation_about_axis(rc.random_axes(6, rng),
                                                   np.radians(np.full(6, 60.0)))
    i, j = np.r_[case.i, case.i[steps]], np.r_[case.j, case.j[steps]]
    R = np.concatenate([case.R, wrong])
    _, alone = _solve(case, case.i, case.j, case.R)
    _, merged_median = _solve(case, i, j, R, settle=False)
    settled, settled_median = _solve(case, i, j, R)
    assert merged_median > 10.0 * alone
    assert settled.num_parallel_set_aside == 6 and settled.num_parallel_undecided == 0
    assert abs(settled_median - alone) <= 0.01 * alone


def _tail_hung_by_a_step_sent_two_ways() -> rc.RegimeCase:
    """A tail of 20 keyframes that hangs by one odometry step, sent twice, 60 deg apart:
    every rotation of the step fits it exactly, so no solution can tell the two apart."""
    case = rc.lattice_case("test/lattice/tail", 4, noise_deg=1.0, seed=1)
    n0 = case.num_nodes
    rng = np.random.default_rng(2)
    tail = rc.chain_trajectory(20, rng)
    gt = np.concatenate([np.asarray(case.gt), tail @ np.asarray(case.gt)[-1]])
    ti, tj = np.arange(n0 - 1, n0 + 19), np.arange(n0, n0 + 20)
    tR = rc.perturb(rc.relative(gt, ti, tj), 1.0, rng)
    wrong = tR[:1] @ rc.rotation_about_axis(np.array([[1.0, 0.0, 0.0]]), np.radians([60.0]))
    i, j = np.r_[case.i, ti, ti[:1]], np.r_[case.j, tj, tj[:1]]
    R = np.concatenate([case.R, tR, wrong])
    return rc.RegimeCase("test/lattice/tail", "slam", n0 + 20, i, j, R, gt, None, None, 1.0,
                         "", 1.0)


def test_a_bridge_measured_two_ways_is_undecided_and_warns() -> None:
    case = _tail_hung_by_a_step_sent_two_ways()
    res, _ = _solve(case, case.i, case.j, case.R)
    assert res.num_parallel_undecided == 1 and res.num_parallel_set_aside == 0
    stats = AccumulatorStats(received=case.num_edges, accepted=case.num_edges, rejected={},
                             notes={}, num_nodes=case.num_nodes,
                             num_measurements=case.num_edges, version=1, generation=0)
    level, message, values = diagnostic_values(stats, SolveBookkeeping(last_result=res),
                                               settings_from_parameters({}))
    assert values["parallel_pairs_undecided"] == 1
    assert level == Level.WARN and "could not settle" in message
    assert parallel_warning(res) is not None


def test_the_command_line_warns_of_an_undecided_pair(tmp_path: Path, capsys) -> None:
    case = _tail_hung_by_a_step_sent_two_ways()
    src = tmp_path / "tail.g2o"
    src.write_text("".join(
        f"EDGE_SE3:QUAT {a} {b} 0 0 0 " + " ".join(repr(float(v)) for v in matrix_to_quat(Rk))
        + "\n" for a, b, Rk in zip(case.i.tolist(), case.j.tolist(), case.R, strict=True)))
    assert main(["solve", str(src), "-o", str(tmp_path / "out.g2o")]) == 0
    assert "1 node pair(s) measured with rotations that disagree" in capsys.readouterr().err


def test_the_check_is_a_node_parameter_and_a_flag(tmp_path: Path, capsys) -> None:
    assert settings_from_parameters({}).solver.verify.settle_parallel
    off = settings_from_parameters({"settle_parallel": False}).solver
    assert not off.verify.settle_parallel
    case = _tail_hung_by_a_step_sent_two_ways()
    src = tmp_path / "tail.g2o"
    src.write_text("".join(
        f"EDGE_SE3:QUAT {a} {b} 0 0 0 " + " ".join(repr(float(v)) for v in matrix_to_quat(Rk))
        + "\n" for a, b, Rk in zip(case.i.tolist(), case.j.tolist(), case.R, strict=True)))
    assert main(["solve", str(src), "-o", str(tmp_path / "out.g2o"),
                 "--no-settle-parallel"]) == 0
    assert "measured with rotations that disagree" not in capsys.readouterr().err
