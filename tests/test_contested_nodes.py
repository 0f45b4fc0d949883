"""Nodes whose rotation rests on one measurement that others contradict
(``core.robust.contested_nodes``): found on small graphs by hand, reported by the solver,
the node's diagnostics and the command line, and silent where every node is checked."""

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
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.result import SolveResult, contested_warning
from rotavg_ros.core.robust.contested_nodes import contested_nodes
from rotavg_ros.core.so3 import matrix_to_quat
from rotavg_ros.core.solver import RotationAverager
from rotavg_ros.core.types import FloatArray, IntArray
from rotavg_ros.core.view_graph import ViewGraph

# A square 0-1-2-3 with its diagonal, and a tail 3-4-5-6.
SQUARE_I = np.array([0, 1, 2, 3, 0])
SQUARE_J = np.array([1, 2, 3, 0, 2])
TAIL_I = np.array([3, 4, 5])
TAIL_J = np.array([4, 5, 6])


def _contested(extra_i: list[int], extra_j: list[int], kept_extra: list[bool],
               trusted_tail: bool = False) -> list[int]:
    i = np.r_[SQUARE_I, TAIL_I, extra_i].astype(np.int64)
    j = np.r_[SQUARE_J, TAIL_J, extra_j].astype(np.int64)
    kept = np.r_[np.ones(SQUARE_I.size + TAIL_I.size, bool), np.asarray(kept_extra, bool)]
    trusted = np.zeros(i.size, bool)
    if trusted_tail:
        trusted[SQUARE_I.size:SQUARE_I.size + TAIL_I.size] = True
    return np.flatnonzero(contested_nodes(7, i, j, kept, trusted)).tolist()


def test_a_block_held_by_one_edge_that_a_left_out_edge_contradicts() -> None:
    assert _contested([], [], []) == []  # a tail nothing else measures: nothing contradicts
    # An edge left out from the square to node 5: the bridges 3-4 and 4-5 hold nodes 4-6
    # (resp. 5-6) against it; 5-6 holds node 6 alone, which that edge does not reach.
    assert _contested([1], [5], [False]) == [4, 5, 6]
    # Another measurement of the pair 5-6, left out: node 6 hangs by 5-6 against it.
    assert _contested([6], [5], [False]) == [6]
    # Kept 4-6 closes the cycle 4-5-6: a left-out 4-5 stays inside 3-4's block.
    assert _contested([4, 4], [6, 5], [True, False]) == []
    # Kept, the same edge makes a cycle: no bridge left to contest but 5-6.
    assert _contested([1], [5], [True]) == []
    assert _contested([1, 6], [5, 2], [True, False]) == [6]
    # Kept odometry is trusted: the tail is no contest.
    assert _contested([1], [5], [False], trusted_tail=True) == []


def test_the_smaller_side_of_a_contested_bridge_is_marked() -> None:
    # Node 0 hangs by 0-1 from a square 1-2-3-4 with its diagonal; a left-out 0-3 contests
    # that bridge: node 0 is marked, not the four nodes on the far side from it.
    i = np.array([0, 1, 2, 3, 4, 1, 0])
    j = np.array([1, 2, 3, 4, 1, 3, 3])
    kept = np.r_[np.ones(6, bool), False]
    marked = contested_nodes(5, i, j, kept, np.zeros(7, bool))
    assert np.flatnonzero(marked).tolist() == [0]


def test_nodes_no_kept_edge_reaches_are_contested() -> None:
    i = np.r_[SQUARE_I, TAIL_I].astype(np.int64)
    j = np.r_[SQUARE_J, TAIL_J].astype(np.int64)
    kept = np.ones(i.size, bool)
    kept[-2:] = False  # 4-5 and 5-6 left out: nodes 5 and 6 hang by nothing kept
    assert np.flatnonzero(contested_nodes(7, i, j, kept, np.zeros(i.size, bool))).tolist() == [
        4, 5, 6]  # and 4, held by 3-4 against the left-out 4-5


def _view_graph_with_a_node_measured_four_ways(
        false_edges: int) -> tuple[rc.RegimeCase, IntArray, IntArray, FloatArray]:
    """A clean random view graph (60 cameras, mean degree 10, 1 deg noise) and camera 60,
    measured by one true edge and ``false_edges`` false ones, each a random rotation to
    another camera: they contradict the true one and each other."""
    case = rc.dense_case("test/dense/contested", 60, 10, outliers=0.0, noise_deg=1.0, seed=4)
    rng = np.random.default_rng(7)
    gt = np.concatenate([np.asarray(case.gt), rc.random_rotations(1, rng)])
    others = rng.choice(60, 1 + false_edges, replace=False)
    ends_i, ends_j = others, np.full(others.size, 60)
    truth = rc.relative(gt, ends_i, ends_j)
    R = np.concatenate([rc.perturb(truth[:1], 1.0, rng),
                        rc.false_rotations(truth[1:], rng)])
    return (case, np.r_[case.i, ends_i], np.r_[case.j, ends_j],
            np.concatenate([case.R, R]))


def _solve(i: IntArray, j: IntArray, R: FloatArray) -> SolveResult:
    g = ViewGraph()
    g.add_edges(i.tolist(), j.tolist(), R)
    return RotationAverager(SolverOptions.for_profile("default", seed=0)).solve(g)


def test_the_solver_reports_a_camera_its_edges_cannot_place() -> None:
    case, i, j, R = _view_graph_with_a_node_measured_four_ways(false_edges=3)
    res = _solve(i, j, R)
    assert res.contested_ids() == [60] and res.num_contested_nodes == 1
    stats = AccumulatorStats(received=i.size, accepted=i.size, rejected={}, notes={},
                             num_nodes=61, num_measurements=i.size, version=1, generation=0)
    level, message, values = diagnostic_values(stats, SolveBookkeeping(last_result=res),
                                               settings_from_parameters({}))
    assert values["nodes_contested"] == 1 and values["nodes_contested_ids"] == "60"
    assert level == Level.WARN and "rest on one measurement" in message
    warning = contested_warning(res)
    assert warning is not None and warning.endswith(": 60")
    # Its true edge alone: nothing contradicts it, nothing is reported.
    clean = _solve(i[:-3], j[:-3], R[:-3])
    assert clean.num_contested_nodes == 0 and contested_warning(clean) is None
    level, message, values = diagnostic_values(stats, SolveBookkeeping(last_result=clean),
                                               settings_from_parameters({}))
    assert values["nodes_contested"] == 0 and "rest on one measurement" not in message


def test_the_command_line_names_the_contested_camera(tmp_path: Path, capsys) -> None:
    _, i, j, R = _view_graph_with_a_node_measured_four_ways(false_edges=3)
    src = tmp_path / "view_graph.g2o"
    src.write_text("".join(
        f"EDGE_SE3:QUAT {a} {b} 0 0 0 " + " ".join(repr(float(v)) for v in matrix_to_quat(Rk))
        + "\n" for a, b, Rk in zip(i.tolist(), j.tolist(), R, strict=True)))
    assert main(["solve", str(src), "-o", str(tmp_path / "out.g2o")]) == 0
    assert "1 node(s) rest on one measurement that others contradict" in capsys.readouterr().err
