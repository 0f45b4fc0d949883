"""Block turns: rigid moves of a block of nodes that one piece of evidence alone holds.

A least-squares (or GNC) fit can leave a whole block of nodes turned: where the block's edges
to the rest are few and one of them is wrong, a local method fits the wrong one and rejects
the true ones (each of which, from there, looks like an outlier). The single-node moves of
:mod:`.relocalize` cannot undo that: every node of the block agrees with its neighbours in
the block. The block's own edges to the rest say so. The explained edges (residual within
the cap, or trusted) hold such a block to the rest by one piece of evidence only:

- **a bridge** of the explained graph (:func:`find_bridges`): one edge (the 1,661-node
  parking-garage of ``regime_stress`` draw 97 with wrong odometry steps: nodes 0-56 and
  1581-1660 held by the wrong step at keyframe 56, the true step 1580-1581 and a true
  closure to the rest rejected, 73 deg off together);
- **a run of loop closures** (:func:`~.closure_runs.closure_runs`: closures between the
  same two stretches) whose removal splits the explained graph with the whole run between
  the two sides: one wrong match repeated keyframe after keyframe (the issue's new-user
  chain with a group of seven false closures and a wrong odometry step: nodes 0-41 held by
  the group, the four true closures across rejected, 62.6 deg mean error).

A trusted edge is a cut only where the caller says it may break (odometry: a front end
that lost its track reports one wrong step, and trusted, it holds everything after it; on
the issue's new-user chains with one wrong step, 34 graphs of 778 had the far-off nodes held
by the trusted wrong step alone, two or more true pieces of evidence across rejected: up to
72 deg mean error). The closures across a stretch of trusted steps cannot tell which of
them broke (each cut fits them alike): of the bridges with the same rejected edges across,
only the step with the largest measured rotation is proposed (a lost track's step is a
random rotation, rarely as small as a keyframe's usual motion), and none where an
untrusted bridge has the same edges across.

For each such cut, with two nodes or more on the other side (a single node held by one
wrong step is a block too: its own edges across are the evidence), the nodes on the side
away from node 0 turn as ``R_k <- R_k M``: edges inside the block and outside it
keep their residuals. A rejected edge ``(a, b)`` from the block to the rest predicts ``M =
R_a^T R_ab R_b`` (``a`` in the block) or ``R_b^T R_ab^T R_a`` (``b`` in the block). The
largest group of predictions within ``tolerance`` of one of them proposes the turn to their
chordal mean where it is at least two independent pieces of evidence
(:func:`~.closure_runs.independent_pieces`: each run one, each other edge one) and lies
farther than ``tolerance`` from the block's placement (nearer, the edges are only noisy: a
re-fit's business). The tolerance is wide (the caller's initial threshold, 30 deg): the
true edges' predictions carry the drift of the fit that left the block turned (13 deg
apart in that parking-garage); random false edges rarely agree within it, and a group of
consistent false ones is one run, one piece. A proposal is only that: the caller re-fits
each and keeps it where its objective says so (:func:`~.verify.turn_blocks`).

Conventions: world-to-node ``R_i``, ``R_ij ~= R_i R_j^T``; a block turns in its nodes' own
frames (right multiplication), on the side away from node 0 (the anchor) where one side
holds it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from rotavg_ros.core.robust.closure_runs import closure_runs, independent_pieces
from rotavg_ros.core.robust.gauss_newton import residual_angles
from rotavg_ros.core.so3 import geodesic_distance, project_to_so3, rotation_angle
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray

MAX_TURNS = 3
"""At most this many block turns are proposed (each costs the caller a least-squares re-fit),
the best supported first."""


@dataclass(frozen=True)
class Bridges:
    """The bridges of a graph from one depth-first search (roots in node order)."""

    edges: IntArray
    """Edge index of each bridge."""
    child: IntArray
    """The bridge's end deeper in the search: its subtree is the side away from the root."""
    pre: IntArray
    """Preorder number of every node: a subtree is ``pre[child] <= pre < pre[child] +
    size[child]``."""
    size: IntArray
    """Nodes in each node's subtree."""
    component_size: IntArray
    """Nodes in each node's connected component."""


def find_bridges(num_nodes: int, i: IntArray, j: IntArray, keep: BoolArray) -> Bridges:
    """Bridges of the graph of the ``keep`` edges (parallel edges are no bridges): an
    iterative depth-first search with low points (Tarjan)."""
    e_keep = np.flatnonzero(keep)
    ends = np.concatenate([i[e_keep], j[e_keep]])
    others = np.concatenate([j[e_keep], i[e_keep]])
    ids = np.concatenate([e_keep, e_keep])
    order = np.argsort(ends, kind="stable")
    start = np.searchsorted(ends[order], np.arange(num_nodes + 1)).tolist()
    other, edge_id = others[order].tolist(), ids[order].tolist()
    pre = [-1] * num_nodes
    low = [0] * num_nodes
    size = [1] * num_nodes
    comp = [0] * num_nodes
    ptr = start[:-1]
    bridge_edges: list[int] = []
    bridge_child: list[int] = []
    comp_sizes: list[int] = []
    counter = 0
    for root in range(num_nodes):
        if pre[root] >= 0:
            continue
        first = counter
        pre[root] = low[root] = counter
        counter += 1
        stack = [(root, -1)]
        while stack:
            v, parent_edge = stack[-1]
            comp[v] = len(comp_sizes)
            if ptr[v] < start[v + 1]:
                k = ptr[v]
                ptr[v] += 1
                e, u = edge_id[k], other[k]
                if e == parent_edge:
                    continue
                if pre[u] < 0:
                    pre[u] = low[u] = counter
                    counter += 1
                    stack.append((u, e))
                elif pre[u] < low[v]:
                    low[v] = pre[u]
                continue
            stack.pop()
            size[v] = counter - pre[v]
            if stack:
                p = stack[-1][0]
                if low[v] < low[p]:
                    low[p] = low[v]
                if low[v] > pre[p]:
                    bridge_edges.append(parent_edge)
                    bridge_child.append(v)
        comp_sizes.append(counter - first)
    return Bridges(np.asarray(bridge_edges, np.int64), np.asarray(bridge_child, np.int64),
                   np.asarray(pre, np.int64), np.asarray(size, np.int64),
                   np.asarray(comp_sizes, np.int64)[np.asarray(comp, np.int64)])


@dataclass(frozen=True)
class BlockTurn:
    """A rigid turn of a block of nodes: ``R_k <- R_k turn`` for ``k`` in ``nodes``."""

    nodes: IntArray
    turn: FloatArray
    cut: IntArray
    """The edges the turn cuts: the bridge, or the run of closures, that alone held the
    block where it was."""
    joins: IntArray
    """The crossing edges that agree on the turn (they hold the block after it)."""
    relocalized: int
    """Nodes on the smaller side of the cut (those that end far off if the turn is wrong)."""


def block_turns(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray, cap: float,
    tolerance: float, trusted: BoolArray | None = None,
    closures: BoolArray | None = None, limit: int = MAX_TURNS,
    breakable: BoolArray | None = None,
) -> list[BlockTurn]:
    """Up to ``limit`` block turns (module docstring), the best supported first: for each
    cut of the edges ``rot`` explains (residual ``sqrt(w) * angle`` within ``cap``, or
    ``trusted``) by one piece of evidence that is not trusted (a bridge, or a run of
    ``closures``, :func:`~.closure_runs.closure_runs`), with two nodes or more on the
    other side, the largest group of unexplained crossing edges whose predicted turns lie
    within ``tolerance`` of one of them, where it is at least two independent pieces of evidence
    (:func:`~.closure_runs.independent_pieces`) and its turn lies farther than
    ``tolerance`` from the block's placement. ``breakable``: trusted edges whose bridges are
    cuts too (module docstring)."""
    n = rot.shape[0]
    known = np.zeros(i.size, bool) if trusted is None else trusted
    runs_of = np.zeros(i.size, bool) if closures is None else closures
    keep = (residual_angles(rot, i, j, R) * np.sqrt(w) <= cap) | known
    if keep.all():
        return []
    unexplained = np.flatnonzero(~keep)
    turns: list[tuple[tuple[float, bool, float], BlockTurn]] = []
    may_break = (np.zeros(i.size, bool) if breakable is None else breakable) & known
    step_angle = rotation_angle(R) if may_break.any() else None
    for cut, side, component in _cuts(n, i, j, keep, known, runs_of, may_break, step_angle):
        if component - side.sum() < 2:
            continue
        in_a, in_b = side[i[unexplained]], side[j[unexplained]]
        e = unexplained[in_a != in_b]
        if e.size < 2:
            continue
        # The turn each crossing edge predicts: M = R_a^T R_ab R_b with a in the block,
        # its transpose with b in the block.
        pred = np.transpose(rot[i[e]], (0, 2, 1)) @ R[e] @ rot[j[e]]
        P = np.where(in_a[in_a != in_b][:, None, None], pred, np.transpose(pred, (0, 2, 1)))
        near = geodesic_distance(P[:, None], P[None]) <= tolerance
        group = near[int(np.argmax(near @ w[e]))]
        joins = e[group]
        # Independent pieces: each run of closures one, each other edge one (odometry steps
        # side by side are no run).
        joined_closures = np.zeros(i.size, bool)
        joined_closures[joins[runs_of[joins]]] = True
        if (independent_pieces(i, j, joined_closures)
                + int(np.count_nonzero(~runs_of[joins])) < 2):
            continue
        M = project_to_so3(np.einsum("e,eab->ab", w[joins], P[group]))
        if geodesic_distance(M, np.eye(3)) <= tolerance:
            continue
        nodes = np.flatnonzero(side)
        smaller = min(nodes.size, component - nodes.size)
        # The best supported first; the same joins propose the same turn from any of
        # their cuts: an untrusted cut before a trusted one, a larger step before a
        # smaller, and a trusted cut only where no cut before it has those joins.
        rank = (-float(w[joins].sum()), bool(known[cut].any()),
                0.0 if step_angle is None else -float(step_angle[cut].max()))
        turns.append((rank, BlockTurn(nodes, M, cut, joins, smaller)))
    turns.sort(key=lambda t: t[0])
    proposed: list[BlockTurn] = []
    for _, turn in turns:
        if not (known[turn.cut].any()
                and any(np.array_equal(turn.joins, p.joins) for p in proposed)):
            proposed.append(turn)
    return proposed[:limit]


def _cuts(n: int, i: IntArray, j: IntArray, keep: BoolArray, known: BoolArray,
          closures: BoolArray, may_break: BoolArray, step_angle: FloatArray | None,
          ) -> list[tuple[IntArray, BoolArray, int]]:
    """``(cut edges, side, component size)`` for each bridge of the ``keep`` edges that is
    not ``known`` or ``may_break`` (of those with the same unexplained edges across, the one
    with the largest ``step_angle``, none where a bridge not known has them too), then each
    run of kept ``closures`` (not ``known``) whose removal splits its component in two with
    the whole run between them; ``side``: the nodes of the side away from node 0 (for a run
    where neither side holds node 0, the side of the run's first edge's first end)."""
    out: list[tuple[IntArray, BoolArray, int]] = []
    bridges = find_bridges(n, i, j, keep)
    candidates = ~known[bridges.edges] | may_break[bridges.edges]
    edges, child = bridges.edges[candidates], bridges.child[candidates]
    if step_angle is not None and edges.size:
        edges, child = _one_step_per_crossing(bridges, edges, child, i, j, keep, known,
                                              step_angle)
    for bridge, v in zip(edges.tolist(), child.tolist(), strict=True):
        lo, hi = bridges.pre[v], bridges.pre[v] + bridges.size[v]
        out.append((np.array([bridge]), (bridges.pre >= lo) & (bridges.pre < hi),
                    int(bridges.component_size[v])))
    runs = closure_runs(i, j, keep & closures & ~known)
    if runs:
        # A run splits nothing whose first edge's ends stay joined without every run's
        # edges (a subgraph of the graph without that run): one labelling skips most.
        without_runs = keep.copy()
        without_runs[np.concatenate(runs)] = False
        joined = _labels(n, i, j, without_runs)
    for run in runs:
        if joined[i[run[0]]] == joined[j[run[0]]]:
            continue
        rest = keep.copy()
        rest[run] = False
        label = _labels(n, i, j, rest)
        a, b = label[i[run]], label[j[run]]
        ends = {int(a[0]), int(b[0])}
        if len(ends) < 2 or not all({int(x), int(y)} == ends for x, y in zip(a, b, strict=True)):
            continue
        far = int(b[0]) if label[0] == a[0] else int(a[0])
        out.append((run, label == far, int(np.count_nonzero(np.isin(label, list(ends))))))
    return out


def _labels(n: int, i: IntArray, j: IntArray, keep: BoolArray) -> IntArray:
    """Connected-component label of each node in the graph of the ``keep`` edges."""
    graph = coo_matrix((np.ones(int(keep.sum())), (i[keep], j[keep])), shape=(n, n))
    return np.asarray(connected_components(graph, directed=False)[1])


def _one_step_per_crossing(bridges: Bridges, edges: IntArray, child: IntArray, i: IntArray,
                           j: IntArray, keep: BoolArray, known: BoolArray,
                           step_angle: FloatArray) -> tuple[IntArray, IntArray]:
    """The candidate bridges ``edges`` (with their deeper ends ``child``) less the known
    ones that fewer than two unexplained edges cross, or whose unexplained edges across are
    those of an unknown bridge or of a known one with a larger ``step_angle``: the edges
    across cannot tell those cuts apart."""
    unexplained = np.flatnonzero(~keep)
    pa, pb = bridges.pre[i[unexplained]], bridges.pre[j[unexplained]]
    lo = bridges.pre[child][:, None]
    hi = lo + bridges.size[child][:, None]
    across = ((pa >= lo) & (pa < hi)) != ((pb >= lo) & (pb < hi))
    trusted = known[edges]
    keys = [row.tobytes() for row in np.packbits(across, axis=1)]
    taken = {keys[k] for k in np.flatnonzero(~trusted)}
    best: dict[bytes, int] = {}
    for k in np.flatnonzero(trusted & (across.sum(axis=1) >= 2)).tolist():
        if keys[k] in taken:
            continue
        if keys[k] not in best or step_angle[edges[k]] > step_angle[edges[best[keys[k]]]]:
            best[keys[k]] = k
    chosen = np.zeros(edges.size, bool)
    chosen[~trusted] = True
    chosen[list(best.values())] = True
    return edges[chosen], child[chosen]
