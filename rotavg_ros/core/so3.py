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
from numpy.typing import ArrayLike

from rotavg_ros.core.types import FloatArray


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


NEAR_ROTATION = 1e-6
""":func:`renormalize`: a matrix with ``max |X^T X - I|`` up to this is within rounding of a
rotation and is corrected by one Newton-Schulz step (error afterwards about its square)."""


def renormalize(M: ArrayLike) -> FloatArray:
    """:func:`project_to_so3` for matrices that are rotations up to rounding (products of
    rotations): one Newton-Schulz step of the polar decomposition, ``X (3 I - X^T X) / 2``,
    two batched products instead of a batched SVD. A matrix further off (``NEAR_ROTATION``)
    or with det <= 0 is projected by the SVD."""
    M = np.asarray(M, dtype=np.float64)
    gram = np.ascontiguousarray(np.swapaxes(M, -1, -2)) @ M  # a copy: faster than a view
    gram -= np.eye(3)
    out = M - 0.5 * (M @ gram)
    det = np.einsum("...i,...i->...", M[..., 0, :], np.cross(M[..., 1, :], M[..., 2, :]))
    off = (np.abs(gram).max(axis=(-2, -1)) > NEAR_ROTATION) | (det <= 0.0)
    if np.any(off):
        out[off] = project_to_so3(M[off])
    return out


def geodesic_distance(A: ArrayLike, B: ArrayLike) -> FloatArray:
    """Angle of ``A B^T`` in radians (the Riemannian distance on SO(3))."""
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    tr = np.einsum("...ij,...ij->...", A, B)  # trace(A B^T)
    return np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))


def geodesic_midpoint(A: ArrayLike, B: ArrayLike) -> FloatArray:
    """The rotation halfway along the geodesic from ``B`` to ``A``, ``exp(log(A B^T) / 2) B``
    (each pair of a stack; the same point from either end, the metric being bi-invariant;
    for two rotations less than pi apart, the one nearest both)."""
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    return exp_map(0.5 * log_map(A @ np.swapaxes(B, -1, -2))) @ B


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


NEAR_PI = 2.5
""":func:`log_map`: above this angle the axis comes from the symmetric part of ``R``."""


def _vee_skew(R: FloatArray) -> FloatArray:
    """``vee(R - R^T)`` = ``2 sin(theta) * axis``."""
    return np.stack([R[..., 2, 1] - R[..., 1, 2],
                     R[..., 0, 2] - R[..., 2, 0],
                     R[..., 1, 0] - R[..., 0, 1]], axis=-1)


def rotation_angle(R: FloatArray) -> FloatArray:
    """Angle of each rotation in ``[0, pi]`` via ``atan2`` (accurate near 0 and pi)."""
    return _angle(R, _vee_skew(R))


def _angle(R: FloatArray, v: FloatArray) -> FloatArray:
    """:func:`rotation_angle` of ``R`` given ``v = _vee_skew(R)``."""
    s = np.linalg.norm(v, axis=-1) / 2.0
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arctan2(s, c)


def log_map(R: FloatArray) -> FloatArray:
    """Rotation vectors ``(..., 3)`` with ``exp(hat(v)) = R``, ``|v| <= pi``."""
    R = np.asarray(R, dtype=np.float64)
    v = _vee_skew(R)
    theta = _angle(R, v)
    s = np.sin(theta)
    small = theta < 1e-6
    # theta / (2 sin theta), with its Taylor series near 0.
    scale = np.where(small, 0.5 + theta**2 / 12.0, theta / (2.0 * np.where(small, 1.0, s)))
    out = scale[..., None] * v
    near_pi = theta > NEAR_PI
    if np.any(near_pi):
        Rp = R[near_pi]
        th = theta[near_pi]
        cos = np.cos(th)
        # (R + R^T)/2 = cos I + (1 - cos) a a^T
        S = (Rp + np.swapaxes(Rp, -1, -2)) / 2.0 - cos[:, None, None] * np.eye(3)
        S /= (1.0 - cos)[:, None, None]
        k = np.argmax(np.diagonal(S, axis1=-2, axis2=-1), axis=-1)
        axis = S[np.arange(k.size), :, k]
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        sign = np.where(np.einsum("ka,ka->k", axis, v[near_pi]) < 0, -1.0, 1.0)
        out[near_pi] = (sign * th)[:, None] * axis
    return out


def exp_map(v: FloatArray) -> FloatArray:
    """Rodrigues' formula for rotation vectors ``(..., 3)``."""
    v = np.asarray(v, dtype=np.float64)
    theta = np.linalg.norm(v, axis=-1)
    small = theta < 1e-6
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    K = np.zeros((*v.shape[:-1], 3, 3))
    K[..., 0, 1], K[..., 0, 2] = -v[..., 2], v[..., 1]
    K[..., 1, 0], K[..., 1, 2] = v[..., 2], -v[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -v[..., 1], v[..., 0]
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)
