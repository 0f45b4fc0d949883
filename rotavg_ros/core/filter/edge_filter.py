"""Spanning-tree edge filtering from triplet-loop support (the paper's Algorithm 1).

Input edges are ``(i, j, R_ij)`` with ``i < j`` and ``R_ij ~= R_i R_j^T`` (world-to-node
``R_i``), one edge per pair.

1. Every triangle ``(a, b, c)`` gives the loop error ``delta = d_chord(R_ab, R_ac R_cb)``.
   The three loop errors of one triangle are equal (they are chordal norms of the same
   cycle rotation, up to conjugation), so it is computed once and credited to all three
   edges.
2. ``epsilon`` = median of all loop errors; per edge, the mean loop error and the support
   count ``s`` = number of its loops with ``delta < epsilon``.
3. Kruskal's spanning forest with edges ordered by ``s`` descending, then mean error
   ascending (ablation (b): mean error only); exact ties by weight, then input order.
4. Tree rotations ``R_i^tree`` by traversal from each component's root; an edge is removed
   when ``d_chord(R_ij, R_i^tree R_j^tree^T) > sigma``.

Edges that lie on no triangle (common in SLAM graphs, which are mostly chains) carry no
loop evidence of their own. They are ordered after every triangle-supported edge (by
weight, then input order), so the tree uses them only where the graph needs them. They are
tested against the tree only where that test means something: when the tree path between
their end nodes consists of triangle-verified edges alone (e.g. a loop closure over an
odometry chain whose steps are confirmed by short loops). Then they are removed beyond the
looser ``sigma_untested``, which allows for the drift of a long path. Where the path uses
unverified edges (pose graphs without triangles, such as the SE-Sync benchmarks), the tree
is no reference and the edge is kept, left to the robust loss and reweighting of the DMF.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree

from rotavg_ros.core.filter.triangles import enumerate_triangles
from rotavg_ros.core.so3 import chordal_distance
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray


@dataclass(frozen=True)
class EdgeFilterResult:
    """Outcome of :func:`filter_edges`; arrays are indexed like the input edges."""

    kept: BoolArray
    in_tree: BoolArray
    tested: BoolArray
    """True for edges on at least one triangle (subject to the sigma test)."""
    path_tested: BoolArray
    """Edges on no triangle whose tree path is all triangle-verified (``sigma_untested``)."""
    support: IntArray
    mean_loop_error: FloatArray
    tree_residual: FloatArray
    """d_chord(R_ij, R_ij^tree)."""
    tree_rotations: FloatArray
    """(N, 3, 3) world-to-node rotations implied by the tree (root of each component = I)."""
    epsilon: float
    num_triangles: int

    @property
    def num_removed(self) -> int:
        return int((~self.kept).sum())


def loop_statistics(
    i: IntArray, j: IntArray, R: FloatArray, num_nodes: int
) -> tuple[IntArray, FloatArray, FloatArray, float, int]:
    """Per-edge support count, loop-error sum, loop count; epsilon; triangle count."""
    tri = enumerate_triangles(i, j, num_nodes)
    num_edges = i.size
    if tri.count == 0:
        zeros = np.zeros(num_edges)
        return np.zeros(num_edges, np.int64), zeros, zeros, float("nan"), 0
    delta = loop_errors(R, tri.e_ab, tri.e_bc, tri.e_ac)
    epsilon = float(np.median(delta))
    low = delta < epsilon
    count = np.zeros(num_edges)
    total = np.zeros(num_edges)
    support = np.zeros(num_edges, np.int64)
    # Each triangle credits its three edges; the sums run over ab, then bc, then ac, in
    # triangle order (np.add.at accumulates in index order, as a bincount would over the
    # three concatenated), without the 3T-long copies.
    for e in (tri.e_ab, tri.e_bc, tri.e_ac):
        count += np.bincount(e, minlength=num_edges)
        support += np.bincount(e[low], minlength=num_edges)
        np.add.at(total, e, delta)
    return support, total, count, epsilon, tri.count


def loop_errors(
    R: FloatArray, e_ab: IntArray, e_bc: IntArray, e_ac: IntArray, chunk: int = 1 << 15
) -> FloatArray:
    """``delta = d_chord(R_ab, R_ac R_cb) = ||R_ab - R_ac R_bc^T||_F`` per triangle.

    Edge rotations are gathered in a structure-of-arrays layout (9, T) and the 3x3 products
    written out as multiply-adds over T (several times faster than ``einsum`` over (T, 3, 3)
    on a million triangles), in chunks of ``chunk`` triangles to bound memory (small ones:
    their 2 MB arrays are reused in cache; Ellis Island in a fresh process 0.23 s with
    chunks of 2^18, 0.12 s with 2^15).
    """
    rows = torch.as_tensor(R.reshape(-1, 9).T.copy())  # rows[3a + b] = R[:, a, b]
    out = np.empty(e_ab.size)
    for start in range(0, e_ab.size, chunk):
        sl = slice(start, start + chunk)
        ab, bc, ac = (rows.index_select(1, torch.as_tensor(e[sl])) for e in (e_ab, e_bc, e_ac))
        sq = torch.zeros(ab.shape[1], dtype=torch.float64)
        for a in range(3):
            for c in range(3):  # (R_ac R_bc^T)[a, c] = sum_b R_ac[a, b] R_bc[c, b]
                pred = ac[3 * a] * bc[3 * c]
                pred.addcmul_(ac[3 * a + 1], bc[3 * c + 1]).addcmul_(ac[3 * a + 2], bc[3 * c + 2])
                sq.add_((ab[3 * a + c] - pred).square_())
        out[sl] = sq.sqrt_().numpy()
    return out


def priority_order(
    support: IntArray, mean_error: FloatArray, weight: FloatArray, use_support: bool
) -> IntArray:
    """Edge indices from highest to lowest priority for the greedy tree.

    Triangle-supported edges first; then support count descending (unless
    ``use_support`` is off), mean loop error ascending. Algorithm 1 leaves exact ties open
    (two edges of a degree-2 node on one triangle tie on both keys); they go to the higher
    weight, then the earlier input edge.
    """
    idx = np.arange(support.size)
    untested = ~np.isfinite(mean_error)
    err = np.where(untested, np.inf, mean_error)
    keys: tuple[NDArray[Any], ...] = (idx, -weight, err, -support, untested)
    if not use_support:
        keys = (idx, -weight, err, untested)
    return np.lexsort(keys).astype(np.int64)


def tree_rotations(
    i: IntArray, j: IntArray, R: FloatArray, tree_edges: IntArray, num_nodes: int
) -> FloatArray:
    """World-to-node rotations from the spanning forest; each component root is identity.

    The root of a component is its lowest node index. Each other node's rotation follows
    from its parent's through the tree edge between them, in breadth-first order (a node's
    parent in a tree does not depend on the traversal order, so neither does the result).
    """
    rot = np.tile(np.eye(3), (num_nodes, 1, 1))
    if tree_edges.size == 0:
        return rot
    ti, tj = i[tree_edges].astype(np.int64), j[tree_edges].astype(np.int64)
    adj = coo_matrix((np.ones(ti.size), (ti, tj)), shape=(num_nodes, num_nodes)).tocsr()
    # Tree edge of a node pair: sorted keys min * N + max, found by binary search.
    keys = np.minimum(ti, tj) * num_nodes + np.maximum(ti, tj)
    by_key = np.argsort(keys)
    sorted_keys = keys[by_key]
    labels = connected_components(adj, directed=False)[1]
    roots = np.unique(labels, return_index=True)[1]  # lowest index of each component
    for root in roots[np.bincount(labels)[labels[roots]] > 1]:
        order, pred = breadth_first_order(adj, int(root), directed=False,
                                          return_predecessors=True)
        # int64: scipy returns int32, and the pair keys below reach num_nodes ** 2.
        nodes = order[1:].astype(np.int64)
        parents = pred[nodes].astype(np.int64)
        pair = np.minimum(nodes, parents) * num_nodes + np.maximum(nodes, parents)
        e = tree_edges[by_key[np.searchsorted(sorted_keys, pair)]]
        # Edge (parent, node): R_pn = R_p R_n^T -> R_n = R_pn^T R_p; edge (node, parent):
        # R_np = R_n R_p^T -> R_n = R_np R_p.
        step = np.where((i[e] == parents)[:, None, None], R[e].transpose(0, 2, 1), R[e])
        for node, s, parent in zip(nodes.tolist(), step, parents.tolist(), strict=True):
            rot[node] = s @ rot[parent]
    return rot


def filter_edges(
    i: IntArray,
    j: IntArray,
    R: FloatArray,
    weight: FloatArray,
    num_nodes: int,
    sigma: float,
    use_support_count: bool = True,
    sigma_untested: float | None = None,
) -> EdgeFilterResult:
    """Algorithm 1 of the paper; see the module docstring for the rules.

    ``sigma_untested`` (default: no test) is the threshold for edges on no triangle whose
    tree path is triangle-verified.
    """
    support, total, count, epsilon, num_tri = loop_statistics(i, j, R, num_nodes)
    tested = count > 0
    mean_err = np.full(i.size, np.inf)
    mean_err[tested] = total[tested] / count[tested]
    order = priority_order(support, mean_err, weight, use_support_count)
    # Kruskal via scipy: MST on ranks (1 = best) gives the greedy forest of this order.
    # Of parallel edges (one node pair measured more than once) only the best-ranked one
    # enters the matrix: a sparse matrix sums duplicate entries, and the sum of two ranks
    # named another edge or none (an IndexError on a tree of parallel edges).
    rank = np.empty(i.size)
    rank[order] = np.arange(1, i.size + 1)
    pair = np.minimum(i, j) * num_nodes + np.maximum(i, j)
    best = order[np.unique(pair[order], return_index=True)[1]]  # first in rank order
    mst = minimum_spanning_tree(coo_matrix((rank[best], (i[best], j[best])),
                                           shape=(num_nodes, num_nodes)))
    mst = mst.tocoo()
    rank_to_edge = order  # rank r -> edge order[r - 1]
    tree_edges = rank_to_edge[np.rint(mst.data).astype(np.int64) - 1]
    in_tree = np.zeros(i.size, bool)
    in_tree[tree_edges] = True
    rot = tree_rotations(i, j, R, tree_edges, num_nodes)
    R_tree = np.einsum("eab,ecb->eac", rot[i], rot[j])
    resid = chordal_distance(R, R_tree)
    path_tested = np.zeros(i.size, bool)
    if sigma_untested is not None:
        path_tested = ~tested & ~in_tree & _verified_path(i, j, tree_edges, tested, num_nodes)
    kept = in_tree | np.where(tested, resid <= sigma,
                              ~path_tested | (resid <= (sigma_untested or 0.0)))
    return EdgeFilterResult(kept, in_tree, tested, path_tested, support, mean_err, resid, rot,
                            epsilon, num_tri)


def _verified_path(
    i: IntArray, j: IntArray, tree_edges: IntArray, tested: BoolArray, num_nodes: int
) -> BoolArray:
    """Per edge: are its end nodes joined by triangle-verified tree edges only?

    In a tree the path between two nodes is unique, so it is all-verified exactly when the
    nodes share a component of the forest made of the verified tree edges.
    """
    ver = tree_edges[tested[tree_edges]]
    adj = coo_matrix((np.ones(ver.size), (i[ver], j[ver])), shape=(num_nodes, num_nodes))
    labels = connected_components(adj, directed=False)[1]
    return labels[i] == labels[j]


def num_components(i: IntArray, j: IntArray, num_nodes: int) -> int:
    adj = coo_matrix((np.ones(i.size), (i, j)), shape=(num_nodes, num_nodes))
    return int(connected_components(adj, directed=False)[0])
