"""The order of the nodes along the trajectory, which tells the odometry (consecutive nodes).

A SLAM front end numbers its keyframes in the order it makes them, and its odometry joins
consecutive keyframes. A graph's dense indices follow the order its nodes were first named,
which is that order where the nodes come first (a g2o file's vertices, the node's frames as
they arrive) but not where only edges name them: an edge list sorted by ``(i, j)`` names
node 57 with the closure ``(0, 57)`` before node 2, and every closure so breaks two steps.
The odometry rule (``verify.odometry``, :func:`~.robust.verify.odometry_edges`) then no longer
finds a chain, and the false closures go unchecked (``chain/1000/rand40``'s edges sorted:
65.4 deg mean error against 3.4 deg).

So the sequence is one of these orders, whichever chains more of the nodes with edges:

- **the natural order of the ids**: integers by value (keyframe numbers, in whatever
  order the edges name them, with gaps or a stride), names by their text with each run of
  digits read as a number (``kf_9`` before ``kf_10``; two robots' ``a_12`` and ``b_12``
  each in their own run);
- **the order the nodes were first named** (the one kept on a tie, and for ids that are
  neither integers nor text);
- where neither chains ``ODOMETRY_COVERAGE`` of the nodes (ids that carry no order:
  random labels), **the graph's own paths** (:func:`path_order`), if they do: a keyframe
  that closes no loop has two edges, both odometry, so the edges at a node of degree at
  most two are the odometry's, and they form its paths; where two keyframes that both
  close loops follow each other, the one edge between the two paths' ends joins them.
"""

from __future__ import annotations

import numbers
import re
from collections.abc import Hashable, Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from rotavg_ros.core.robust.verify import ODOMETRY_COVERAGE
from rotavg_ros.core.types import BoolArray, IntArray

_DIGITS = re.compile(r"(\d+)")


def node_sequence(node_ids: Sequence[Hashable], i: IntArray, j: IntArray) -> IntArray:
    """Each node's position in the sequence (module docstring): an (N,) permutation of
    ``0 .. N-1``, indexed by dense index; ``i``, ``j`` are the edges' dense indices."""
    n = len(node_ids)
    best = np.arange(n, dtype=np.int64)  # the order first named
    best_chained = chained(best, i, j)
    natural = _natural_order(node_ids)
    if natural is not None:
        rank = _rank(natural)
        if (count := chained(rank, i, j)) > best_chained:
            best, best_chained = rank, count
    enough = ODOMETRY_COVERAGE * max(n - 1, 1)
    if best_chained >= enough:
        return best
    a, b, step = path_steps(n, i, j)
    if np.count_nonzero(step) < enough:  # (a path order chains little more than its
        return best  # steps: an edge between one path's end and the next path's start)
    rank = _rank(_walk(n, a[step], b[step]))
    return rank if chained(rank, i, j) >= enough else best


def _rank(order: IntArray) -> IntArray:
    """Each node's position in ``order`` (the dense indices in sequence order)."""
    rank = np.empty(order.size, np.int64)
    rank[order] = np.arange(order.size)
    return rank


def path_order(n: int, i: IntArray, j: IntArray) -> IntArray:
    """The nodes (dense indices) path by path along :func:`path_steps`: the paths in the
    order of their lower end's index, each walked from that end, then the rings, each cut
    at its lowest index."""
    a, b, step = path_steps(n, i, j)
    return _walk(n, a[step], b[step])


def path_steps(n: int, i: IntArray, j: IntArray) -> tuple[IntArray, IntArray, BoolArray]:
    """The graph's node pairs ``(a, b)``, ``a < b``, one per pair of nodes joined by an edge,
    and which of them are the steps of its paths (module docstring): the pairs at a node of
    degree at most two, but none at a node with more than two of them (a loop closure to a
    chain's end), and the bridges between paths (:func:`_bridges`)."""
    pair = np.unique(np.minimum(i, j) * np.int64(n) + np.maximum(i, j))
    a, b = pair // n, pair % n
    degree = np.bincount(np.r_[a, b], minlength=n)
    step = (degree[a] <= 2) | (degree[b] <= 2)
    steps_at = np.bincount(np.r_[a[step], b[step]], minlength=n)
    step &= (steps_at[a] <= 2) & (steps_at[b] <= 2)
    return a, b, step | _bridges(n, a, b, step)


def _walk(n: int, a: IntArray, b: IntArray) -> IntArray:
    """Every node once, along the steps ``(a, b)`` (at most two at a node): from each path
    end in index order, then around what is left (rings)."""
    nxt: list[list[int]] = [[] for _ in range(n)]
    for u, v in zip(a.tolist(), b.tolist(), strict=True):
        nxt[u].append(v)
        nxt[v].append(u)
    order: list[int] = []
    seen = np.zeros(n, bool)
    ends = [k for k in range(n) if len(nxt[k]) <= 1]
    for start in ends + list(range(n)):
        prev, cur = -1, start
        while cur >= 0 and not seen[cur]:
            seen[cur] = True
            order.append(cur)
            prev, cur = cur, next((m for m in nxt[cur] if m != prev and not seen[m]), -1)
    return np.asarray(order, np.int64)


def _natural_order(node_ids: Sequence[Hashable]) -> IntArray | None:
    """The dense indices in the ids' natural order (:func:`natural_key`, stable); None
    where some id has no natural key."""
    if all(type(k) is int for k in node_ids):
        try:  # plain integers (the usual case): sorted in numpy
            return np.argsort(np.array(node_ids, np.int64), kind="stable").astype(np.int64)
        except OverflowError:
            pass
    keys = [natural_key(k) for k in node_ids]
    if any(k is None for k in keys):
        return None
    return np.array(sorted(range(len(keys)), key=lambda m: keys[m] or ()), np.int64)


def natural_key(node_id: Hashable) -> tuple[tuple[int, int | str], ...] | None:
    """The id's place in the natural order: an integer by value (integers before names), a
    name by its text with each run of digits read as a number; None for any other id."""
    if isinstance(node_id, numbers.Integral) and not isinstance(node_id, bool):
        return ((0, int(node_id)),)
    if not isinstance(node_id, str):
        return None
    return tuple(_number(part) if _DIGITS.fullmatch(part) else (2, part)
                 for part in _DIGITS.split(node_id) if part)


def _number(digits: str) -> tuple[int, str]:
    """A run of digits in a name, ordered by its value (its length without leading zeros,
    then its text: no conversion, so no limit on its length) and before text."""
    value = digits.lstrip("0")
    return (1, f"{len(value):012d}{value}")


def _bridges(n: int, a: IntArray, b: IntArray, step: BoolArray) -> BoolArray:
    """The edges that join the ends of two different paths of ``step`` where no end is
    offered more such edges than it has room for (a path's end one, a lone node two): the
    steps between keyframes that both close loops. (Each such keyframe's other edges are
    its path's step and its closure, which ends inside another path.)"""
    steps_at = np.bincount(np.r_[a[step], b[step]], minlength=n)
    _, path = connected_components(
        coo_matrix((np.ones(int(step.sum())), (a[step], b[step])), shape=(n, n)),
        directed=False)
    room = 2 - steps_at
    bridge = ~step & (room[a] >= 1) & (room[b] >= 1) & (path[a] != path[b])
    offers = np.bincount(np.r_[a[bridge], b[bridge]], minlength=n)
    return bridge & (offers[a] <= room[a]) & (offers[b] <= room[b])


def chained(rank: IntArray, i: IntArray, j: IntArray) -> int:
    """How many consecutive pairs of the sequence ``rank`` some edge joins."""
    ri, rj = rank[i], rank[j]
    step = np.abs(ri - rj) == 1
    return int(np.unique(np.minimum(ri, rj)[step]).size)
