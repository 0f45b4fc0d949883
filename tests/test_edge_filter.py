"""Triangle enumeration and the spanning-tree edge filter (Algorithm 1)."""

from __future__ import annotations

from itertools import combinations

import numpy as np
import pytest

from rotavg_ros.core.filter.edge_filter import (
    filter_edges,
    loop_errors,
    loop_statistics,
    tree_rotations,
)
from rotavg_ros.core.filter.triangles import enumerate_triangles
from rotavg_ros.core.so3 import chordal_distance, random_rotations, rotation_about_axis


def _random_edges(n: int, p: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    pairs = [(a, b) for a, b in combinations(range(n), 2) if rng.random() < p]
    rng.shuffle(pairs)  # input order must not matter
    e = np.asarray(pairs, dtype=np.int64)
    return e[:, 0], e[:, 1]


def _noisy_graph(
    n: int, p: float, noise_deg: float, outlier_frac: float, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Edges (i < j) with R_ij = R_i R_j^T perturbed, a fraction replaced by random rotations."""
    rng = np.random.default_rng(seed)
    R = random_rotations(n, rng)
    i, j = _random_edges(n, p, rng)
    Rij = np.einsum("eab,ecb->eac", R[i], R[j])
    noise = rotation_about_axis(rng.normal(size=(i.size, 3)),
                                np.radians(noise_deg) * rng.normal(size=i.size))
    Rij = noise @ Rij
    outlier = np.zeros(i.size, bool)
    outlier[rng.choice(i.size, int(round(outlier_frac * i.size)), replace=False)] = True
    Rij[outlier] = random_rotations(int(outlier.sum()), rng)
    return i, j, Rij, R, outlier


def _brute_force_triangles(i: np.ndarray, j: np.ndarray, n: int) -> set[tuple[int, int, int]]:
    adj = np.zeros((n, n), bool)
    adj[i, j] = adj[j, i] = True
    return {(a, b, c) for a, b, c in combinations(range(n), 3)
            if adj[a, b] and adj[b, c] and adj[a, c]}


@pytest.mark.parametrize("chunk_pairs", [4_000_000, 7])
def test_triangles_match_brute_force(chunk_pairs: int) -> None:
    rng = np.random.default_rng(0)
    n = 30
    i, j = _random_edges(n, 0.3, rng)
    tri = enumerate_triangles(i, j, n, chunk_pairs=chunk_pairs)
    nodes = tri.nodes(i, j)
    found = [tuple(t) for t in nodes.tolist()]
    assert len(found) == len(set(found))  # each triangle once
    assert set(found) == _brute_force_triangles(i, j, n)
    assert tri.count == len(found) > 0
    # The three edges close the triangle: ab, bc, ac.
    a, b, c = nodes.T
    assert np.all((a < b) & (b < c))
    np.testing.assert_array_equal(i[tri.e_bc], b)
    np.testing.assert_array_equal(j[tri.e_bc], c)
    np.testing.assert_array_equal(i[tri.e_ac], a)


def test_triangles_edge_cases() -> None:
    empty = np.zeros(0, np.int64)
    assert enumerate_triangles(empty, empty, 5).count == 0
    chain = np.arange(5)
    assert enumerate_triangles(chain[:-1], chain[1:], 5).count == 0
    with pytest.raises(ValueError):
        enumerate_triangles(np.array([2]), np.array([1]), 3)


def test_loop_statistics_sum_each_edges_loops_in_triangle_order() -> None:
    """Per edge: the loops it lies on, those below the median loop error, and the sum of
    their errors, added up over ab, then bc, then ac, in triangle order (bit for bit)."""
    n = 40
    i, j, Rij, _, _ = _noisy_graph(n, 0.5, 3.0, 0.2, seed=5)
    support, total, count, epsilon, ntri = loop_statistics(i, j, Rij, n)
    tri = enumerate_triangles(i, j, n)
    assert ntri == tri.count > 0
    loop = np.concatenate([tri.e_ab, tri.e_bc, tri.e_ac])
    nodes = np.tile(tri.nodes(i, j), (3, 1))
    a, b, c = nodes.T
    # Each loop's error, d_chord(R_ab, R_ac R_bc^T), whichever edge of it is credited.
    R = {(int(p), int(q)): r for p, q, r in zip(i, j, Rij, strict=True)}
    by_hand = np.array([np.linalg.norm(R[(p, q)] - R[(p, r)] @ R[(q, r)].T)
                        for p, q, r in zip(a.tolist(), b.tolist(), c.tolist(), strict=True)])
    delta = np.tile(loop_errors(Rij, tri.e_ab, tri.e_bc, tri.e_ac), 3)
    np.testing.assert_allclose(delta, by_hand, rtol=1e-12, atol=1e-15)
    assert epsilon == np.median(delta[:tri.count])
    expected_total = np.zeros(i.size)
    for e, d in zip(loop.tolist(), delta, strict=True):
        expected_total[e] += d
    np.testing.assert_array_equal(count, np.bincount(loop, minlength=i.size))
    np.testing.assert_array_equal(support,
                                  np.bincount(loop[delta < epsilon], minlength=i.size))
    np.testing.assert_array_equal(total, expected_total)  # the same additions, in order


def test_loop_statistics_zero_on_consistent_data() -> None:
    rng = np.random.default_rng(1)
    n = 12
    R = random_rotations(n, rng)
    i, j = _random_edges(n, 0.6, rng)
    Rij = np.einsum("eab,ecb->eac", R[i], R[j])
    support, total, count, epsilon, ntri = loop_statistics(i, j, Rij, n)
    assert ntri == len(_brute_force_triangles(i, j, n)) > 0
    assert epsilon < 1e-12
    assert np.all(total < 1e-10)
    assert count.sum() == 3 * ntri


def test_filter_removes_planted_outliers() -> None:
    n = 40
    i, j, Rij, _, outlier = _noisy_graph(n, 0.7, 1.0, 0.15, seed=3)
    res = filter_edges(i, j, Rij, np.ones(i.size), n, sigma=0.2)
    assert res.num_triangles > 0 and np.all(res.tested)
    removed = ~res.kept
    frac_outliers_removed = removed[outlier].mean()
    frac_inliers_kept = res.kept[~outlier].mean()
    assert frac_outliers_removed >= 0.9, frac_outliers_removed
    assert frac_inliers_kept >= 0.9, frac_inliers_kept
    # Spanning tree: N - 1 edges, all kept, mostly inliers.
    assert res.in_tree.sum() == n - 1
    assert np.all(res.kept[res.in_tree])
    assert outlier[res.in_tree].sum() == 0
    assert res.tree_rotations.shape == (n, 3, 3)
    assert res.num_removed == int(removed.sum())


def test_filter_without_support_count_still_runs() -> None:
    n = 40
    i, j, Rij, _, outlier = _noisy_graph(n, 0.7, 1.0, 0.15, seed=3)
    res = filter_edges(i, j, Rij, np.ones(i.size), n, sigma=0.2, use_support_count=False)
    assert res.in_tree.sum() == n - 1
    assert res.kept.shape == (i.size,)
    assert np.all(res.kept[res.in_tree])
    # Mean loop error alone is still a useful ordering on this easy graph.
    assert (~res.kept)[outlier].mean() >= 0.8
    assert res.kept[~outlier].mean() >= 0.8


def test_edges_on_no_triangle_are_never_removed() -> None:
    # A chain 0-1-...-9 plus a single long loop closure (0, 9) that is a gross outlier,
    # plus one triangle elsewhere so epsilon is defined.
    n = 12
    rng = np.random.default_rng(4)
    R = random_rotations(n, rng)
    pairs = [(k, k + 1) for k in range(9)] + [(0, 9), (10, 11), (9, 10), (9, 11)]
    i = np.array([p[0] for p in pairs])
    j = np.array([p[1] for p in pairs])
    Rij = np.einsum("eab,ecb->eac", R[i], R[j])
    closure = pairs.index((0, 9))
    Rij[closure] = rotation_about_axis([0.0, 0.0, 1.0], 2.5) @ Rij[closure]  # ~143 deg off
    res = filter_edges(i, j, Rij, np.ones(i.size), n, sigma=0.2)
    on_triangle = np.zeros(i.size, bool)
    on_triangle[[pairs.index(p) for p in [(9, 10), (10, 11), (9, 11)]]] = True
    np.testing.assert_array_equal(res.tested, on_triangle)
    assert np.all(res.kept[~res.tested])
    assert res.kept[closure]
    assert res.tree_residual[closure] > 0.2  # it would have failed the sigma test
    assert res.num_triangles == 1
    assert res.in_tree.sum() == n - 1


def test_tree_rotations_exact_on_noise_free_data() -> None:
    n = 25
    rng = np.random.default_rng(5)
    R = random_rotations(n, rng)
    i, j = _random_edges(n, 0.4, rng)
    Rij = np.einsum("eab,ecb->eac", R[i], R[j])
    res = filter_edges(i, j, Rij, np.ones(i.size), n, sigma=0.2)
    assert np.all(res.kept)
    assert np.all(res.tree_residual < 1e-12)
    # Root (node 0) is identity: tree rotations are R_k R_0^T.
    expected = np.einsum("kab,cb->kac", R, R[0])
    np.testing.assert_allclose(res.tree_rotations, expected, atol=1e-12)
    assert np.all(chordal_distance(res.tree_rotations[0], np.eye(3)) < 1e-15)


def test_tree_rotations_per_component_roots() -> None:
    # Two components: {0, 1, 2} and {3, 4}; each root gets identity.
    R = random_rotations(5, np.random.default_rng(6))
    pairs = [(0, 1), (1, 2), (0, 2), (3, 4)]
    i = np.array([p[0] for p in pairs])
    j = np.array([p[1] for p in pairs])
    Rij = np.einsum("eab,ecb->eac", R[i], R[j])
    res = filter_edges(i, j, Rij, np.ones(i.size), 5, sigma=0.2)
    assert res.in_tree.sum() == 3
    np.testing.assert_allclose(res.tree_rotations[0], np.eye(3), atol=1e-15)
    np.testing.assert_allclose(res.tree_rotations[3], np.eye(3), atol=1e-15)
    np.testing.assert_allclose(res.tree_rotations[4], R[4] @ R[3].T, atol=1e-12)
    np.testing.assert_allclose(res.tree_rotations[2], R[2] @ R[0].T, atol=1e-12)


@pytest.mark.parametrize("index_dtype", [np.int64, np.int32])
def test_tree_rotations_on_a_70k_node_chain(index_dtype: type) -> None:
    # Pair keys min * N + max pass 2**32 here: they must not be formed in int32 (scipy's
    # traversal returns int32 node arrays).
    n = 70_000
    R = random_rotations(n, np.random.default_rng(7))
    i: np.ndarray = np.arange(n - 1, dtype=index_dtype)
    j = i + 1
    Rij = np.einsum("eab,ecb->eac", R[i], R[j])
    rot = tree_rotations(i, j, Rij, np.arange(n - 1), n)
    expected = np.einsum("kab,cb->kac", R, R[0])
    np.testing.assert_allclose(rot, expected, atol=1e-8)


@pytest.mark.parametrize("swap, weights, expected", [
    (False, (1.0, 1.0), (1, 3)),  # exact tie: input order decides
    (True, (1.0, 1.0), (2, 3)),
    (False, (1.0, 2.0), (2, 3)),  # exact tie: higher weight first
])
def test_exact_priority_ties_fall_back_on_weight_then_input_order(
    swap: bool, weights: tuple[float, float], expected: tuple[int, int]
) -> None:
    # Node 3's two edges lie on the same single triangle (1, 2, 3), so they tie on support
    # count and mean loop error (Ellis Island's camera 23); they disagree by 40 deg, so the
    # tree keeps exactly one of them.
    rng = np.random.default_rng(7)
    R = random_rotations(4, rng)
    pairs = [(0, 1), (0, 2), (1, 2), (1, 3), (2, 3)]
    if swap:
        pairs[3], pairs[4] = pairs[4], pairs[3]
    i = np.array([p[0] for p in pairs])
    j = np.array([p[1] for p in pairs])
    Rij = np.einsum("eab,ecb->eac", R[i], R[j])
    Rij[pairs.index((2, 3))] = rotation_about_axis([1.0, 0.0, 0.0], np.radians(40.0)) @ Rij[
        pairs.index((2, 3))]
    w = np.ones(i.size)
    w[pairs.index((1, 3))], w[pairs.index((2, 3))] = weights
    res = filter_edges(i, j, Rij, w, 4, sigma=0.2)
    a, b = pairs.index((1, 3)), pairs.index((2, 3))
    assert res.support[a] == res.support[b]
    assert res.mean_loop_error[a] == res.mean_loop_error[b]
    chosen = [p for k, p in enumerate(pairs) if res.in_tree[k] and p in ((1, 3), (2, 3))]
    assert chosen == [expected]
    assert res.kept[pairs.index(expected)]
    assert not res.kept[pairs.index((1, 3) if expected == (2, 3) else (2, 3))]


def test_parallel_edges_enter_the_spanning_tree_by_their_best_rank() -> None:
    """A node pair measured more than once (the array API does not merge them; the graph
    store does): the tree takes the best-ranked of each pair. Before, the sparse matrix
    summed their ranks, which named another edge or none (an IndexError on a tree of
    parallel edges)."""
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.solver import average_rotations

    rng = np.random.default_rng(3)
    truth = random_rotations(3, rng)
    i = np.array([0, 0, 1, 1, 1])
    j = np.array([1, 1, 2, 2, 2])
    R = np.einsum("eab,ecb->eac", truth[i], truth[j])
    R[0] = R[0] @ rotation_about_axis(np.array([0.0, 0.0, 1.0]), 0.3)  # one copy off
    weight = np.array([1.0, 2.0, 1.0, 1.0, 3.0])  # the heavier copy ranks first
    result = filter_edges(i, j, R, weight, 3, sigma=0.2)
    assert np.flatnonzero(result.in_tree).tolist() == [1, 4]
    for profile in ("paper", "default"):
        solved = average_rotations(3, i, j, R, weight, SolverOptions.for_profile(profile))
        rel = np.einsum("ab,cb->ac", solved.rotations[1], solved.rotations[2])
        assert chordal_distance(rel, truth[1] @ truth[2].T) < 1e-6
