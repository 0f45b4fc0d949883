"""Weighted geodesic least squares on SO(3) by Gauss-Newton, and the edge residuals.

Conventions: ``R_i`` world-to-node, edge ``(i, j, R_ij)`` with ``R_ij ~= R_i R_j^T``. The
residual of an edge is the rotation vector ``e_ij = log(R_ij^T R_i R_j^T)``; its norm is the
angle between the measurement and the prediction. An update perturbs each rotation on the
left, ``R_i <- exp(d_i) R_i``, so ``e_ij ~= e_ij + R_j R_i^T d_i - d_j`` to first order (the
right Jacobian of the log is taken as identity: exact at zero residual, and the weights of a
robust loss make large residuals irrelevant). Node 0 (the anchor) stays fixed.

One step solves the 3N x 3N normal equations ``sum_e w_e A_e^T A_e d = -sum_e w_e A_e^T e``
(sparse, SPD once the anchor is fixed) with the solver :class:`Factor` picks for the graph:
dense Cholesky, Jacobi-preconditioned conjugate gradients or SuperLU.
"""

from __future__ import annotations

from collections.abc import Callable
from contextvars import ContextVar
from typing import Any

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.linalg import LinearOperator, cg, splu

from rotavg_ros.core.so3 import exp_map, log_map, project_to_so3
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray


def edge_residuals(rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray) -> FloatArray:
    """``(E, 3)`` rotation vectors ``log(R_ij^T R_i R_j^T)``."""
    return log_map(np.swapaxes(R, 1, 2) @ rot[i] @ np.swapaxes(rot[j], 1, 2))


def residual_angles(rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray) -> FloatArray:
    """``(E,)`` angles (radians) between each measurement and its prediction."""
    return np.linalg.norm(edge_residuals(rot, i, j, R), axis=-1)


def _assemble(rot: FloatArray, i: IntArray, j: IntArray, w: FloatArray
              ) -> tuple[Any, FloatArray, IntArray]:
    """``(H on the free coordinates (CSC), P^T per edge, free coordinates)``.

    ``H = sum_e w_e A_e^T A_e`` with ``A_e = [P_e^T at i, -I at j]``, ``P_e = R_i R_j^T``;
    the anchor (node 0) and nodes no weighted edge reaches are not free.
    """
    n = rot.shape[0]
    Pt = rot[j] @ np.swapaxes(rot[i], 1, 2)  # P^T = R_j R_i^T
    deg = np.bincount(i, w, n) + np.bincount(j, w, n)
    reached = deg > 0
    reached[0] = False  # the anchor is fixed
    free = np.flatnonzero(np.repeat(reached, 3))
    index = np.full(n, -1)  # node -> its first free coordinate
    index[reached] = 3 * np.arange(int(reached.sum()))
    # H_ii += w I, H_jj += w I (+ 1e-12 I: no exactly singular matrix), H_ij += -w P,
    # H_ji += -w P^T, for the blocks between free nodes.
    both = (index[i] >= 0) & (index[j] >= 0)
    a = np.arange(3)
    rr = np.broadcast_to(index[i][both][:, None, None] + a[None, :, None], (both.sum(), 3, 3))
    cc = np.broadcast_to(index[j][both][:, None, None] + a[None, None, :], (both.sum(), 3, 3))
    off = -w[both][:, None, None] * np.swapaxes(Pt[both], 1, 2)  # -w P at (i, j)
    diag = np.arange(free.size)
    rows = np.concatenate([diag, rr.ravel(), cc.ravel()])
    cols = np.concatenate([diag, cc.ravel(), rr.ravel()])
    # The (j, i) block is the transpose of the (i, j) block: same values, swapped indices.
    vals = np.concatenate([np.repeat(deg[reached], 3) + 1e-12, off.ravel(), off.ravel()])
    Hf = coo_matrix((vals, (rows, cols)), shape=(free.size, free.size)).tocsc()
    return Hf, Pt, free


def scatter_add(index: IntArray, values: FloatArray, n: int) -> FloatArray:
    """``out[k] = sum of values[e] over the e with index[e] == k`` for k < n (``np.add.at``,
    as one sparse product: several times faster)."""
    flat = values.reshape(index.size, -1)
    S = csr_matrix((np.ones(index.size), (index, np.arange(index.size))),
                   shape=(n, index.size))
    return np.asarray(S @ flat).reshape((n, *values.shape[1:]))


class Factor:
    """A solver for the normal matrix on the free coordinates ``free``: dense Cholesky for
    small or dense systems, conjugate gradients for large well-connected ones, SuperLU
    (symmetric mode) otherwise."""

    def __init__(self, Hf: Any, free: IntArray) -> None:
        self.free = free
        self._dense = None
        self._lu = None
        self._matrix: Any = None  # conjugate gradients on this matrix
        size = free.size
        if size <= DENSE_MAX and (Hf.nnz > DENSE_FILL * size ** 2 or size <= DENSE_ALWAYS):
            self._dense = cho_factor(Hf.toarray(), lower=True, check_finite=False)
        elif (WELL_CONNECTED.get()
              or Hf.nnz / size - 3.0 >= 3.0 * ITERATIVE_MIN_DEGREE):  # 3 entries per neighbour
            self._matrix = Hf
            self._inverse_diagonal = 1.0 / Hf.diagonal()
        else:
            self._factor_sparse(Hf)

    def _factor_sparse(self, Hf: Any) -> None:
        self._lu = splu(Hf, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                        options={"SymmetricMode": True})
        self._matrix = None

    @property
    def sparse(self) -> bool:
        """Whether this is a sparse factorization (worth reusing as a preconditioner)."""
        return self._lu is not None

    def solve(self, b: FloatArray) -> FloatArray:
        """``H^-1 b`` for a vector or the columns of a matrix ``b``."""
        if self._dense is not None:
            return np.asarray(cho_solve(self._dense, b, check_finite=False))
        if self._matrix is not None:
            x = jacobi_pcg(self._matrix, b, self._inverse_diagonal, PCG_TOLERANCE,
                           PCG_MAX_ITERATIONS)
            if x is not None:
                return x
            self._factor_sparse(self._matrix)  # did not converge: factor after all
        assert self._lu is not None
        return np.asarray(self._lu.solve(b))


DENSE_MAX = 3000
"""Free coordinates up to which a normal matrix with more than ``DENSE_FILL`` of its entries
set is solved densely (Cholesky, 72 MB at most): random view graphs fill SuperLU's factors
almost completely (1,000 nodes, 20,000 edges: 0.95 s per SuperLU factorization, 0.13 s
dense), while chains and pose graphs stay sparse (a 300-keyframe chain: 50 ms dense, about
1 ms sparse)."""
DENSE_FILL = 0.02
DENSE_ALWAYS = 300
"""Free coordinates up to which every normal matrix is solved densely (a few ms)."""
ITERATIVE_MIN_DEGREE = 10.0
"""Above ``DENSE_MAX``: mean number of weighted edges per node from which the normal matrix
is solved by Jacobi-preconditioned conjugate gradients instead of SuperLU. A graph this
well connected (an SfM view graph; the solver's dense-mode threshold) fills SuperLU's
factors (2,000 nodes, 20,000 edges: 4.3 s per factorization) but is well conditioned:
CG converges in a few dozen products with the sparse matrix. Chains and pose graphs
(degree 2-5) are the other way round. A CG that does not converge falls back to SuperLU."""
WELL_CONNECTED: ContextVar[bool] = ContextVar("WELL_CONNECTED", default=False)
"""Set (by :func:`~rotavg_ros.core.robust.verify.verify`) while the input graph has at
least ``ITERATIVE_MIN_DEGREE`` edges per node: then every large normal matrix is solved by
conjugate gradients first, also where GNC's zero weights leave fewer active edges. Those
matrices are still expander-like, and SuperLU fills them in: a 5,000-node graph of mean
degree 18 spent 81 s in 7 factorizations (11.6 s each) where CG converges in at most 200
iterations."""
PCG_MAX_ITERATIONS = 300
"""Conjugate-gradient iterations of :func:`jacobi_pcg` before the solve falls back to
SuperLU (2,000 nodes at mean degree 20 need 25-30)."""
PCG_TOLERANCE = 1e-6
"""Relative residual at which :func:`jacobi_pcg` stops (per column)."""


def jacobi_pcg(A: Any, b: FloatArray, inverse_diagonal: FloatArray, rtol: float,
               maxiter: int) -> FloatArray | None:
    """Conjugate gradients for ``A x = b`` (``A`` sparse SPD) preconditioned by ``A``'s
    diagonal, on every column of ``b`` at once (each column its own step sizes). None when
    some column has not converged after ``maxiter`` iterations.

    (The diagonal blocks of a normal matrix here are multiples of the identity, ``sum w I``,
    so this is also the block-Jacobi preconditioner.)
    """
    B = b.reshape(b.shape[0], -1)
    scale = np.linalg.norm(B, axis=0)
    x = np.zeros_like(B)
    r = B.copy()
    z = inverse_diagonal[:, None] * r
    p = z.copy()
    rz = np.einsum("ik,ik->k", r, z)
    for _ in range(maxiter):
        if np.all(np.linalg.norm(r, axis=0) <= rtol * scale):
            return x.reshape(b.shape)
        Ap = A @ p
        pAp = np.einsum("ik,ik->k", p, Ap)
        alpha = np.divide(rz, pAp, out=np.zeros_like(rz), where=pAp > 0)
        x += alpha * p
        r -= alpha * Ap
        z = inverse_diagonal[:, None] * r
        rz_new = np.einsum("ik,ik->k", r, z)
        beta = np.divide(rz_new, rz, out=np.zeros_like(rz), where=rz > 0)
        p = z + beta * p
        rz = rz_new
    return x.reshape(b.shape) if np.all(np.linalg.norm(r, axis=0) <= rtol * scale) else None


def _normal_matrix(rot: FloatArray, i: IntArray, j: IntArray, w: FloatArray
                   ) -> tuple[Factor | None, FloatArray, IntArray]:
    """``(factor of H on the free coordinates, P^T per edge, free coordinates)``."""
    Hf, Pt, free = _assemble(rot, i, j, w)
    return (Factor(Hf, free) if free.size else None), Pt, free


def gauss_newton_step(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    precondition: Factor | None = None,
) -> tuple[FloatArray, Factor | None]:
    """One Gauss-Newton step of ``min sum_e w_e |e_e|^2``: the new rotations and the factor
    of the normal matrix it used.

    With ``precondition`` (the factor of an earlier, similar step, e.g. the previous
    iteration's) the step is solved by conjugate gradients preconditioned with it, which
    costs a few triangular solves instead of a factorization; if that does not converge
    (the matrix moved too far), the step factors afresh. Edges with ``w_e = 0`` take no
    part; nodes no weighted edge reaches keep their rotation.
    """
    n = rot.shape[0]
    active = w > 0
    i, j, R, w = i[active], j[active], R[active], w[active]
    if n < 2 or i.size == 0:
        return rot.copy(), None
    e = edge_residuals(rot, i, j, R)
    Hf, Pt, free = _assemble(rot, i, j, w)
    if free.size == 0:
        return rot.copy(), None
    # Gradient: b_i += w P e, b_j -= w e.
    Pe = (e[:, None, :] @ Pt)[:, 0, :]  # P e = (P^T)^T e
    b = scatter_add(i, w[:, None] * Pe, n) - scatter_add(j, w[:, None] * e, n)
    rhs = -b.reshape(-1)[free]
    x = None
    factor = precondition
    # A dense factor is cheap to redo and expensive to apply n times: CG only with SuperLU.
    if factor is not None and factor.sparse and np.array_equal(factor.free, free):
        M = LinearOperator(Hf.shape, matvec=factor.solve, dtype=np.float64)
        x, info = cg(Hf, rhs, rtol=1e-8, atol=0.0, maxiter=CG_MAX_ITERATIONS, M=M)
        if info != 0:
            x = None
    if x is None:
        factor = Factor(Hf, free)
        x = factor.solve(rhs)
    d = np.zeros(3 * n)
    d[free] = x
    step = exp_map(d.reshape(n, 3))
    return project_to_so3(step @ rot), factor


CG_MAX_ITERATIONS = 30
"""Preconditioned conjugate-gradient iterations before a step factors afresh."""


def prediction_variance(
    rot: FloatArray, i: IntArray, j: IntArray, w: FloatArray, probes: int = 32,
    seed: int = 0, exact: BoolArray | Callable[[FloatArray], BoolArray] | None = None,
) -> FloatArray:
    """Per edge, ``q_e = tr(A_e H^-1 A_e^T) / 3`` for the least-squares fit with weights
    ``w`` (``w_e = 0``: not in the fit), estimated with random probes.

    In units of the noise variance of a unit-weight edge: an edge in the fit has leverage
    ``w_e q_e`` (its residual variance shrinks by ``1 - w_e q_e``), an edge outside it is
    predicted with variance ``1 / w_e + q_e``. Probes ``z = H^-1 A^T W^(1/2) g`` with
    ``g ~ N(0, I)`` have covariance ``H^-1``, so ``E |A_e z|^2 = tr(A_e H^-1 A_e^T)``
    (about 15% relative error with 32 probes). Edges marked in ``exact`` get ``q_e`` from
    three solves each instead (needed where the leverage is close to 1); ``exact`` may be a
    function of the probe estimates that returns the mask (one factorization serves both).
    """
    n = rot.shape[0]
    q = np.zeros(i.size)
    active = w > 0
    if n < 2 or not active.any():
        return q
    ai, aj, aw = i[active], j[active], w[active]
    lu, Pt_active, free = _normal_matrix(rot, ai, aj, aw)
    if lu is None:
        return q
    rng = np.random.default_rng(seed)
    g = rng.standard_normal((ai.size, 3, probes)) * np.sqrt(aw)[:, None, None]
    b = scatter_add(ai, np.swapaxes(Pt_active, 1, 2) @ g, n) - scatter_add(aj, g, n)  # P g
    z = np.zeros((3 * n, probes))
    z[free] = lu.solve(np.ascontiguousarray(b.reshape(3 * n, probes)[free]))
    z3 = z.reshape(n, 3, probes)
    Pt = rot[j] @ np.swapaxes(rot[i], 1, 2)
    Az = Pt @ z3[i] - z3[j]
    q = np.mean(np.sum(Az * Az, axis=1), axis=1) / 3.0
    if callable(exact):
        exact = exact(q)
    if exact is not None and exact.any():
        q[exact] = _exact_prediction_variance(lu, free, n, Pt[exact], i[exact], j[exact])
    return q


def _exact_prediction_variance(lu: Any, free: IntArray, n: int, Pt: FloatArray,
                               i: IntArray, j: IntArray, batch: int = 32) -> FloatArray:
    """``tr(A_e H^-1 A_e^T) / 3`` by solving ``H X = A_e^T`` for each edge's 3 columns."""
    out = np.empty(i.size)
    index = np.full(3 * n, -1)
    index[free] = np.arange(free.size)
    for lo in range(0, i.size, batch):
        sl = slice(lo, min(lo + batch, i.size))
        m = sl.stop - lo
        rhs = np.zeros((free.size, 3 * m))
        for a in range(3):
            for b in range(3):  # column 3k+b of A_e^T: P[:, b] at node i, -e_b at node j
                ri = index[3 * i[sl] + a]
                ok = ri >= 0
                rhs[ri[ok], (3 * np.arange(m) + b)[ok]] += Pt[sl][ok, b, a]
            rj = index[3 * j[sl] + a]
            ok = rj >= 0
            rhs[rj[ok], (3 * np.arange(m) + a)[ok]] -= 1.0
        x = lu.solve(rhs)
        # A_e x = P^T x_i - x_j, for the three columns; trace over the 3 x 3 result.
        xi = np.zeros((m, 3, 3))
        xj = np.zeros((m, 3, 3))
        for a in range(3):
            ri = index[3 * i[sl] + a]
            rj = index[3 * j[sl] + a]
            cols = 3 * np.arange(m)[:, None] + np.arange(3)[None, :]
            xi[:, a, :] = np.where((ri >= 0)[:, None], x[np.maximum(ri, 0)[:, None], cols], 0.0)
            xj[:, a, :] = np.where((rj >= 0)[:, None], x[np.maximum(rj, 0)[:, None], cols], 0.0)
        Ax = Pt[sl] @ xi - xj
        out[sl] = np.trace(Ax, axis1=1, axis2=2) / 3.0
    return out


def refine_least_squares(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    iterations: int = 10, tolerance: float = 1e-5,
) -> FloatArray:
    """Gauss-Newton iterations of weighted geodesic least squares from ``rot``.

    Stops when the largest update is below ``tolerance`` radians.
    """
    factor: Factor | None = None
    for _ in range(iterations):
        new, factor = gauss_newton_step(rot, i, j, R, w, factor)
        moved = np.linalg.norm(log_map(new @ np.swapaxes(rot, 1, 2)), axis=-1)
        rot = new
        if moved.size == 0 or float(moved.max()) < tolerance:
            break
    return rot
