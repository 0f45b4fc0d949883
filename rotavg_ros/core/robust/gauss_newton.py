"""Weighted geodesic least squares on SO(3) by Gauss-Newton, and the edge residuals.

Conventions: ``R_i`` world-to-node, edge ``(i, j, R_ij)`` with ``R_ij ~= R_i R_j^T``. The
residual of an edge is the rotation vector ``e_ij = log(R_ij^T R_i R_j^T)``; its norm is the
angle between the measurement and the prediction. An update perturbs each rotation on the
left, ``R_i <- exp(d_i) R_i``, so ``e_ij ~= e_ij + R_j R_i^T d_i - d_j`` to first order (the
right Jacobian of the log is taken as identity: exact at zero residual, and the weights of a
robust loss make large residuals irrelevant). Node 0 (the anchor) stays fixed.

One step solves the 3N x 3N normal equations ``sum_e w_e A_e^T A_e d = -sum_e w_e A_e^T e``
(SPD once the anchor is fixed). With ``A_e = [R_j R_i^T at i, -I at j]`` and the change of
variables ``d_i = R_i v_i``, ``A_e d = R_j (v_i - v_j)``: the normal matrix is exactly
``B (L kron I_3) B^T`` with ``B = blockdiag(R_i)`` and ``L`` the weighted graph Laplacian
(N x N, scalar). So every solve is a solve with ``L`` on three right-hand sides per column,
rotated in and out (:class:`Factor`), and ``L`` depends on the weights only: steps with the
same weights share one factorization. ``L`` is solved by dense Cholesky, Jacobi-preconditioned
conjugate gradients or SuperLU, by size and connectivity.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any

import numpy as np
from scipy.linalg import cho_factor, cho_solve, lapack
from scipy.sparse import coo_matrix, csc_matrix, csr_matrix

from rotavg_ros.core import so3_soa as soa
from rotavg_ros.core.sparse_factor import factor_fills_heavily, factor_spd, solve_by_blocks
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray


def edge_residuals(rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray) -> FloatArray:
    """``(E, 3)`` rotation vectors ``log(R_ij^T R_i R_j^T)``."""
    return np.ascontiguousarray(_residuals(soa.to_soa(rot), i, j, soa.to_soa(R)).T)


def _residuals(rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray) -> FloatArray:
    """:func:`edge_residuals` in the ``(3, 3, n)`` layout of :mod:`~rotavg_ros.core.so3_soa`
    (``rot`` and ``R``), as ``(3, E)``."""
    predicted = soa.matmul(np.take(rot, i, axis=2), np.take(rot, j, axis=2), transpose_b=True)
    return soa.log(soa.matmul(R, predicted, transpose_a=True))


def residual_angles(rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray) -> FloatArray:
    """``(E,)`` angles (radians) between each measurement and its prediction."""
    return np.linalg.norm(edge_residuals(rot, i, j, R), axis=-1)


def _anchored_edges(n: int, i: IntArray, j: IntArray, w: FloatArray,
                    ) -> tuple[FloatArray, IntArray, IntArray, IntArray, FloatArray]:
    """``(weighted degrees (n,), free nodes, a, b, weights)``: the free nodes are those a
    weighted edge reaches, but the anchor (node 0); ``a``, ``b`` are the rows (positions
    in the free nodes) of the edges between two free nodes, with their weights."""
    deg: FloatArray = (np.bincount(i, w, n) + np.bincount(j, w, n)).astype(np.float64, copy=False)
    reached = deg > 0
    reached[0] = False  # the anchor is fixed
    nodes: IntArray = np.flatnonzero(reached).astype(np.int64, copy=False)
    index = np.full(n, -1, dtype=np.int64)
    index[nodes] = np.arange(nodes.size)
    both = (index[i] >= 0) & (index[j] >= 0)
    a: IntArray = index[i][both]
    b: IntArray = index[j][both]
    return deg, nodes, a, b, w[both]


def _sparse_laplacian(deg: FloatArray, nodes: IntArray, a: IntArray, b: IntArray,
                      w: FloatArray) -> Any:
    """The Laplacian on the free nodes (CSC) from :func:`_anchored_edges`' pieces."""
    diag = np.arange(nodes.size)
    return coo_matrix((np.concatenate([deg[nodes] + 1e-12, -w, -w]),
                       (np.concatenate([diag, a, b]), np.concatenate([diag, b, a]))),
                      shape=(nodes.size, nodes.size)).tocsc()


def anchored_laplacian(n: int, i: IntArray, j: IntArray, w: FloatArray,
                       ) -> tuple[Any, IntArray]:
    """``(L on the free nodes (CSC), free nodes)``: the weighted graph Laplacian, without
    the anchor (node 0) and the nodes no weighted edge reaches (+ 1e-12 on the diagonal: no
    exactly singular matrix)."""
    deg, nodes, a, b, wb = _anchored_edges(n, i, j, w)
    return _sparse_laplacian(deg, nodes, a, b, wb), nodes


def laplacian_factor(n: int, i: IntArray, j: IntArray, w: FloatArray) -> Factor | None:
    """:class:`Factor` of :func:`anchored_laplacian` (None: no free node). Where it will be
    factored densely, the dense matrix is summed directly (``np.bincount``) instead of
    through a sparse matrix: on a 125-node pose graph that assembly was a third of each
    Gauss-Newton step (the same matrix up to the order in which parallel edges add up)."""
    deg, nodes, a, b, wb = _anchored_edges(n, i, j, w)
    size = nodes.size
    if size == 0:
        return None
    if size <= DENSE_MAX:
        # Stored entries of the sparse Laplacian: the diagonal and each node pair both ways.
        off = a != b
        pairs = np.unique(np.minimum(a[off], b[off]) * size + np.maximum(a[off], b[off])).size
        if _factor_densely(size, size + 2 * pairs):
            L: FloatArray = np.bincount(
                np.concatenate([a * size + b, b * size + a]), np.concatenate([-wb, -wb]),
                size * size).astype(np.float64, copy=False).reshape(size, size)
            L[np.arange(size), np.arange(size)] += deg[nodes] + 1e-12
            return Factor.from_dense(L, nodes)
    order = ELIMINATION_ORDER.get()
    if order is not None and order.num_nodes == n and not WELL_CONNECTED.get():
        # In the graph's order from a remembered structure: only the values are summed
        # (the sparse matrix's assembly and permutation cost as much as a pose graph's
        # factorization). The same matrix, so the same factor. (A well-connected graph's
        # Laplacians go to conjugate gradients unpermuted: no structure is built for them.)
        pattern = order.pattern(nodes, a, b)
        if not _solves_iteratively(size, pattern.nnz, _route_for(n)):
            return Factor.from_ordered(pattern.matrix(deg[nodes] + 1e-12, wb), pattern.perm,
                                       nodes, n, order.supernodes)
    return Factor(_sparse_laplacian(deg, nodes, a, b, wb), nodes, n)


class LaplacianPattern:
    """The sparse structure of the Laplacian of one set of edges (:func:`_anchored_edges`'
    free nodes and rows ``a``, ``b``) in its graph's :class:`EliminationOrder`: the matrix
    ``L[perm][:, perm]`` (CSC, sorted rows, parallel edges summed into one entry) is
    ``matrix(diagonal, weights)`` for any values, by one ``np.bincount``."""

    def __init__(self, rank: IntArray, nodes: IntArray, a: IntArray, b: IntArray) -> None:
        size = nodes.size
        self.size = size
        self.perm: IntArray = np.argsort(rank[nodes], kind="stable")
        """The free nodes' rows in the order: row ``k`` of the matrix is ``perm[k]``'s."""
        position = np.empty(size, np.int64)
        position[self.perm] = np.arange(size)
        diag = np.arange(size)
        rows = position[np.concatenate([diag, a, b])]
        cols = position[np.concatenate([diag, b, a])]
        entries, slot = np.unique(cols * size + rows, return_inverse=True)
        self._slot: IntArray = slot.reshape(-1)  # each diagonal and edge entry's place
        self.nnz = int(entries.size)
        self._indices = (entries % size).astype(np.int32)
        self._indptr = np.searchsorted(entries // size, np.arange(size + 1)).astype(np.int32)

    def matrix(self, diagonal: FloatArray, w: FloatArray) -> Any:
        """The ordered matrix with ``diagonal`` (per free node) and ``-w`` per edge."""
        data = np.bincount(self._slot, np.concatenate([diagonal, -w, -w]), self.nnz)
        return csc_matrix((data, self._indices, self._indptr), shape=(self.size, self.size))


class EliminationOrder:
    """One fill-reducing order of a graph's nodes, for every sparse factorization of the
    Laplacians of its edges at any weights (Gauss-Newton, GNC, leverages): SuperLU's
    minimum-degree ordering of the Laplacian with every edge at weight 1, computed once
    when first needed. Zero weights (GNC's outliers) and unreached nodes leave a subgraph,
    whose fill under the induced order is a subset of the whole graph's; the ordering
    itself was 15-40% of each factorization of a SLAM graph (sphere2500, parking-garage,
    torus3D). Set it with :func:`shared_elimination_order`.

    The same first factorization tells whether the graph's factors fill in heavily (a 3D
    lattice's: :func:`~rotavg_ros.core.sparse_factor.factor_fills_heavily`); then every
    factorization in this order takes SuperLU's supernode settings (1.6x faster on a
    22^3 lattice's Laplacian; a subgraph fills in less, never more)."""

    def __init__(self, num_nodes: int, i: IntArray, j: IntArray) -> None:
        self.num_nodes = num_nodes
        self._edges = (i, j)
        self._rank: IntArray | None = None
        self._supernodes = False
        self._lock = threading.Lock()  # the verification's threads share one order
        self._patterns: OrderedDict[bytes, LaplacianPattern] = OrderedDict()

    def is_of(self, num_nodes: int, i: IntArray, j: IntArray) -> bool:
        """Whether this is the order of the graph ``(i, j)`` on ``num_nodes`` nodes."""
        mine_i, mine_j = self._edges
        return (num_nodes == self.num_nodes and np.array_equal(i, mine_i)
                and np.array_equal(j, mine_j))

    def pattern(self, nodes: IntArray, a: IntArray, b: IntArray) -> LaplacianPattern:
        """The :class:`LaplacianPattern` of these free nodes and edge rows, remembered for
        the last :data:`PATTERNS_KEPT` sets of edges (the fits of one fold, one GNC stage
        or one IRLS run keep their edges from step to step)."""
        key = b"".join((np.int64(nodes.size).tobytes(), nodes.tobytes(), a.tobytes(),
                        b.tobytes()))
        with self._lock:
            found = self._patterns.get(key)
            if found is not None:
                self._patterns.move_to_end(key)
                return found
        made = LaplacianPattern(self.rank, nodes, a, b)
        with self._lock:
            self._patterns[key] = made
            while len(self._patterns) > PATTERNS_KEPT:
                self._patterns.popitem(last=False)
        return made

    @property
    def rank(self) -> IntArray:
        """``rank[node]``: the node's position in the order (the anchor's is arbitrary)."""
        with self._lock:
            return self._order_once()[0]

    @property
    def supernodes(self) -> bool:
        """Whether factorizations in this order take SuperLU's supernode settings."""
        with self._lock:
            return self._order_once()[1]

    def _order_once(self) -> tuple[IntArray, bool]:
        if self._rank is None:
            i, j = self._edges
            n = self.num_nodes
            keep = (i != j) & (i < n) & (j < n)
            L, nodes = anchored_laplacian(n, i[keep], j[keep],
                                          np.ones(int(keep.sum())))
            rank = np.zeros(n, np.int64)
            if nodes.size:
                lu = factor_spd(L)
                # perm_c[k] is the position of column k: rank the free nodes by it
                rank[nodes] = lu.perm_c + 1
                self._supernodes = factor_fills_heavily(lu, nodes.size)
            self._rank = rank
        return self._rank, self._supernodes


ELIMINATION_ORDER: ContextVar[EliminationOrder | None] = ContextVar(
    "ELIMINATION_ORDER", default=None)
"""The current graph's :class:`EliminationOrder` (see :func:`shared_elimination_order`)."""


class ConjugateGradientRoute:
    """Whether the large Laplacians of one graph (``num_nodes`` nodes, at any weights) are
    still solved by conjugate gradients first (:data:`WELL_CONNECTED`,
    ``ITERATIVE_MIN_DEGREE``): not once CG has failed on more of them than it converged
    on. Many edges per node do not make a graph well conditioned: a long trajectory
    revisited often (the Manhattan world's 10,000 poses at mean degree 12.9) has
    Laplacians on which Jacobi CG does not converge in ``PCG_MAX_ITERATIONS`` (3 s for 64
    columns), while their factors are sparse (31 entries a column, 26 ms). Set it with
    :func:`remembered_cg_failures`."""

    def __init__(self, num_nodes: int) -> None:
        self.num_nodes = num_nodes
        self.converged = 0
        """Laplacians of the graph on which CG converged."""
        self.not_converged = 0
        """... and on which it did not (then factored after all)."""

    @property
    def failed(self) -> bool:
        """Whether CG failed more often than it converged on the graph's Laplacians: then it
        is no longer tried (a view graph whose CG converges but for a rare ill-conditioned
        weighting keeps it). (Plain counters: the verification's threads only add to
        them, and a count lost to a race changes which solver runs, never a result's
        accuracy.)"""
        return self.not_converged > self.converged


CG_ROUTE: ContextVar[ConjugateGradientRoute | None] = ContextVar("CG_ROUTE", default=None)
"""The current graph's :class:`ConjugateGradientRoute` (see :func:`remembered_cg_failures`)."""


@contextmanager
def remembered_cg_failures(num_nodes: int) -> Iterator[None]:
    """Within this block, CG's failures on the Laplacians of a graph on ``num_nodes`` nodes
    (:class:`Factor` given ``num_nodes``), once more than its successes, send every later
    one straight to the sparse factorization. Where a route for that graph is set already
    (the solver's, around the verification's own), that one stands: the counts hold for
    the whole solve."""
    current = CG_ROUTE.get()
    if current is not None and current.num_nodes == num_nodes:
        yield
        return
    token = CG_ROUTE.set(ConjugateGradientRoute(num_nodes))
    try:
        yield
    finally:
        CG_ROUTE.reset(token)


@contextmanager
def shared_elimination_order(num_nodes: int, i: IntArray, j: IntArray) -> Iterator[None]:
    """Within this block, every sparse factorization of a Laplacian on ``num_nodes`` nodes
    (:class:`Factor` given ``num_nodes``) uses one fill-reducing order of the graph
    ``(i, j)``, computed at the first, instead of ordering each matrix afresh. Where the
    current order is that of the same graph already (the solver's, around the
    verification's own), that one stands, with the structures it remembers."""
    current = ELIMINATION_ORDER.get()
    if current is not None and current.is_of(num_nodes, i, j):
        yield
        return
    token = ELIMINATION_ORDER.set(EliminationOrder(num_nodes, i, j))
    try:
        yield
    finally:
        ELIMINATION_ORDER.reset(token)


BINCOUNT_MAX_COLUMNS = 8
""":func:`scatter_add` sums up to this many columns with one ``np.bincount`` each (a
Gauss-Newton step's three: 7-9x faster than building the sparse incidence matrix, from 125
nodes to 100,000 edges, and the same sums in the same order); more (the leverage probes'
96) with one sparse product."""


def scatter_add(index: IntArray, values: FloatArray, n: int) -> FloatArray:
    """``out[k] = sum of values[e] over the e with index[e] == k`` for k < n (``np.add.at``,
    much faster)."""
    flat = values.reshape(index.size, -1)
    if flat.shape[1] <= BINCOUNT_MAX_COLUMNS:
        out = np.empty((n, flat.shape[1]))
        for c in range(flat.shape[1]):
            out[:, c] = np.bincount(index, flat[:, c], minlength=n)[:n]
    else:
        S = csr_matrix((np.ones(index.size), (index, np.arange(index.size))),
                       shape=(n, index.size))
        out = np.asarray(S @ flat)
    return out.reshape((n, *values.shape[1:]))


class Factor:
    """A solver for the graph Laplacian ``L`` on the free nodes ``nodes``: dense Cholesky
    for small or dense graphs, conjugate gradients for large well-connected ones, SuperLU
    (symmetric mode) otherwise, in the current graph's :class:`EliminationOrder` where one
    is set for ``num_nodes`` nodes."""

    def __init__(self, L: Any, nodes: IntArray, num_nodes: int | None = None) -> None:
        self.nodes = nodes
        self._num_nodes = num_nodes
        self._perm: IntArray | None = None  # SuperLU's rows: L's rows self._perm
        self._dense = None
        self._lu = None
        self._matrix: Any = None  # conjugate gradients on this matrix
        size = nodes.size
        self._route = _route_for(num_nodes)
        if _factor_densely(size, L.nnz):
            self._dense = cho_factor(L.toarray(), lower=True, check_finite=False)
        elif _solves_iteratively(size, L.nnz, self._route):
            self._matrix = L
            self._inverse_diagonal = 1.0 / L.diagonal()
        else:
            self._factor_sparse(L)

    def _factor_sparse(self, L: Any) -> None:
        order = ELIMINATION_ORDER.get()
        supernodes = False
        if order is not None and order.num_nodes == self._num_nodes:
            self._perm = np.argsort(order.rank[self.nodes], kind="stable")
            L = L[self._perm][:, self._perm].tocsc()
            supernodes = order.supernodes
        self._lu = factor_spd(L, ordered=self._perm is not None, supernodes=supernodes)
        self._matrix = None

    @classmethod
    def _unset(cls, nodes: IntArray, num_nodes: int | None) -> Factor:
        """A factor on the free ``nodes`` with no solver set yet (for the constructors)."""
        factor = cls.__new__(cls)
        factor.nodes = nodes
        factor._num_nodes = num_nodes
        factor._perm = None
        factor._dense = None
        factor._lu = None
        factor._matrix = None
        factor._route = _route_for(num_nodes)
        return factor

    @classmethod
    def from_ordered(cls, L: Any, perm: IntArray, nodes: IntArray, num_nodes: int,
                     supernodes: bool) -> Factor:
        """The sparse factor of ``L``, given in the graph's :class:`EliminationOrder`
        already: its rows are those of the free ``nodes``' ``perm``."""
        factor = cls._unset(nodes, num_nodes)
        factor._perm = perm
        factor._lu = factor_spd(L, ordered=True, supernodes=supernodes)
        return factor

    @classmethod
    def from_dense(cls, L: FloatArray, nodes: IntArray) -> Factor:
        """The dense Cholesky factor of ``L`` (a dense array) on the free ``nodes``."""
        factor = cls._unset(nodes, None)
        factor._dense = cho_factor(L, lower=True, check_finite=False)
        return factor

    @property
    def sparse(self) -> bool:
        """Whether this is a sparse factorization."""
        return self._lu is not None

    def dense_inverse(self) -> FloatArray | None:
        """``L^-1`` (free nodes x free nodes) from the dense Cholesky factor; None where
        ``L`` is not factored densely."""
        if self._dense is None:
            return None
        c, lower = self._dense
        inv, info = lapack.dpotri(c, lower=lower)
        if info != 0:
            raise np.linalg.LinAlgError(f"dpotri failed (info {info})")
        half = np.tril(inv) if lower else np.triu(inv).T  # the stored triangle, as lower
        return np.asarray(half + np.tril(half, -1).T)

    def solve(self, b: FloatArray) -> FloatArray:
        """``L^-1 b`` for a vector or the columns of a matrix ``b``."""
        if self._dense is not None:
            return np.asarray(cho_solve(self._dense, b, check_finite=False))
        if self._matrix is not None:
            x = jacobi_pcg(self._matrix, b, self._inverse_diagonal, PCG_TOLERANCE,
                           PCG_MAX_ITERATIONS)
            if self._route is not None:  # (where CG fails more often than not, the
                if x is None:  # graph's later Laplacians are factored at once)
                    self._route.not_converged += 1
                else:
                    self._route.converged += 1
            if x is not None:
                return x
            self._factor_sparse(self._matrix)  # did not converge: factor after all
        assert self._lu is not None
        if self._perm is None:
            return np.asarray(solve_by_blocks(self._lu, b))
        x = np.empty_like(b)
        x[self._perm] = solve_by_blocks(self._lu, np.ascontiguousarray(b[self._perm]))
        return x


def _route_for(num_nodes: int | None) -> ConjugateGradientRoute | None:
    """The current :class:`ConjugateGradientRoute` where it is that of a graph on
    ``num_nodes`` nodes."""
    route = CG_ROUTE.get()
    return route if route is not None and route.num_nodes == num_nodes else None


def _solves_iteratively(size: int, nnz: int, route: ConjugateGradientRoute | None) -> bool:
    """Whether a sparse Laplacian on ``size`` free nodes with ``nnz`` stored entries is
    solved by conjugate gradients (:data:`WELL_CONNECTED`, :data:`ITERATIVE_MIN_DEGREE`,
    unless CG failed on the graph: ``route``)."""
    return ((WELL_CONNECTED.get() or nnz / size - 1.0 >= ITERATIVE_MIN_DEGREE)
            and not (route is not None and route.failed))


PATTERNS_KEPT = 16
"""Sets of edges whose :class:`LaplacianPattern` an :class:`EliminationOrder` remembers
(with its key, about 1 MB each on City10000's 10,000 nodes and 20,687 edges)."""
DENSE_MAX = 1000
"""Free nodes up to which a Laplacian with more than ``DENSE_FILL`` of its entries set is
solved densely (Cholesky, 8 MB at most): random view graphs fill SuperLU's factors almost
completely, while chains and pose graphs stay sparse. (The same sizes as when the 3N x 3N
normal matrix itself was factored: 3,000 and 300 coordinates.)"""
DENSE_FILL = 0.02
DENSE_ALWAYS = 100
"""Free nodes up to which every Laplacian is solved densely (well under a millisecond)."""


def _factor_densely(size: int, nnz: int) -> bool:
    """Whether a Laplacian on ``size`` free nodes with ``nnz`` stored entries (its sparse
    form's) is factored by dense Cholesky (:data:`DENSE_MAX`, :data:`DENSE_FILL`,
    :data:`DENSE_ALWAYS`)."""
    return size <= DENSE_MAX and (nnz > DENSE_FILL * size ** 2 or size <= DENSE_ALWAYS)
ITERATIVE_MIN_DEGREE = 10.0
"""Above ``DENSE_MAX``: mean number of weighted edges per node from which the Laplacian is
solved by Jacobi-preconditioned conjugate gradients instead of SuperLU. A graph this
well connected (an SfM view graph; the solver's dense-mode threshold) fills SuperLU's
factors (2,000 nodes, 20,000 edges, when the 3N x 3N matrix was factored: 4.3 s per
factorization) but is well conditioned:
CG converges in a few dozen products with the sparse matrix. Chains and pose graphs
(degree 2-5) are the other way round. A CG that does not converge falls back to SuperLU."""
WELL_CONNECTED: ContextVar[bool] = ContextVar("WELL_CONNECTED", default=False)
"""Set (by :func:`~rotavg_ros.core.robust.verify.verify`) while the input graph has at
least ``ITERATIVE_MIN_DEGREE`` edges per node: then every large normal matrix is solved by
conjugate gradients first (until CG fails more often than not on the graph's matrices:
:class:`ConjugateGradientRoute`), also where GNC's zero weights leave fewer active edges.
Those matrices are still expander-like, and SuperLU fills them in: a 5,000-node graph of mean
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


def gauss_newton_step(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    laplacian: Factor | None = None, residuals: FloatArray | None = None,
) -> tuple[FloatArray, Factor | None]:
    """One Gauss-Newton step of ``min sum_e w_e |e_e|^2``: the new rotations and the
    factor of the graph Laplacian it used.

    ``laplacian``: that of an earlier step with the same weights ``w`` (it depends on
    nothing else), reused instead of a new factorization. ``residuals``: the
    :func:`edge_residuals` of ``rot`` on every edge, when the caller has them already.
    Edges with ``w_e = 0`` take no part; nodes no weighted edge reaches keep their rotation.
    """
    n = rot.shape[0]
    active = w > 0
    i, j, R, w = i[active], j[active], R[active], w[active]
    if n < 2 or i.size == 0:
        return rot.copy(), None
    rs = soa.to_soa(rot)  # the products below in the (3, 3, n) layout: several times faster
    e = _residuals(rs, i, j, soa.to_soa(R)) if residuals is None else residuals[active].T
    if laplacian is None:
        laplacian = laplacian_factor(n, i, j, w)
        if laplacian is None:
            return rot.copy(), None
    # The normal equations in the rotated variables v_i = R_i^T d_i (module docstring):
    # L v = -B^T b, where the gradient b_i += w P e, b_j -= w e (P = R_i R_j^T) turns into
    # R_i^T P e = R_j^T e at i and -R_j^T e at j. Then d_i = R_i v_i.
    u = (w * soa.apply(np.take(rs, j, axis=2), e, transpose=True)).T  # w R_j^T e, as rows
    Bb = scatter_add(i, u, n) - scatter_add(j, u, n)
    nodes = laplacian.nodes
    d = np.zeros((3, n))
    d[:, nodes] = soa.apply(np.take(rs, nodes, axis=2), laplacian.solve(-Bb[nodes]).T)
    return soa.from_soa(soa.renormalize(soa.matmul(soa.exp(d), rs))), laplacian


class ProbeDraws:
    """The normal draws of :func:`prediction_variance`'s probes, drawn once for every fit
    of one graph: the draws depend on the count of edges in the fit, the probes and the
    seed only, and a generator's ``(m, c)`` draw is the first ``m`` rows of its ``(M, c)``
    draw for any ``M >= m``, so the widest draw so far serves every narrower fit with the
    same numbers a fresh draw gives. (Each fit of City10000's verification drew 20,000 x
    96 normals afresh, 19 ms of its 70.) Set it with :func:`shared_probe_draws`."""

    def __init__(self) -> None:
        self._draws: dict[tuple[int, int], FloatArray] = {}
        self._lock = threading.Lock()  # the verification's threads share the draws

    def normals(self, rows: int, cols: int, seed: int) -> FloatArray:
        """``np.random.default_rng(seed).standard_normal((rows, cols))``, read-only."""
        with self._lock:
            drawn = self._draws.get((cols, seed))
            if drawn is None or drawn.shape[0] < rows:
                drawn = np.random.default_rng(seed).standard_normal((rows, cols))
                drawn.flags.writeable = False
                self._draws[(cols, seed)] = drawn
        return drawn[:rows]


PROBE_DRAWS: ContextVar[ProbeDraws | None] = ContextVar("PROBE_DRAWS", default=None)
"""The current graph's :class:`ProbeDraws` (see :func:`shared_probe_draws`)."""


@contextmanager
def shared_probe_draws() -> Iterator[None]:
    """Within this block, :func:`prediction_variance` takes its probes' normal draws from
    one :class:`ProbeDraws` instead of drawing them afresh for each fit (the same numbers)."""
    token = PROBE_DRAWS.set(ProbeDraws())
    try:
        yield
    finally:
        PROBE_DRAWS.reset(token)


def _probe_normals(rows: int, cols: int, seed: int) -> FloatArray:
    """The probes' ``(rows, cols)`` standard normal draw for ``seed``: from the shared
    :class:`ProbeDraws` where one is set, else drawn now (read-only either way)."""
    return (PROBE_DRAWS.get() or ProbeDraws()).normals(rows, cols, seed)


PROBE_BLOCK = 8192
""":func:`prediction_variance` squares the probes' differences for this many edges at a
time."""


def prediction_variance(
    rot: FloatArray, i: IntArray, j: IntArray, w: FloatArray, probes: int = 32,
    seed: int = 0, exact: BoolArray | Callable[[FloatArray], BoolArray] | None = None,
) -> FloatArray:
    """Per edge, ``q_e = tr(A_e H^-1 A_e^T) / 3`` for the least-squares fit with weights
    ``w`` (``w_e = 0``: not in the fit), estimated with random probes.

    In units of the noise variance of a unit-weight edge: an edge in the fit has leverage
    ``w_e q_e`` (its residual variance shrinks by ``1 - w_e q_e``), an edge outside it is
    predicted with variance ``1 / w_e + q_e``. Since ``H = B (L kron I_3) B^T`` (module
    docstring), ``q_e`` is the effective resistance ``(u_i - u_j)^T L^-1 (u_i - u_j)``
    between the edge's ends in the weighted graph (``u_k``: unit vectors, the anchor's
    zero): it depends on the weights only, not on ``rot`` (which gives the node count).
    Probes ``z = L^-1 B^T W^(1/2) g`` with ``g ~ N(0, I)`` have covariance ``L^-1``, so
    ``E (z_i - z_j)^2 = q_e``; ``3 probes`` of them (the 3 columns per probe of the
    rotation-block form) give about 15% relative error. Edges marked in ``exact`` get
    ``q_e`` from one solve each instead (needed where the leverage is close to 1); ``exact``
    may be a function of the probe estimates that returns the mask (one factorization
    serves both).

    Where ``L`` is factored densely (at most :data:`DENSE_MAX` free nodes: SfM view graphs,
    small pose graphs) every ``q_e`` is exact instead, from ``L^-1`` itself (the probes'
    ``E x 3 probes`` normal draws were most of the time: Ellis Island 23 of 35 ms, against
    about 1 ms for the inverse); a callable ``exact`` is then called on the exact values.
    """
    n = rot.shape[0]
    q = np.zeros(i.size)
    factored = _factored_laplacian(n, i, j, w)
    if factored is None:
        return q
    laplacian, index = factored
    nodes = laplacian.nodes
    active = w > 0
    ai, aj, aw = i[active], j[active], w[active]
    inverse = laplacian.dense_inverse()
    if inverse is not None:
        q = _resistance_from_inverse(inverse, index, i, j)
        if callable(exact):
            exact(q)
        return q
    g = _probe_normals(ai.size, 3 * probes, seed) * np.sqrt(aw)[:, None]
    b = scatter_add(ai, g, n) - scatter_add(aj, g, n)  # B^T W^(1/2) g
    del g
    z = np.zeros((n, 3 * probes))
    z[nodes] = laplacian.solve(np.ascontiguousarray(b[nodes]))
    # (z_i - z_j)^2 averaged over the probes, a block of edges at a time: (E, 3 probes)
    # temporaries cost 77 MB each on 100,000 edges, and more time than the arithmetic.
    for lo in range(0, i.size, PROBE_BLOCK):
        diff = z[i[lo:lo + PROBE_BLOCK]] - z[j[lo:lo + PROBE_BLOCK]]
        diff *= diff
        q[lo:lo + PROBE_BLOCK] = np.mean(diff, axis=1)
    if callable(exact):
        exact = exact(q)
    if exact is not None and exact.any():
        q[exact] = _effective_resistance(laplacian, index, i[exact], j[exact])
    return q


def effective_resistances(n: int, i: IntArray, j: IntArray, w: FloatArray,
                          edges: IntArray) -> FloatArray:
    """Exact ``q_e`` (as in :func:`prediction_variance`: the effective resistance between
    the edge's ends in the graph weighted ``w``) for the ``edges`` (indices into ``i``,
    ``j``) only: one factorization, then the dense inverse where ``L`` is small, else one
    solve per edge. Without probes: the cost of a few edges stays a few solves."""
    q = np.zeros(edges.size)
    factored = _factored_laplacian(n, i, j, w) if edges.size else None
    if factored is None:
        return q
    factor, index = factored
    inverse = factor.dense_inverse()
    if inverse is not None:
        return _resistance_from_inverse(inverse, index, i[edges], j[edges])
    return _effective_resistance(factor, index, i[edges], j[edges])


def _factored_laplacian(n: int, i: IntArray, j: IntArray, w: FloatArray
                        ) -> tuple[Factor, IntArray] | None:
    """The factored Laplacian of the edges weighted ``w`` (``w_e = 0``: left out) and each
    node's row in it (-1: the anchor or a node no edge reaches, whose potential is 0); None
    where there is nothing to factor."""
    active = w > 0
    if n < 2 or not active.any():
        return None
    factor = laplacian_factor(n, i[active], j[active], w[active])
    if factor is None:
        return None
    index = np.full(n, -1)
    index[factor.nodes] = np.arange(factor.nodes.size)
    return factor, index


def _resistance_from_inverse(inverse: FloatArray, index: IntArray, i: IntArray,
                             j: IntArray) -> FloatArray:
    """``(u_i - u_j)^T L^-1 (u_i - u_j)`` per edge from ``L^-1``; ``index`` as in
    :func:`_effective_resistance` (-1: potential 0)."""
    a, b = index[i], index[j]
    diagonal = np.append(np.diagonal(inverse), 0.0)  # [-1]: the anchor's 0
    cross = np.where((a >= 0) & (b >= 0), inverse[a, b], 0.0)
    return np.asarray(diagonal[a] + diagonal[b] - 2.0 * cross)


def _effective_resistance(laplacian: Factor, index: IntArray, i: IntArray, j: IntArray,
                          batch: int = 96) -> FloatArray:
    """``(u_i - u_j)^T L^-1 (u_i - u_j)`` by one solve per edge; ``index``: node -> row of
    ``L`` (-1: the anchor or an unreached node, whose potential is 0)."""
    out = np.empty(i.size)
    size = laplacian.nodes.size
    for lo in range(0, i.size, batch):
        sl = slice(lo, min(lo + batch, i.size))
        cols = np.arange(sl.stop - lo)
        ri, rj = index[i[sl]], index[j[sl]]
        rhs = np.zeros((size, cols.size))
        rhs[ri[ri >= 0], cols[ri >= 0]] += 1.0
        rhs[rj[rj >= 0], cols[rj >= 0]] -= 1.0
        x = laplacian.solve(rhs)
        xi = np.where(ri >= 0, x[np.maximum(ri, 0), cols], 0.0)
        xj = np.where(rj >= 0, x[np.maximum(rj, 0), cols], 0.0)
        out[sl] = xi - xj
    return out


def refine_least_squares(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    iterations: int = 10, tolerance: float = 1e-5,
) -> FloatArray:
    """Gauss-Newton iterations of weighted geodesic least squares from ``rot``.

    Stops when the largest update is below ``tolerance`` radians.
    """
    laplacian: Factor | None = None  # the weights stay: one factorization serves
    for _ in range(iterations):
        new, laplacian = gauss_newton_step(rot, i, j, R, w, laplacian)
        moved = np.linalg.norm(
            soa.log(soa.matmul(soa.to_soa(new), soa.to_soa(rot), transpose_b=True)), axis=0)
        rot = new
        if moved.size == 0 or float(moved.max()) < tolerance:
            break
    return rot
