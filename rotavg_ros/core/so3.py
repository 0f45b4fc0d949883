"""Batched SO(3) helpers on numpy arrays.

Conventions
-----------
* Rotation matrices are ``(..., 3, 3)`` float arrays.
* Quaternions use the ROS order ``(x, y, z, w)`` (scalar last), and the Hamilton
  product, so ``quat_to_matrix`` agrees with ``tf2`` and ``geometry_msgs``.
* ``geodesic_distance(A, B) = ||Log(A B^T)||`` in radians, in [0, pi].
* ``chordal_distance(A, B) = ||A - B||_F``, in [0, 2*sqrt(2)].
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def quat_to_matrix(q: ArrayLike) -> FloatArray:
    """Rotation matrices from quaternions ``(..., 4)`` in ROS order x, y, z, w.

    The quaternions are normalised first; a zero quaternion gives NaN.
    """
    qa: FloatArray = np.asarray(q, dtype=np.float64)
    qa = qa / np.linalg.norm(qa, axis=-1, keepdims=True)
    x, y, z, w = qa[..., 0], qa[..., 1], qa[..., 2], qa[..., 3]
    out = np.empty(qa.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - z * w)
    out[..., 0, 2] = 2 * (x * z + y * w)
    out[..., 1, 0] = 2 * (x * y + z * w)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - x * w)
    out[..., 2, 0] = 2 * (x * z - y * w)
    out[..., 2, 1] = 2 * (y * z + x * w)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def matrix_to_quat(R: ArrayLike) -> FloatArray:
    """Quaternions ``(..., 4)`` (x, y, z, w, with w >= 0) from rotation matrices.

    Uses the numerically stable branch on the largest diagonal term.
    """
    R = np.asarray(R, dtype=np.float64)
    m = R.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    cand = np.stack(
        [tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1
    )
    k = np.argmax(cand, axis=1)
    q = np.empty((m.shape[0], 4))
    for case in range(4):
        sel = k == case
        if not np.any(sel):
            continue
        a = m[sel]
        if case == 0:
            s = np.sqrt(np.maximum(tr[sel] + 1.0, 1e-300)) * 2.0
            q[sel] = np.stack(
                [(a[:, 2, 1] - a[:, 1, 2]) / s, (a[:, 0, 2] - a[:, 2, 0]) / s,
                 (a[:, 1, 0] - a[:, 0, 1]) / s, 0.25 * s], axis=1)
        elif case == 1:
            s = np.sqrt(np.maximum(1.0 + a[:, 0, 0] - a[:, 1, 1] - a[:, 2, 2], 1e-300)) * 2.0
            q[sel] = np.stack(
                [0.25 * s, (a[:, 0, 1] + a[:, 1, 0]) / s,
                 (a[:, 0, 2] + a[:, 2, 0]) / s, (a[:, 2, 1] - a[:, 1, 2]) / s], axis=1)
        elif case == 2:
            s = np.sqrt(np.maximum(1.0 + a[:, 1, 1] - a[:, 0, 0] - a[:, 2, 2], 1e-300)) * 2.0
            q[sel] = np.stack(
                [(a[:, 0, 1] + a[:, 1, 0]) / s, 0.25 * s,
                 (a[:, 1, 2] + a[:, 2, 1]) / s, (a[:, 0, 2] - a[:, 2, 0]) / s], axis=1)
        else:
            s = np.sqrt(np.maximum(1.0 + a[:, 2, 2] - a[:, 0, 0] - a[:, 1, 1], 1e-300)) * 2.0
            q[sel] = np.stack(
                [(a[:, 0, 2] + a[:, 2, 0]) / s, (a[:, 1, 2] + a[:, 2, 1]) / s,
                 0.25 * s, (a[:, 1, 0] - a[:, 0, 1]) / s], axis=1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1.0
    return q.reshape(R.shape[:-2] + (4,))


def project_to_so3(M: ArrayLike) -> FloatArray:
    """Nearest rotation (Frobenius) to each 3x3 matrix: SVD with a determinant fix."""
    M = np.asarray(M, dtype=np.float64)
    U, _, Vt = np.linalg.svd(M)
    d = np.where(np.linalg.det(U @ Vt) < 0, -1.0, 1.0)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def geodesic_distance(A: ArrayLike, B: ArrayLike) -> FloatArray:
    """Angle of ``A B^T`` in radians (the Riemannian distance on SO(3))."""
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    tr = np.einsum("...ij,...ij->...", A, B)  # trace(A B^T)
    return np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))


def chordal_distance(A: ArrayLike, B: ArrayLike) -> FloatArray:
    """Frobenius distance ``||A - B||_F``."""
    diff = np.asarray(A, dtype=np.float64) - np.asarray(B, dtype=np.float64)
    return np.sqrt(np.einsum("...ij,...ij->...", diff, diff))


def chord_from_angle(angle_rad: ArrayLike) -> FloatArray:
    """Chordal distance of two rotations that differ by ``angle_rad``: 2*sqrt(2)*sin(a/2)."""
    return 2.0 * np.sqrt(2.0) * np.sin(np.asarray(angle_rad, dtype=np.float64) / 2.0)


def angle_from_chord(chord: ArrayLike) -> FloatArray:
    """Inverse of :func:`chord_from_angle`, in radians."""
    c = np.clip(np.asarray(chord, dtype=np.float64) / (2.0 * np.sqrt(2.0)), 0.0, 1.0)
    return 2.0 * np.arcsin(c)


def random_rotations(n: int, rng: np.random.Generator) -> FloatArray:
    """``n`` rotations drawn uniformly (Haar) from SO(3)."""
    q = rng.normal(size=(n, 4))
    return quat_to_matrix(q)


def rotation_about_axis(axis: ArrayLike, angle_rad: ArrayLike) -> FloatArray:
    """Rodrigues: rotations by ``angle_rad`` about unit ``axis`` (broadcast)."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    half = np.asarray(angle_rad, dtype=np.float64)[..., None] / 2.0
    q = np.concatenate([axis * np.sin(half), np.cos(half)], axis=-1)
    return quat_to_matrix(q)
