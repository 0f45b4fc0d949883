"""The order of the nodes along the trajectory, which tells the odometry (consecutive nodes).

A SLAM front end numbers its keyframes in the order it makes them, and its odometry joins
consecutive keyframes. A graph's dense indices follow the order its nodes were first named,
which is that order where the nodes come first (a g2o file's vertices, the node's frames as
they arrive) but not where only edges name them: an edge list sorted by ``(i, j)`` names
node 57 with the closure ``(0, 57)`` before node 2, and every closure so breaks two steps.
The odometry rule (``verify.odometry``, :func:`~.robust.verify.odometry_edges`) then no longer
finds a chain, and the false closures go unchecked (``chain/1000/rand40``'s edges sorted:
65.4 deg mean error against 3.4 deg).

So the sequence is one of two orders, whichever chains more of the nodes with edges:

- **the natural order of the ids**: integers by value (keyframe numbers, in whatever
  order the edges name them, with gaps or a stride), names by their text with each run of
  digits read as a number (``kf_9`` before ``kf_10``; two robots' ``a_12`` and ``b_12``
  each in their own run);
- **the order the nodes were first named** (the one kept on a tie, and for ids that are
  neither integers nor text).

Neither order can tell the odometry of ids that carry no order (random labels).
"""

from __future__ import annotations

import numbers
import re
from collections.abc import Hashable, Sequence

import numpy as np

from rotavg_ros.core.types import IntArray

_DIGITS = re.compile(r"(\d+)")


def node_sequence(node_ids: Sequence[Hashable], i: IntArray, j: IntArray) -> IntArray:
    """Each node's position in the sequence (module docstring): an (N,) permutation of
    ``0 .. N-1``, indexed by dense index; ``i``, ``j`` are the edges' dense indices."""
    n = len(node_ids)
    added = np.arange(n, dtype=np.int64)
    keys = [key for key in map(natural_key, node_ids) if key is not None]
    if len(keys) < n:
        return added
    natural = np.empty(n, np.int64)
    natural[sorted(range(n), key=lambda m: keys[m])] = added
    return natural if chained(natural, i, j) > chained(added, i, j) else added


def natural_key(node_id: Hashable) -> tuple[tuple[int, int | str], ...] | None:
    """The id's place in the natural order: an integer by value, a name by its text with
    each run of digits read as a number; None for any other id."""
    if isinstance(node_id, numbers.Integral) and not isinstance(node_id, bool):
        return ((0, int(node_id)),)
    if not isinstance(node_id, str):
        return None
    return tuple((0, int(part)) if _DIGITS.fullmatch(part) else (1, part)
                 for part in _DIGITS.split(node_id) if part)


def chained(rank: IntArray, i: IntArray, j: IntArray) -> int:
    """How many consecutive pairs of the sequence ``rank`` some edge joins."""
    ri, rj = rank[i], rank[j]
    step = np.abs(ri - rj) == 1
    return int(np.unique(np.minimum(ri, rj)[step]).size)
