"""Runs of loop closures, and the least-squares test of a run's common pull.

A run of mutually consistent false closures between two stretches of the trajectory
(perceptual aliasing: the same wrong match, keyframe after keyframe) that a re-solve kept has
bent the solution to fit. Each of its closures is supported by the others, so every test of
one edge passes; the pairwise test over the odometry (:mod:`.closure_consistency`) cannot
reach it where the odometry between it and the true closures is long (its drift excuses the
group). What gives it away is that all its closures pull the same way: each measures
``R_a W R_b^T`` for one wrong ``W``, so each residual, in world coordinates, is about
``log W^T`` less the part the bent solution took up.

**Leverages remembered.** The fits of one robust re-solve that the test judges differ by a
few edges (City10000's: 0 to 128 of 20,687, once 7,494), and ``h_S`` depends on the fit's
weights only. Within :func:`remembered_run_leverages` each run's ``h_S`` is kept, and the
next fit's follows from it exactly by the Woodbury identity over the edges whose weight
changed (one Laplacian solve with a column per such edge, :class:`RunLeverages`) instead of
one solve per run (City10000's 2,466 runs: ten solves of 256 columns, 3 s a fit).

**Runs.** Loop closures ``e = (a, b)``, ``a < b``, are linked where ``|a_e - a_f|`` and
``|b_e - b_f|`` are both at most ``RUN_GAP`` (closures between the same two stretches,
forward or backward); runs are the linked pieces of at least two closures.

**The test.** In the tangent space of the least-squares fit (:mod:`.gauss_newton`: the normal
matrix is ``B (L kron I_3) B^T``), an edge's whitened residual in world coordinates,
``u_e = sqrt(w_e) R_j^T e_e``, moves by ``sqrt(w_e) (v_i - v_j)``, the same on each axis. A
run's common pull is ``p_S = s^T U_S`` with ``s = sqrt(w_S) / |sqrt(w_S)|``; with noise
``sigma`` per axis the fit leaves it the variance ``sigma^2 (1 - h_S)`` per axis, where
``h_S = y_S^T L^-1 y_S`` and ``y_S = sum_e w_e (1_a - 1_b) / |sqrt(w_S)|`` (``1_a``: the
indicator vector of node ``a``; one Laplacian solve per run). So ``T_S = |p_S|^2 / (1 - h_S)``
is ``sigma^2`` times a chi-square with 3 degrees of freedom for a run of true closures (1
on a planar problem, :data:`~.noise.NOISE_AXES`: the noise turns about one axis); it
is also how much lower the weighted sum of squares would be if the run's common pull were
freed (the deletion of one combined observation). A run far above that (``RUN_QUANTILE``,
over all the fit's runs) is suspect.

Conventions: world-to-node ``R_i``, ``R_ij ~= R_i R_j^T``, node 0 fixed (anchor).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.special import chdtri

from rotavg_ros.core.robust.gauss_newton import Factor, anchored_laplacian, edge_residuals
from rotavg_ros.core.robust.noise import NOISE_AXES
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray

RUN_GAP = 2
"""Closures whose first ends and second ends are both at most this many node ids apart are
in one run (a front end that matches every other keyframe still forms runs)."""

RUN_QUANTILE = 0.999
"""A run is suspect where its ``T_S`` exceeds ``sigma^2`` times the chi-square quantile
(3 degrees of freedom, 1 on a planar problem) at which the noise alone makes any of the
fit's runs suspect with probability ``1 - RUN_QUANTILE`` (Bonferroni: ``1 - (1 -
RUN_QUANTILE) / runs`` per run; 16.3 sigma^2 for one run, 25.5 for parking-garage's 80)."""

_COLUMNS = 256  # runs per block of Laplacian solves


def independent_pieces(i: IntArray, j: IntArray, closures: BoolArray) -> int:
    """How many independent pieces of evidence the ``closures`` edges are: each run
    (:func:`closure_runs`) one, each closure in no run one."""
    runs = closure_runs(i, j, closures)
    return len(runs) + int(np.count_nonzero(closures)) - sum(r.size for r in runs)


def closure_runs(i: IntArray, j: IntArray, closures: BoolArray) -> list[IntArray]:
    """Runs (edge indices) of the ``closures`` edges, at least two each (module docstring)."""
    idx = np.flatnonzero(closures)
    if idx.size < 2:
        return []
    a, b = np.minimum(i[idx], j[idx]), np.maximum(i[idx], j[idx])
    span = int(b.max()) + RUN_GAP + 1
    key = a * span + b  # (a, b) -> one integer, in (a, b) order
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    rows: list[IntArray] = []
    cols: list[IntArray] = []
    for dp in range(-RUN_GAP, RUN_GAP + 1):
        for dq in range(-RUN_GAP, RUN_GAP + 1):
            if (dp, dq) <= (0, 0):
                continue  # each link once, from its smaller end
            at = np.searchsorted(sorted_key, key + dp * span + dq)
            at = np.minimum(at, key.size - 1)
            found = sorted_key[at] == key + dp * span + dq
            rows.append(np.flatnonzero(found))
            cols.append(order[at[found]])
    if not sum(r.size for r in rows):
        return []
    link = coo_matrix((np.ones(sum(r.size for r in rows)),
                       (np.concatenate(rows), np.concatenate(cols))), shape=(idx.size,) * 2)
    label = connected_components(link, directed=False)[1]
    order = np.argsort(label, kind="stable")
    bounds = np.flatnonzero(np.diff(label[order])) + 1
    return [idx[part] for part in np.split(order, bounds) if part.size >= 2]


def run_pull(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    runs: list[IntArray],
) -> FloatArray:
    """Per run, ``T_S`` (module docstring): the squared common pull of the run's residuals
    in the least-squares fit with weights ``w`` (0: not in the fit; ``rot`` is that fit),
    standardized by its own variance; radians^2 of a unit-weight edge. NaN where the rest
    of the fit does not determine the run (leaving it out splits the graph)."""
    out = np.full(len(runs), np.nan)
    n = rot.shape[0]
    fit = w > 0
    L, nodes = anchored_laplacian(n, i[fit], j[fit], w[fit])
    if not nodes.size or not runs:
        return out
    row = np.full(n, -1)
    row[nodes] = np.arange(nodes.size)
    e = edge_residuals(rot, i, j, R)
    u = np.einsum("eba,eb->ea", rot[j], e) * np.sqrt(w)[:, None]  # sqrt(w) R_j^T e
    # y_S = sum_e w_e (1_a - 1_b) / |sqrt(w_S)| (one column per run), L^-1 y_S and
    # h_S = y_S^T L^-1 y_S, a block of runs at a time.
    members = np.concatenate(runs)
    column = np.repeat(np.arange(len(runs)), [r.size for r in runs])
    norm = np.sqrt(np.bincount(column, w[members], len(runs)))
    laplacian = Factor(L, nodes, n)
    memory = REMEMBERED_RUN_LEVERAGES.get()
    if memory is None:
        leverage = _leverages(laplacian, row, i, j, w, runs)
    else:
        leverage = memory.leverages(laplacian, row, i, j, w, runs)
    pull = np.zeros((len(runs), 3))  # s^T U: sum_e sqrt(w_e) u_e / |sqrt(w_S)|
    np.add.at(pull, column, np.sqrt(w[members])[:, None] * u[members])
    pull /= np.maximum(norm, 1e-300)[:, None]
    determined = (norm > 0) & (leverage < 1.0 - 1e-6)
    out[determined] = np.sum(pull[determined] ** 2, axis=1) / (1.0 - leverage[determined])
    return out


def _run_columns(row: IntArray, i: IntArray, j: IntArray, w: FloatArray,
                 runs: list[IntArray]) -> tuple[IntArray, IntArray, FloatArray]:
    """The runs' ``y_S = sum_e w_e (1_a - 1_b) / |sqrt(w_S)|`` as entries ``(rows,
    columns, values)`` of the matrix whose column ``k`` is run ``k``'s (``row``: node ->
    row of the Laplacian, -1 for the anchor's potential 0, whose entries are left out)."""
    members = np.concatenate(runs)
    column = np.repeat(np.arange(len(runs)), [r.size for r in runs])
    norm = np.sqrt(np.bincount(column, w[members], len(runs)))
    scale = w[members] / np.maximum(norm[column], 1e-300)
    rows = np.concatenate([row[i[members]], row[j[members]]])
    columns = np.concatenate([column, column])
    values = np.concatenate([scale, -scale])
    here = rows >= 0
    return rows[here], columns[here], values[here]


def _leverages(laplacian: Factor, row: IntArray, i: IntArray, j: IntArray, w: FloatArray,
               runs: list[IntArray]) -> FloatArray:
    """``h_S = y_S^T L^-1 y_S`` per run, by Laplacian solves, a block of runs at a time."""
    rows, columns, values = _run_columns(row, i, j, w, runs)
    leverage = np.empty(len(runs))
    for lo in range(0, len(runs), _COLUMNS):
        block = (columns >= lo) & (columns < lo + _COLUMNS)
        y = np.zeros((laplacian.nodes.size, min(_COLUMNS, len(runs) - lo)))
        np.add.at(y, (rows[block], columns[block] - lo), values[block])
        leverage[lo:lo + y.shape[1]] = np.einsum("nk,nk->k", y, laplacian.solve(y))
    return leverage


UPDATE_MAX_SHARE = 0.5
""":class:`RunLeverages` updates the remembered runs' leverages where fewer edges changed
weight than this share of those runs (the update's solve has a column per changed edge, the
direct one a column per run)."""

UPDATE_MAX_CONDITION = 1e8
"""Condition number of the Woodbury update's small matrix above which the leverages are
solved for afresh (a change that nearly splits the graph)."""


class RunLeverages:
    """The runs' leverages ``h_S`` of the last fit :func:`run_pull` judged, and their exact
    update to the next fit's (module docstring, "Leverages remembered").

    With ``L1 = L0 + U C U^T`` (``U``: the incidence columns of the edges whose weight
    changed, ``C``: the changes), Woodbury's identity for ``L0 = L1 - U C U^T`` gives
    ``h1 = h0 + g^T N^-1 g`` with ``g = V^T y_S``, ``V = L1^-1 U`` and ``N = U^T V -
    C^-1``: one solve with the new fit's factor, a column per changed edge. A run that is
    new, or whose edges' weights changed, is solved for as before, and so is every run
    where the graph's edges or the Laplacian's free nodes are not the last fit's."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._edges: tuple[IntArray, IntArray] | None = None
        self._weights: FloatArray | None = None
        self._nodes: IntArray | None = None
        self._known: dict[bytes, float] = {}

    @staticmethod
    def _key(run: IntArray, w: FloatArray) -> bytes:
        return run.tobytes() + w[run].tobytes()

    def leverages(self, laplacian: Factor, row: IntArray, i: IntArray, j: IntArray,
                  w: FloatArray, runs: list[IntArray]) -> FloatArray:
        """``h_S`` per run for the fit with weights ``w`` (``laplacian``: its factor)."""
        with self._lock:
            edges, before, nodes, known = self._edges, self._weights, self._nodes, self._known
        keys = [self._key(r, w) for r in runs]
        h = np.full(len(runs), np.nan)
        if (edges is not None and before is not None and nodes is not None
                and np.array_equal(edges[0], i) and np.array_equal(edges[1], j)
                and np.array_equal(nodes, laplacian.nodes)):
            kept = np.array([k for k, key in enumerate(keys) if key in known], np.int64)
            if kept.size:
                old = np.array([known[keys[k]] for k in kept])
                update = self._update(laplacian, row, i, j, w, before,
                                      [runs[k] for k in kept])
                if update is not None:
                    h[kept] = old + update
        todo = np.flatnonzero(np.isnan(h))
        if todo.size:
            h[todo] = _leverages(laplacian, row, i, j, w, [runs[k] for k in todo])
        with self._lock:
            self._edges, self._weights = (i.copy(), j.copy()), w.copy()
            self._nodes = laplacian.nodes.copy()
            self._known = dict(zip(keys, h.tolist(), strict=True))
        return h

    @staticmethod
    def _update(laplacian: Factor, row: IntArray, i: IntArray, j: IntArray, w: FloatArray,
                before: FloatArray, runs: list[IntArray]) -> FloatArray | None:
        """``g^T N^-1 g`` per run (class docstring); None where too many edges changed
        (:data:`UPDATE_MAX_SHARE`) or ``N`` is ill-conditioned."""
        changed = np.flatnonzero(before != w)
        if changed.size == 0:
            return np.zeros(len(runs))
        if changed.size >= UPDATE_MAX_SHARE * len(runs):
            return None
        size = laplacian.nodes.size
        U = np.zeros((size, changed.size))
        cols = np.arange(changed.size)
        for ends, sign in ((i[changed], 1.0), (j[changed], -1.0)):
            r = row[ends]
            np.add.at(U, (r[r >= 0], cols[r >= 0]), sign)
        V = laplacian.solve(U)
        padded = np.vstack([V, np.zeros((1, changed.size))])  # [-1]: the anchor's 0
        N = (padded[row[i[changed]]] - padded[row[j[changed]]]  # U^T V, row by row
             - np.diag(1.0 / (w[changed] - before[changed])))
        N = 0.5 * (N + N.T)
        if not np.linalg.cond(N) < UPDATE_MAX_CONDITION:
            return None
        rows, columns, values = _run_columns(row, i, j, w, runs)
        Y = coo_matrix((values, (columns, rows)), shape=(len(runs), size)).tocsr()
        G = np.asarray(Y @ V)  # g_S = V^T y_S, one row per run
        return np.asarray(np.einsum("rk,kr->r", G, np.linalg.solve(N, G.T)))


REMEMBERED_RUN_LEVERAGES: ContextVar[RunLeverages | None] = ContextVar(
    "REMEMBERED_RUN_LEVERAGES", default=None)
"""The current re-solve's :class:`RunLeverages` (see :func:`remembered_run_leverages`)."""


@contextmanager
def remembered_run_leverages() -> Iterator[None]:
    """Within this block, :func:`run_pull` keeps its runs' leverages and updates them to
    the next fit's (:class:`RunLeverages`)."""
    token = REMEMBERED_RUN_LEVERAGES.set(RunLeverages())
    try:
        yield
    finally:
        REMEMBERED_RUN_LEVERAGES.reset(token)


def suspect_runs(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    fit: BoolArray, closures: BoolArray, sigma: float,
) -> list[IntArray]:
    """Runs of the ``closures`` edges in the least-squares fit ``rot`` on ``fit`` whose
    ``T_S`` exceeds the limit of ``RUN_QUANTILE`` (``sigma``: noise per axis of a
    unit-weight edge, radians), the most suspect first."""
    runs = closure_runs(i, j, closures & fit)
    if not runs or not sigma > 0.0:
        return []
    limit = sigma * sigma * chdtri(NOISE_AXES.get(), (1.0 - RUN_QUANTILE) / len(runs))
    excess = run_pull(rot, i, j, R, w * fit, runs) / limit
    order = np.argsort(-np.nan_to_num(excess, nan=0.0), kind="stable")
    return [runs[k] for k in order if excess[k] > 1.0]
