"""ViewGraph: dense ids, edge orientation, repeat policies, validation, components."""

from __future__ import annotations

import numpy as np
import pytest

from rotavg_ros.core.so3 import geodesic_distance, random_rotations, rotation_about_axis
from rotavg_ros.core.view_graph import RepeatPolicy, ViewGraph


def _rot(seed: int) -> np.ndarray:
    return random_rotations(1, np.random.default_rng(seed))[0]


def test_string_ids_dense_first_appearance_order() -> None:
    g = ViewGraph()
    g.add_edge("map", "odom", np.eye(3))
    g.add_edge("base_link", "odom", np.eye(3))
    g.add_node("camera")
    g.add_node("map")  # idempotent
    assert g.node_ids == ["map", "odom", "base_link", "camera"]
    assert [g.index_of(k) for k in g.node_ids] == [0, 1, 2, 3]
    assert g.num_nodes == 4 and g.num_measurements == 2
    assert g.has_node("camera") and not g.has_node("lidar")
    with pytest.raises(KeyError):
        g.index_of("lidar")


def test_int_ids_dense_first_appearance_order() -> None:
    g = ViewGraph()
    g.add_edge(17, 3, np.eye(3))
    g.add_edge(3, 100, np.eye(3))
    g.add_edge(5, 17, np.eye(3))
    assert g.node_ids == [17, 3, 100, 5]
    assert g.index_of(17) == 0 and g.index_of(5) == 3
    e = g.edge_arrays()
    assert np.all(e.i < e.j)
    assert sorted(zip(e.i.tolist(), e.j.tolist(), strict=True)) == [(0, 1), (0, 3), (1, 2)]


def test_reversed_edge_stored_transposed() -> None:
    R = _rot(0)
    g = ViewGraph()
    g.add_node("a")
    g.add_node("b")
    g.add_edge("b", "a", R)  # R_ba: stored as (a, b, R_ba^T)
    e = g.edge_arrays()
    assert (e.i[0], e.j[0]) == (0, 1)
    np.testing.assert_allclose(e.R[0], R.T, atol=0)
    i, j, Rm, w = g.measurement_arrays()
    assert (i[0], j[0]) == (0, 1)
    np.testing.assert_allclose(Rm[0], R.T, atol=0)


def test_input_matrix_is_copied() -> None:
    R = _rot(1)
    g = ViewGraph()
    g.add_edge(0, 1, R)
    R[:] = 0.0
    stored = g.edge_arrays().R[0]
    assert np.all(np.isfinite(stored)) and abs(np.linalg.det(stored) - 1) < 1e-12


def test_merge_is_robust_to_one_gross_outlier() -> None:
    rng = np.random.default_rng(7)
    R = _rot(2)
    g = ViewGraph(RepeatPolicy.MERGE)
    weights = [1.0, 2.0, 1.5, 1.0]
    for k in range(3):
        noisy = rotation_about_axis(rng.normal(size=3), np.radians(0.5)) @ R
        g.add_edge(0, 1, noisy, weights[k])
    outlier = rotation_about_axis([1.0, 0.0, 0.0], np.radians(150.0)) @ R
    g.add_edge(1, 0, outlier.T, weights[3])  # reversed orientation, same pair
    e = g.edge_arrays()
    assert e.num_edges == 1
    assert e.multiplicity.tolist() == [4]
    assert np.degrees(geodesic_distance(e.R[0], R)) < 1.0
    assert e.weight[0] == pytest.approx(sum(weights))
    assert abs(np.linalg.det(e.R[0]) - 1.0) < 1e-12


def test_merge_single_measurement_unchanged() -> None:
    R = _rot(3)
    g = ViewGraph()
    g.add_edge(0, 1, R, 2.5)
    e = g.edge_arrays()
    np.testing.assert_allclose(e.R[0], R, atol=1e-12)
    assert e.weight[0] == 2.5 and e.multiplicity[0] == 1


@pytest.mark.parametrize(("policy", "expected_index"), [("latest", 2), ("first", 0)])
def test_latest_and_first_policies(policy: str, expected_index: int) -> None:
    Rs = [_rot(10 + k) for k in range(3)]
    ws = [1.0, 2.0, 3.0]
    g = ViewGraph(policy)
    assert g.repeat_policy is RepeatPolicy(policy)
    g.add_edge("x", "y", Rs[0], ws[0])
    g.add_edge("y", "x", Rs[1].T, ws[1])
    g.add_edge("x", "y", Rs[2], ws[2])
    g.add_edge("x", "z", Rs[0], 1.0)  # another pair in between
    e = g.edge_arrays()
    assert e.num_edges == 2
    k = int(np.flatnonzero((e.i == 0) & (e.j == 1))[0])
    np.testing.assert_allclose(e.R[k], Rs[expected_index], atol=1e-15)
    assert e.weight[k] == ws[expected_index]
    assert e.multiplicity[k] == 3


def test_edge_arrays_cache_invalidated_on_add() -> None:
    g = ViewGraph("latest")
    g.add_edge(0, 1, _rot(20))
    first = g.edge_arrays()
    R2 = _rot(21)
    g.add_edge(0, 1, R2)
    np.testing.assert_allclose(g.edge_arrays().R[0], R2, atol=0)
    assert first.multiplicity[0] == 1 and g.edge_arrays().multiplicity[0] == 2


@pytest.mark.parametrize(
    ("a", "b", "R", "w"),
    [
        ("n", "n", np.eye(3), 1.0),  # self-loop
        (0, 1, np.full((3, 3), np.nan), 1.0),  # NaN
        (0, 1, np.array([[1.0, 0, 0], [0, np.inf, 0], [0, 0, 1]]), 1.0),  # inf
        (0, 1, np.eye(2), 1.0),  # wrong shape
        (0, 1, np.eye(3), 0.0),  # zero weight
        (0, 1, np.eye(3), -1.0),  # negative weight
        (0, 1, np.eye(3), float("nan")),  # NaN weight
        (0, 1, np.eye(3), float("inf")),  # inf weight
    ],
)
def test_invalid_measurements_raise(a: object, b: object, R: np.ndarray, w: float) -> None:
    g = ViewGraph()
    with pytest.raises(ValueError):
        g.add_edge(a, b, R, w)
    assert g.num_measurements == 0


def test_add_edges_vectorised_and_length_check() -> None:
    Rs = random_rotations(3, np.random.default_rng(5))
    g = ViewGraph()
    g.add_edges([0, 1, 3], [1, 2, 2], Rs, np.array([1.0, 2.0, 3.0]))
    assert g.num_measurements == 3 and g.node_ids == [0, 1, 2, 3]
    e = g.edge_arrays()
    k = int(np.flatnonzero((e.i == 2) & (e.j == 3))[0])  # (3, 2) stored as (2, 3), transposed
    np.testing.assert_allclose(e.R[k], Rs[2].T, atol=0)
    with pytest.raises(ValueError):
        g.add_edges([0, 1], [1], Rs[:2])


def test_add_edges_matches_one_call_per_edge() -> None:
    """Node order, orientation, copies and the first invalid edge as one call each."""
    rng = np.random.default_rng(7)
    ids_i, ids_j = ["c", "a", "b", "d", "a"], ["a", "b", "c", "c", "d"]
    Rs, w = random_rotations(5, rng), rng.uniform(0.5, 2.0, 5)
    bulk, single = ViewGraph(), ViewGraph()
    bulk.add_edges(ids_i, ids_j, Rs, w)
    for a, b, Rk, wk in zip(ids_i, ids_j, Rs, w, strict=True):
        single.add_edge(a, b, Rk, float(wk))
    assert bulk.node_ids == single.node_ids == ["c", "a", "b", "d"]
    for x, y in zip(bulk.measurement_arrays(), single.measurement_arrays(), strict=True):
        np.testing.assert_array_equal(x, y)
    Rs[0] = 0.0  # the graph keeps its own copy
    assert np.all(bulk.measurement_arrays()[2][0] != 0.0)
    bad = ViewGraph()
    with pytest.raises(ValueError, match="self-loop"):
        bad.add_edges([0, 1, 2, 3], [1, 2, 2, 4], random_rotations(4, rng))
    assert bad.num_measurements == 2 and bad.node_ids == [0, 1, 2]


def test_components() -> None:
    g = ViewGraph()
    g.add_edge("a", "b", np.eye(3))
    g.add_edge("b", "c", np.eye(3))
    g.add_edge("d", "e", np.eye(3))
    g.add_node("lonely")
    count, labels = g.components()
    assert count == 3
    assert labels.shape == (6,)
    assert labels[0] == labels[1] == labels[2]
    assert labels[3] == labels[4]
    assert len({labels[0], labels[3], labels[5]}) == 3
    g.add_edge("c", "d", np.eye(3))
    count2, labels2 = g.components()
    assert count2 == 2 and len(set(labels2[:5].tolist())) == 1


def test_clear_keeps_policy() -> None:
    g = ViewGraph("first")
    g.add_edge(0, 1, np.eye(3))
    g.clear()
    assert g.num_nodes == 0 and g.num_measurements == 0
    assert g.repeat_policy is RepeatPolicy.FIRST
    assert g.edge_arrays().num_edges == 0
