"""Runs of loop closures, and the least-squares test of a run's common pull.

A run of mutually consistent false closures between two stretches of the trajectory
(perceptual aliasing: the same wrong match, keyframe after keyframe) that a re-solve kept has
bent the solution to fit. Each of its closures is supported by the others, so every test of
one edge passes; the pairwise test over the odometry (:mod:`.closure_consistency`) cannot
reach it where the odometry between it and the true closures is long (its drift excuses the
group). What gives it away is that all its closures pull the same way: each measures
``R_a W R_b^T`` for one wrong ``W``, so each residual, in world coordinates, is about
``log W^T`` less the part the bent solution took up.

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
    scale = w[members] / np.maximum(norm[column], 1e-300)
    laplacian = Factor(L, nodes, n)
    leverage = np.empty(len(runs))
    for lo in range(0, len(runs), _COLUMNS):
        block = (column >= lo) & (column < lo + _COLUMNS)
        y = np.zeros((nodes.size, min(_COLUMNS, len(runs) - lo)))
        for ends, sign in ((i[members], 1.0), (j[members], -1.0)):
            r = row[ends]
            here = block & (r >= 0)
            np.add.at(y, (r[here], column[here] - lo), sign * scale[here])
        leverage[lo:lo + y.shape[1]] = np.einsum("nk,nk->k", y, laplacian.solve(y))
    pull = np.zeros((len(runs), 3))  # s^T U: sum_e sqrt(w_e) u_e / |sqrt(w_S)|
    np.add.at(pull, column, np.sqrt(w[members])[:, None] * u[members])
    pull /= np.maximum(norm, 1e-300)[:, None]
    determined = (norm > 0) & (leverage < 1.0 - 1e-6)
    out[determined] = np.sum(pull[determined] ** 2, axis=1) / (1.0 - leverage[determined])
    return out


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
