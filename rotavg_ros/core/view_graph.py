"""View graph of relative rotations, with dense node indexing.

Conventions
-----------
* Each node ``i`` has an unknown absolute rotation ``R_i`` that maps **world to node**
  coordinates (``x_node = R_i x_world``).
* An edge ``(i, j)`` carries ``R_ij ~= R_i R_j^T``: it maps node-j coordinates to node-i
  coordinates, i.e. it is the orientation of frame j expressed in frame i (TF convention).
* A reversed measurement ``(j, i, R_ji)`` is stored as ``(i, j, R_ji^T)``.
* Node ids are any hashable (strings for ROS frames, ints for datasets) and are mapped to
  dense indices ``0..N-1`` in order of first appearance.

Parallel measurements of the same pair are all kept; :meth:`ViewGraph.edge_arrays`
consolidates them into one edge per pair according to :class:`RepeatPolicy`.
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable
from dataclasses import dataclass
from enum import Enum

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from rotavg_ros.core.so3 import project_to_so3
from rotavg_ros.core.types import FloatArray, IntArray


class RepeatPolicy(str, Enum):
    """How parallel measurements of one node pair become one edge.

    * ``MERGE`` (default): robust single-rotation average of all measurements (weighted
      chordal L1 median by Weiszfeld iterations, projected to SO(3)); the edge weight is
      the sum of the measurement weights. Suits SLAM graphs that re-observe loop closures.
    * ``LATEST``: the most recent measurement replaces earlier ones.
    * ``FIRST``: the first measurement is kept, later ones are ignored.
    """

    MERGE = "merge"
    LATEST = "latest"
    FIRST = "first"


@dataclass(frozen=True)
class EdgeArrays:
    """One consolidated edge per node pair, with ``i < j`` and ``R[k] ~= R_i R_j^T``."""

    i: IntArray
    j: IntArray
    R: FloatArray
    weight: FloatArray
    multiplicity: IntArray

    @property
    def num_edges(self) -> int:
        return int(self.i.shape[0])


class ViewGraph:
    """Growing multigraph of relative-rotation measurements."""

    def __init__(self, repeat_policy: RepeatPolicy | str = RepeatPolicy.MERGE) -> None:
        self.repeat_policy = RepeatPolicy(repeat_policy)
        self._index: dict[Hashable, int] = {}
        self._ids: list[Hashable] = []
        self._i: list[int] = []
        self._j: list[int] = []
        self._R: list[FloatArray] = []
        self._w: list[float] = []
        self._cache: EdgeArrays | None = None

    # ------------------------------------------------------------------ nodes
    @property
    def num_nodes(self) -> int:
        return len(self._ids)

    @property
    def num_measurements(self) -> int:
        return len(self._i)

    @property
    def node_ids(self) -> list[Hashable]:
        return list(self._ids)

    def index_of(self, node_id: Hashable) -> int:
        """Dense index of ``node_id`` (KeyError if unknown)."""
        return self._index[node_id]

    def has_node(self, node_id: Hashable) -> bool:
        return node_id in self._index

    def add_node(self, node_id: Hashable) -> int:
        """Register ``node_id`` (idempotent) and return its dense index."""
        idx = self._index.get(node_id)
        if idx is None:
            idx = len(self._ids)
            self._index[node_id] = idx
            self._ids.append(node_id)
            self._cache = None
        return idx

    # ------------------------------------------------------------------ edges
    def add_edge(
        self, node_i: Hashable, node_j: Hashable, R_ij: FloatArray, weight: float = 1.0
    ) -> None:
        """Add one measurement ``R_ij ~= R_i R_j^T`` (world-to-node ``R_i``).

        Raises ``ValueError`` for a self-loop, a non-finite or non-3x3 matrix, or a
        non-positive / non-finite weight; callers that must not raise validate first.
        """
        if node_i == node_j:
            raise ValueError(f"self-loop on node {node_i!r}")
        R = np.asarray(R_ij, dtype=np.float64)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise ValueError("R_ij must be a finite 3x3 matrix")
        if not (np.isfinite(weight) and weight > 0):
            raise ValueError(f"weight must be finite and > 0, got {weight!r}")
        a = self.add_node(node_i)
        b = self.add_node(node_j)
        if a > b:
            a, b, R = b, a, R.T
        self._i.append(a)
        self._j.append(b)
        self._R.append(R.copy())
        self._w.append(float(weight))
        self._cache = None

    def add_edges(
        self,
        node_i: Iterable[Hashable],
        node_j: Iterable[Hashable],
        R: FloatArray,
        weight: FloatArray | None = None,
    ) -> None:
        """:meth:`add_edge` for many measurements, checked all at once; when one is invalid,
        the ones before it are added and its error is raised, as one call each would."""
        ni = list(node_i)
        nj = list(node_j)
        R = np.array(R, dtype=np.float64)  # a copy: the graph keeps views of it
        w = np.ones(len(ni)) if weight is None else np.asarray(weight, dtype=np.float64)
        if not (len(ni) == len(nj) == R.shape[0] == w.shape[0]):
            raise ValueError("node_i, node_j, R and weight must have the same length")
        valid = (R.shape[1:] == (3, 3) and bool(np.isfinite(R).all())
                 and bool(np.all(np.isfinite(w) & (w > 0)))
                 and not any(a == b for a, b in zip(ni, nj, strict=True)))
        if not valid:  # one by one, up to the invalid one
            for a, b, Rk, wk in zip(ni, nj, R, w, strict=True):
                self.add_edge(a, b, Rk, float(wk))
            return
        add = self.add_node  # node order as one call each: i, then j, edge by edge
        ends = np.array([(add(a), add(b)) for a, b in zip(ni, nj, strict=True)],
                        dtype=np.int64).reshape(-1, 2)
        ia, ib = ends[:, 0], ends[:, 1]
        swap = ia > ib
        R[swap] = np.swapaxes(R[swap], 1, 2)
        self._i.extend(np.where(swap, ib, ia).tolist())
        self._j.extend(np.where(swap, ia, ib).tolist())
        self._R.extend(R)
        self._w.extend(w.tolist())
        self._cache = None

    def clear(self) -> None:
        """Remove every node and measurement."""
        self.__init__(self.repeat_policy)  # type: ignore[misc]

    def measurement_arrays(self) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
        """All raw measurements (``i < j`` orientation), in arrival order."""
        if not self._i:
            return (np.zeros(0, np.int64), np.zeros(0, np.int64),
                    np.zeros((0, 3, 3)), np.zeros(0))
        return (np.asarray(self._i, np.int64), np.asarray(self._j, np.int64),
                np.stack(self._R), np.asarray(self._w))

    def edge_arrays(self) -> EdgeArrays:
        """Consolidated edges, one per pair, sorted by ``(i, j)``."""
        if self._cache is None:
            self._cache = consolidate(*self.measurement_arrays(), policy=self.repeat_policy)
        return self._cache

    # -------------------------------------------------------------- structure
    def components(self) -> tuple[int, IntArray]:
        """Connected components: ``(count, label per node)``."""
        e = self.edge_arrays()
        n = self.num_nodes
        adj = coo_matrix((np.ones(e.num_edges), (e.i, e.j)), shape=(n, n))
        count, labels = connected_components(adj, directed=False)
        return int(count), labels.astype(np.int64)


def consolidate(
    i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    policy: RepeatPolicy = RepeatPolicy.MERGE, weiszfeld_iters: int = 10,
) -> EdgeArrays:
    """Group measurements by pair (``i < j`` already) and apply ``policy``."""
    if i.size == 0:
        return EdgeArrays(i, j, R, w, np.zeros(0, np.int64))
    n = int(max(i.max(), j.max())) + 1
    key = i * n + j
    order = np.argsort(key, kind="stable")  # stable: arrival order inside each pair
    key_s = key[order]
    uniq, start, counts = np.unique(key_s, return_index=True, return_counts=True)
    if policy is RepeatPolicy.FIRST:
        pick = order[start]
        return EdgeArrays(i[pick], j[pick], R[pick], w[pick], counts.astype(np.int64))
    if policy is RepeatPolicy.LATEST:
        pick = order[start + counts - 1]
        return EdgeArrays(i[pick], j[pick], R[pick], w[pick], counts.astype(np.int64))
    group = np.repeat(np.arange(uniq.size), counts)
    Rs, ws = R[order], w[order]
    total_w = np.bincount(group, weights=ws).astype(np.float64, copy=False)
    mean = _group_sum(group, ws[:, None, None] * Rs, uniq.size) / total_w[:, None, None]
    est = project_to_so3(mean)
    multi = counts > 1
    if np.any(multi):
        # Weiszfeld iterations for the chordal L1 median, only on groups with > 1 item.
        for _ in range(weiszfeld_iters):
            d = np.sqrt(np.einsum("kab,kab->k", Rs - est[group], Rs - est[group]))
            c = ws / np.maximum(d, 1e-9)
            num = _group_sum(group, c[:, None, None] * Rs, uniq.size)
            den = np.bincount(group, weights=c)
            est = np.where(multi[:, None, None], project_to_so3(num / den[:, None, None]), est)
    first = order[start]
    return EdgeArrays(i[first], j[first], est, total_w, counts.astype(np.int64))


def _group_sum(group: IntArray, values: FloatArray, size: int) -> FloatArray:
    out = np.zeros((size,) + values.shape[1:])
    np.add.at(out, group, values)
    return out
