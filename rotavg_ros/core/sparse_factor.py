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
column), SuperLU's own supernode settings are the faster ones again (``supernodes``; see
:func:`~rotavg_ros.core.chordal_init.chordal_rotations`).
"""

from __future__ import annotations

from typing import Any

from scipy.sparse.linalg import SuperLU, splu

SUPERNODE_RELAX = 1
"""SuperLU's ``relax``: columns merged into a relaxed supernode at the elimination tree's
leaves. It must not exceed ``PANEL_SIZE`` (SciPy 1.x crashed with 32 against 16)."""
PANEL_SIZE = 1
"""SuperLU's ``panel_size``: columns factored together."""


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
