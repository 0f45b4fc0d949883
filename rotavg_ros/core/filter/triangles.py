"""Vectorised triangle enumeration on an undirected simple graph.

Edges are given as ``(i, j)`` index arrays with ``i < j`` and no duplicates. A triangle is
reported once, as the indices of its three edges ``ab``, ``bc`` and ``ac`` into the input
arrays, with ``a < b < c`` (:meth:`Triangles.nodes` gives the nodes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rotavg_ros.core.types import IntArray


@dataclass(frozen=True)
class Triangles:
    """Triangles ``a < b < c`` by the indices of their edges ``ab``, ``bc`` and ``ac``."""

    e_ab: IntArray
    e_bc: IntArray
    e_ac: IntArray

    @property
    def count(self) -> int:
        return int(self.e_ab.shape[0])

    def nodes(self, i: IntArray, j: IntArray) -> IntArray:
        """(T, 3) nodes ``a, b, c`` of each triangle, from the edge arrays it was found in
        (``a = i[ab]``, ``b = j[ab]``, ``c = j[ac]``; the filter needs only the edges)."""
        return np.stack([i[self.e_ab], j[self.e_ab], j[self.e_ac]], axis=1)


def enumerate_triangles(
    i: IntArray, j: IntArray, num_nodes: int, chunk_pairs: int = 250_000
) -> Triangles:
    """All triangles of the graph, in O(sum over edges of out-degree) memory per chunk.

    For every edge ``(a, b)`` with ``a < b``, each forward neighbour ``c > b`` of ``b`` is a
    candidate; the candidate is a triangle when the edge ``(a, c)`` exists, found by binary
    search in the sorted edge keys. Work is split in chunks of about ``chunk_pairs``
    candidates so memory stays bounded on dense graphs, and so each chunk's arrays (2 MB
    at 250,000) reuse the memory the last chunk freed, in cache, instead of fresh pages:
    on Ellis Island (1.1 M triangles) one chunk of 4 M took 0.27 s in a fresh process,
    chunks of 250,000 take 0.08 s.
    """
    i = np.asarray(i, dtype=np.int64)
    j = np.asarray(j, dtype=np.int64)
    if i.size == 0:
        empty = np.zeros(0, np.int64)
        return Triangles(empty, empty, empty)
    if np.any(i >= j):
        raise ValueError("edges must satisfy i < j")
    key = i * num_nodes + j
    order = np.argsort(key)
    sorted_key = key[order]
    # Forward adjacency (CSR by source node) over edges sorted by (i, j).
    src_sorted = i[order]
    dst_sorted = j[order]
    row_start = np.searchsorted(src_sorted, np.arange(num_nodes + 1))
    out_deg = np.diff(row_start)

    cand_per_edge = out_deg[j]  # neighbours c > b of b, for edge (a, b)
    cum = np.concatenate([[0], np.cumsum(cand_per_edge)])
    parts: list[tuple[IntArray, IntArray, IntArray]] = []
    start_edge = 0
    num_edges = i.size
    while start_edge < num_edges:
        stop_edge = int(np.searchsorted(cum, cum[start_edge] + chunk_pairs, side="right")) - 1
        stop_edge = max(stop_edge, start_edge + 1)
        stop_edge = min(stop_edge, num_edges)
        e = np.arange(start_edge, stop_edge)
        counts = cand_per_edge[e]
        total = int(counts.sum())
        if total:
            e_rep = np.repeat(e, counts)
            offs = np.arange(total) - np.repeat(cum[e] - cum[start_edge], counts)
            pos = row_start[j[e_rep]] + offs  # position in the sorted edge list: edge (b, c)
            a = i[e_rep]
            c = dst_sorted[pos]
            want = a * num_nodes + c
            loc = np.searchsorted(sorted_key, want)
            loc = np.minimum(loc, sorted_key.size - 1)
            hit = sorted_key[loc] == want
            parts.append((e_rep[hit], order[pos[hit]], order[loc[hit]]))
        start_edge = stop_edge
    if not parts:
        empty = np.zeros(0, np.int64)
        return Triangles(empty, empty, empty)
    return Triangles(*(np.concatenate([p[k] for p in parts]) for k in range(3)))
