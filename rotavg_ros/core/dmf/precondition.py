"""Sparse mode's preconditioner: the loss's curvature near a solution, as a graph Laplacian.

Why: a pose graph's long loops and chains make the sparse fit badly conditioned. Its slow
modes are rotations that vary smoothly along the graph (information diffuses one edge per
step), so plain L-BFGS took 300 steps per reweighting round and still had not converged on
a 3,000-keyframe chain. A preconditioner that knows the graph turns those modes into one
step each.

The model: ``H`` (3N x 3) with node blocks ``H_i ~= U_i``, ``U_i`` orthogonal (the polar
factor of ``H_i``). In local coordinates ``dH_i = U_i C_i`` an edge's residual
``H_i H_j^T - R_ij`` moves by ``U_i (C_i + C_j^T) U_j^T``: its antisymmetric parts (the
rotations) couple as ``A_i - A_j`` and its symmetric parts (scale and shear) as
``S_i + S_j``. With ``c_e`` the edge's curvature (its weight over the Huber ``delta`` where
its entries are on the quadratic side, 0 on the linear side), the Hessian is about

* antisymmetric part: the weighted graph Laplacian ``L_c`` (solved by a sparse LU once per
  reweighting round; a small ridge fixes the global rotation, which the loss leaves free);
* symmetric part: ``D_c + A_c`` plus the ``|H_i H_i^T - I|`` term's ``4 w_diag / delta``,
  well conditioned, so its diagonal (Jacobi) is enough.

Conventions: ``H_i`` world-to-node up to one common rotation, ``R_ij ~= H_i H_j^T``.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.sparse import coo_matrix

from rotavg_ros.core import so3_soa as soa
from rotavg_ros.core.sparse_factor import factor_spd
from rotavg_ros.core.types import FloatArray, IntArray

RIDGE = 1e-9
"""Added to the Laplacian's diagonal, relative to its largest entry: the global rotation
is a null direction of the loss."""

_UPPER = (np.array([0, 0, 1]), np.array([1, 2, 2]))  # the antisymmetric part's entries


class LaplacianPreconditioner:
    """``M^-1`` of the module docstring, applied to a flat gradient of ``H`` (3N x 3, the
    single factor of a depth-2 fit), at the blocks ``H`` it was built from.

    The per-node 3x3 products run in the ``(3, 3, N)`` layout of
    :mod:`~rotavg_ros.core.so3_soa` (on a 1,661-node pose graph 0.5-0.7 ms per application
    against 1.1-1.9 ms with numpy's stacked ``(N, 3, 3)`` products; the same values to
    rounding)."""

    def __init__(self, H: FloatArray, i: IntArray, j: IntArray, curvature: FloatArray,
                 diagonal_curvature: float) -> None:
        n = H.shape[0]
        u, _, vt = np.linalg.svd(H)
        self._U = soa.to_soa(u @ vt)  # polar factors, (3, 3, N)
        degree = np.bincount(i, curvature, n) + np.bincount(j, curvature, n)
        self._half_sym = 0.5 / np.maximum(degree + diagonal_curvature, 1e-300)
        ridge = RIDGE * max(float(degree.max(initial=0.0)), 1e-300)
        laplacian = coo_matrix(
            (np.concatenate([degree + ridge, -curvature, -curvature]),
             (np.concatenate([np.arange(n), i, j]), np.concatenate([np.arange(n), j, i]))),
            shape=(n, n)).tocsc()
        self._lu = factor_spd(laplacian)

    def __call__(self, g: torch.Tensor) -> torch.Tensor:
        G = soa.to_soa(g.detach().cpu().numpy().reshape(-1, 3, 3))
        C = soa.matmul(self._U, G, transpose_a=True)  # U_i^T G_i: local coordinates
        Ct = C.transpose(1, 0, 2)
        Z = (C + Ct) * self._half_sym  # the symmetric part, Jacobi-scaled
        a, b = _UPPER
        anti = 0.5 * (C[a, b] - Ct[a, b])  # (3, N): the antisymmetric part's upper entries
        upper = self._lu.solve(np.ascontiguousarray(anti.T)).T
        Z[a, b] += upper
        Z[b, a] -= upper
        return torch.as_tensor(soa.from_soa(soa.matmul(self._U, Z)).reshape(-1),
                               dtype=g.dtype, device=g.device)
