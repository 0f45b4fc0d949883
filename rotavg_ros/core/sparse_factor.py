"""One sparse factorization for every symmetric positive definite system of the core: graph
Laplacians (Gauss-Newton, GNC, leverages, the sparse fit's preconditioner) and the chordal
relaxation's block Laplacian.

SciPy's SuperLU in symmetric mode (diagonal pivots, the ordering of ``A + A^T``), with its
supernode settings for these matrices: ``relax`` = ``panel_size`` = 1. Their factors are
sparse and their supernodes small, and SuperLU's defaults (panel size 10, relaxed
supernodes) cost more than they save there: one factorization of a pose graph's Laplacian
about 1.5x faster (parking-garage, sphere2500, torus3D), an odometry chain's 2.5x, a whole
chordal relaxation (which also builds the matrix) up to 1.3x (``python -m
benchmarks.bench_sparse_factor``; docs/benchmarks.md, "SuperLU settings"). The factors
hold the same entries (no pivoting), up to rounding.

Where the factor fills in heavily (a 3D lattice's chordal relaxation: 600 entries per
column; its scalar Laplacian from about 150), SuperLU's own supernode settings are the
faster ones again (``supernodes``; :func:`factor_fills_heavily`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.sparse.linalg import SuperLU, splu

SUPERNODE_RELAX = 1
"""SuperLU's ``relax``: columns merged into a relaxed supernode at the elimination tree's
leaves. It must not exceed ``PANEL_SIZE`` (SciPy 1.x crashed with 32 against 16)."""
PANEL_SIZE = 1
"""SuperLU's ``panel_size``: columns factored together."""
SUPERNODE_MIN_FILL = 120.0
"""Entries per column of a factor (L and U, minimum-degree order) from which matrices of
its pattern are factored with SuperLU's supernode settings (:func:`factor_fills_heavily`).
Measured on 3D lattices (scratch, 2026-12-05 and 12-06): the chordal relaxation's block
matrix at 74 per node of its scalar Laplacian 2.9x slower with them, 122 and 145 1.1x
faster, 181 1.4x, 221 (20^3 nodes) 2.0x; the scalar Laplacian itself at 86-145 the same
time, 181 1.2x faster, 221 1.5x, 244 (22^3) 1.6x; a 10,000-step grid-city walk's (65)
1.9x slower. The SE-Sync pose graphs and the regime benchmark's chains have 8-35."""


def factor_spd(A: Any, ordered: bool = False, supernodes: bool = False) -> SuperLU:
    """SuperLU factorization of the sparse symmetric positive definite ``A`` (CSC).

    ``ordered``: ``A`` is already in a fill-reducing order (kept as is); else SuperLU orders
    it by minimum degree on ``A + A^T``. ``supernodes``: SuperLU's default supernode
    settings instead of :data:`SUPERNODE_RELAX` and :data:`PANEL_SIZE` (for factors that
    fill in heavily).
    """
    settings = {} if supernodes else {"relax": SUPERNODE_RELAX, "panel_size": PANEL_SIZE}
    return splu(A, permc_spec="NATURAL" if ordered else "MMD_AT_PLUS_A",
                diag_pivot_thresh=0.0, options={"SymmetricMode": True}, **settings)


SOLVE_COLUMNS = 32
"""Right-hand sides :func:`solve_by_blocks` hands SuperLU at a time, where they are wide
(:data:`WIDE_BYTES`). SuperLU's triangular solves sweep the whole factor once per call with
every column's right-hand side in the working set: 96 columns of City10000's Laplacian
(10,000 nodes, 7.7 MB: the probes of
:func:`~rotavg_ros.core.robust.gauss_newton.prediction_variance`) took 39.7 ms in one call
and 24.4 ms 32 at a time; on the regime benchmark's smaller pose graphs and chains (at most
5,000 nodes, 3.8 MB) blocks were the same or up to 11% slower (``python -m
benchmarks.bench_sparse_factor``, 2026-12-08, this machine's 2 MB L2 per core). The same
numbers: each column's solution does not depend on the block it is solved in (measured bit
for bit, 96 columns against blocks of 32, on seven graphs)."""
WIDE_BYTES = 4 * 1024 * 1024
"""Size of the right-hand sides (bytes) above which :func:`solve_by_blocks` splits them."""


def solve_by_blocks(lu: SuperLU, b: Any, wide_bytes: int = WIDE_BYTES) -> Any:
    """``lu.solve(b)``; where ``b`` is wide (more than ``wide_bytes`` and
    :data:`SOLVE_COLUMNS` columns), its columns :data:`SOLVE_COLUMNS` at a time."""
    if b.ndim < 2 or b.shape[1] <= SOLVE_COLUMNS or b.nbytes <= wide_bytes:
        return lu.solve(b)
    x = np.empty(b.shape)
    for lo in range(0, b.shape[1], SOLVE_COLUMNS):
        x[:, lo:lo + SOLVE_COLUMNS] = lu.solve(np.ascontiguousarray(b[:, lo:lo + SOLVE_COLUMNS]))
    return x


def factor_fills_heavily(lu: SuperLU, size: int) -> bool:
    """Whether the factor ``lu`` of a ``size`` x ``size`` matrix holds at least
    :data:`SUPERNODE_MIN_FILL` entries per column: factor matrices of its pattern with
    ``supernodes``."""
    return bool((lu.L.nnz + lu.U.nnz) / max(size, 1) >= SUPERNODE_MIN_FILL)
