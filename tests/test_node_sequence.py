"""The node sequence (node_sequence): which nodes are consecutive, so which edges are
odometry, whatever order the input names the nodes in."""

from __future__ import annotations

from collections.abc import Callable, Hashable, Mapping

import numpy as np

from benchmarks import regime_cases as rc
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.node_sequence import chained, natural_key, node_sequence, path_order
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.result import SolveResult
from rotavg_ros.core.solver import RotationAverager
from rotavg_ros.core.view_graph import ViewGraph


def _natural(ids: list[Hashable]) -> list[Hashable]:
    return sorted(ids, key=lambda k: natural_key(k) or ())


def test_natural_order_reads_digits_as_numbers() -> None:
    names: list[Hashable] = ["kf_10", "kf_9", "b_2", "a_10", "a_9"]
    assert _natural(names) == ["a_9", "a_10", "b_2", "kf_9", "kf_10"]
    assert _natural([12, 3, 100]) == [3, 12, 100]
    assert natural_key(np.int64(7)) == natural_key(7)
    assert natural_key(True) is None and natural_key((1, 2)) is None
    # Digit runs compare by value with no conversion: no limit on their length.
    assert _natural(["a" + "1" * 5000, "a9", "a010", 7]) == [7, "a9", "a010", "a" + "1" * 5000]


def test_the_order_that_chains_more_nodes_wins() -> None:
    # A chain 0-1-2-3-4 whose edges, sorted by (i, j) with a closure (0, 3), name 3 early.
    ids = [0, 1, 3, 2, 4]  # the order first named: edges (0,1), (0,3), (1,2), (2,3), (3,4)
    index = {k: n for n, k in enumerate(ids)}
    pairs = [(0, 1), (0, 3), (1, 2), (2, 3), (3, 4)]
    i = np.array([index[a] for a, _ in pairs])
    j = np.array([index[b] for _, b in pairs])
    seq = node_sequence(ids, i, j)
    assert [ids[k] for k in np.argsort(seq)] == [0, 1, 2, 3, 4]
    assert chained(seq, i, j) == 4
    # Labels that carry no order: the order first named stands (it chains more).
    labels = [40, 7, 93, 11, 58]
    assert node_sequence(labels, np.arange(4), np.arange(1, 5)).tolist() == [0, 1, 2, 3, 4]
    # Ids that are neither integers nor text: the order first named.
    assert node_sequence([(0,), (2,), (1,)], np.array([0]), np.array([2])).tolist() == [
        0, 1, 2]


def test_the_paths_of_a_chain_are_its_odometry() -> None:
    """A chain 0..11 with closures (2, 9) and (3, 7): 2 and 3 both close loops, so the
    step between them is a bridge between two paths; node 7 is the chain's one-closure
    keyframe. Relabelled so that no id order tells the chain, the paths still do."""
    chain = [(k, k + 1) for k in range(11)]
    pairs = chain + [(2, 9), (3, 7)]
    label = np.array([7, 0, 11, 4, 9, 2, 5, 10, 1, 8, 3, 6])  # node k is named label[k]
    i = label[[a for a, _ in pairs]]
    j = label[[b for _, b in pairs]]
    order = path_order(12, i, j)
    walked = np.argsort(label)[order]  # ... back in chain terms (dense index = name here)
    assert walked.tolist() in (list(range(12)), list(range(11, -1, -1)))
    seq = node_sequence(list(range(12)), i, j)  # (the labels in order chain few steps)
    assert chained(seq, i, j) == 11


def _chain_case() -> rc.RegimeCase:
    return rc.chain_case("chain/300/rand40", 300, closures=12, false_random=0.40, seed=0)


Name = Callable[[int], Hashable]


def _graph(case: rc.RegimeCase, name: Name, order: np.ndarray) -> ViewGraph:
    g = ViewGraph()
    g.add_edges([name(int(k)) for k in case.i[order]], [name(int(k)) for k in case.j[order]],
                case.R[order])
    return g


def _median_error(case: rc.RegimeCase, g: ViewGraph, name: Name) -> tuple[float, int]:
    res = RotationAverager(SolverOptions()).solve(g)
    return _median(res, {name(k): case.gt[k] for k in range(case.num_nodes)}), \
        res.num_trusted_odometry


def _median(res: SolveResult, truth: Mapping[Hashable, np.ndarray]) -> float:
    return evaluate(dict(zip(res.node_ids, res.rotations, strict=True)), truth).median_deg


def test_an_edge_list_sorted_by_id_keeps_its_odometry() -> None:
    """A chain with 40% false closures, sent as edges only and sorted by ``(i, j)``: each
    closure names its far end early, so the order first named breaks two steps per closure
    and no longer chains 90% of the nodes. The ids' order (integers, and names such as
    ``kf_12`` with their digits read as numbers) still finds every step, and the solve is
    the one of the graph whose nodes came in order. (Before the sequence: no odometry
    trusted, 6.23 deg median error against 2.98.)"""
    case = _chain_case()
    in_order = _median_error(case, _graph(case, int, np.arange(case.num_edges)), int)
    assert in_order[1] == case.num_nodes - 1
    by_id = np.lexsort((np.maximum(case.i, case.j), np.minimum(case.i, case.j)))
    names: list[Name] = [int, lambda k: 5 * k + 100, lambda k: f"kf_{k}"]
    for name in names:
        median, trusted = _median_error(case, _graph(case, name, by_id), name)
        assert trusted == case.num_nodes - 1
        assert abs(median - in_order[0]) < 1e-6


def test_ids_without_an_order_keep_the_odometry_of_the_paths() -> None:
    """The same chain with its nodes relabelled at random: no id order tells the odometry,
    but the paths do (all but a few steps between keyframes that both close loops), and
    the solve is the one in order. (Before the paths: no odometry trusted, 24.2 deg
    median against 2.98.)"""
    case = _chain_case()
    in_order = _median_error(case, _graph(case, int, np.arange(case.num_edges)), int)
    rng = np.random.default_rng(5)
    label = rng.permutation(case.num_nodes)

    def relabel(k: int) -> Hashable:
        return int(label[k])

    shuffled = rng.permutation(case.num_edges)  # (nor does the order first named)
    median, trusted = _median_error(case, _graph(case, relabel, shuffled), relabel)
    assert trusted >= 0.97 * (case.num_nodes - 1)
    assert abs(median - in_order[0]) < 1e-6


def test_an_anchor_inside_the_chain_breaks_no_step() -> None:
    """The anchor is turned to identity after the solve, not moved to the front of the
    sequence (which broke the two steps beside it)."""
    case = _chain_case()
    g = _graph(case, int, np.arange(case.num_edges))
    res = RotationAverager(SolverOptions()).solve(g, anchor=150)
    assert res.anchors[0] == 150
    assert np.allclose(res.rotations[g.index_of(150)], np.eye(3), atol=0)
    assert res.num_trusted_odometry == case.num_nodes - 1
    default = RotationAverager(SolverOptions()).solve(g)
    truth: dict[Hashable, np.ndarray] = {k: case.gt[k] for k in range(case.num_nodes)}
    assert abs(_median(res, truth) - _median(default, truth)) < 1e-6
