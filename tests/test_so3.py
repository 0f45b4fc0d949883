"""SO(3) helpers: quaternion order, projection, distances."""

from __future__ import annotations

import numpy as np
import pytest

from rotavg_ros.core.so3 import (
    angle_from_chord,
    chord_from_angle,
    chordal_distance,
    geodesic_distance,
    geodesic_midpoint,
    matrix_to_quat,
    project_to_so3,
    quat_to_matrix,
    random_rotations,
    renormalize,
    rotation_about_axis,
)


def _is_rotation(R: np.ndarray, atol: float = 1e-12) -> bool:
    R = np.asarray(R).reshape(-1, 3, 3)
    orth = np.einsum("kji,kjl->kil", R, R) - np.eye(3)
    return bool(np.all(np.abs(orth) < atol) and np.all(np.abs(np.linalg.det(R) - 1) < atol))


def test_ros_order_z90_maps_x_to_y() -> None:
    s = np.sin(np.pi / 4)
    R = quat_to_matrix([0.0, 0.0, s, s])  # x, y, z, w
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(R @ [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(R @ [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], atol=1e-15)
    # Identity quaternion is (0, 0, 0, 1) in ROS order, not (1, 0, 0, 0).
    np.testing.assert_allclose(quat_to_matrix([0.0, 0.0, 0.0, 1.0]), np.eye(3), atol=1e-15)
    np.testing.assert_allclose(matrix_to_quat(R), [0.0, 0.0, s, s], atol=1e-15)


def test_quat_matrix_round_trip_batch() -> None:
    rng = np.random.default_rng(0)
    q = rng.normal(size=(200, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    R = quat_to_matrix(q)
    assert R.shape == (200, 3, 3) and _is_rotation(R)
    q2 = matrix_to_quat(R)
    # Same rotation: q2 = +-q, and w >= 0 picks the sign.
    q_ref = np.where(q[:, 3:4] < 0, -q, q)
    np.testing.assert_allclose(q2, q_ref, atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix(q2), R, atol=1e-12)


def test_quat_to_matrix_normalises_and_handles_shapes() -> None:
    s = np.sin(np.pi / 4)
    R = quat_to_matrix([0.0, 0.0, 3 * s, 3 * s])  # not unit norm
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)
    q = np.random.default_rng(1).normal(size=(2, 5, 4))
    assert quat_to_matrix(q).shape == (2, 5, 3, 3)
    assert matrix_to_quat(quat_to_matrix(q)).shape == (2, 5, 4)


def test_matrix_to_quat_w_nonnegative_all_branches() -> None:
    # Cover every branch: trace largest and each diagonal entry largest, incl. 180 deg.
    mats = [
        np.eye(3),
        rotation_about_axis([1.0, 0, 0], np.pi),
        rotation_about_axis([0, 1.0, 0], np.pi),
        rotation_about_axis([0, 0, 1.0], np.pi),
        rotation_about_axis([1.0, 0.1, 0.0], 3.0),
        rotation_about_axis([0.1, 1.0, 0.0], 3.0),
        rotation_about_axis([0.0, 0.1, 1.0], 3.0),
        rotation_about_axis([1.0, 1.0, 1.0], -2.5),
    ]
    R = np.stack(mats)
    q = matrix_to_quat(R)
    assert np.all(q[:, 3] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-14)
    np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-12)
    # A quaternion with w < 0 comes back negated (same rotation).
    q_neg = np.array([0.1, -0.2, 0.3, -0.9])
    q_neg /= np.linalg.norm(q_neg)
    np.testing.assert_allclose(matrix_to_quat(quat_to_matrix(q_neg)), -q_neg, atol=1e-12)


def test_rotation_about_axis_matches_quaternion() -> None:
    R = rotation_about_axis([0.0, 0.0, 2.0], np.pi / 2)  # axis need not be unit
    s = np.sin(np.pi / 4)
    np.testing.assert_allclose(R, quat_to_matrix([0.0, 0.0, s, s]), atol=1e-15)
    np.testing.assert_allclose(geodesic_distance(R, np.eye(3)), np.pi / 2, atol=1e-12)


def test_project_to_so3_single_matrix() -> None:
    rng = np.random.default_rng(2)
    R = random_rotations(1, rng)[0]
    P = project_to_so3(R + 1e-3 * rng.normal(size=(3, 3)))
    assert P.shape == (3, 3) and _is_rotation(P)
    assert geodesic_distance(P, R) < 2e-3
    np.testing.assert_allclose(project_to_so3(R), R, atol=1e-13)  # fixed point
    np.testing.assert_allclose(project_to_so3(2.5 * R), R, atol=1e-13)  # scale removed


def test_project_to_so3_batches() -> None:
    rng = np.random.default_rng(3)
    M = rng.normal(size=(4, 6, 3, 3))
    P = project_to_so3(M)
    assert P.shape == M.shape and _is_rotation(P)
    # Nearest in Frobenius norm: no random rotation is closer than the projection.
    cand = random_rotations(500, rng)
    m = M[1, 2]
    best = np.min(chordal_distance(cand, m))
    assert chordal_distance(P[1, 2], m) <= best + 1e-12


def test_renormalize_matches_the_projection_near_and_far_from_so3() -> None:
    rng = np.random.default_rng(5)
    R = random_rotations(200, rng) @ random_rotations(200, rng)  # rotations up to rounding
    near = R + 1e-9 * rng.normal(size=R.shape)
    far = R + 1e-2 * rng.normal(size=R.shape)
    reflected = R[:3] @ np.diag([1.0, 1.0, -1.0])
    for M in (R, near, np.concatenate([near[:50], far[:50], reflected])):
        out = renormalize(M)
        assert _is_rotation(out)
        np.testing.assert_allclose(out, project_to_so3(M), atol=1e-13)


def test_project_to_so3_reflection_gets_det_plus_one() -> None:
    rng = np.random.default_rng(4)
    R = random_rotations(8, rng)
    reflected = R @ np.diag([1.0, 1.0, -1.0])
    assert np.all(np.linalg.det(reflected) < 0)
    P = project_to_so3(reflected)
    np.testing.assert_allclose(np.linalg.det(P), 1.0, atol=1e-12)
    assert _is_rotation(P)
    single = project_to_so3(-np.eye(3))
    np.testing.assert_allclose(np.linalg.det(single), 1.0, atol=1e-12)
    assert _is_rotation(single)


def test_geodesic_and_chordal_consistent() -> None:
    rng = np.random.default_rng(5)
    A = random_rotations(300, rng)
    B = random_rotations(300, rng)
    ang = geodesic_distance(A, B)
    chord = chordal_distance(A, B)
    assert np.all((ang >= 0) & (ang <= np.pi + 1e-12))
    assert np.all((chord >= 0) & (chord <= 2 * np.sqrt(2) + 1e-12))
    np.testing.assert_allclose(chord_from_angle(ang), chord, atol=1e-10)
    np.testing.assert_allclose(angle_from_chord(chord), ang, atol=1e-6)
    # Symmetry and identity.
    np.testing.assert_allclose(geodesic_distance(B, A), ang, atol=1e-12)
    assert np.all(chordal_distance(A, A) < 1e-14)
    assert np.all(geodesic_distance(A, A) < 1e-6)


@pytest.mark.parametrize("angle", [0.0, 0.01, 0.5, 1.0, 2.0, 3.0, np.pi])
def test_chord_angle_inverse_and_known_values(angle: float) -> None:
    R = rotation_about_axis([0.3, -0.4, 0.5], angle)
    assert geodesic_distance(R, np.eye(3)) == pytest.approx(angle, abs=1e-7)
    c = chord_from_angle(angle)
    assert chordal_distance(R, np.eye(3)) == pytest.approx(c, abs=1e-12)
    assert angle_from_chord(c) == pytest.approx(angle, abs=1e-7)


def test_chord_from_angle_endpoints_and_clip() -> None:
    assert chord_from_angle(np.pi) == pytest.approx(2 * np.sqrt(2))
    assert chord_from_angle(np.pi / 2) == pytest.approx(2.0)
    assert angle_from_chord(2 * np.sqrt(2) + 1e-9) == pytest.approx(np.pi)  # clipped
    assert angle_from_chord(0.0) == 0.0


def test_structure_of_arrays_maps_agree_with_the_stacked_ones() -> None:
    """so3_soa's products and maps on (3, 3, n) give so3's on (n, 3, 3): tiny, ordinary
    and near-pi angles (the log's other branch), and matrices off SO(3) (the SVD's)."""
    from rotavg_ros.core import so3_soa as soa
    from rotavg_ros.core.so3 import exp_map, log_map

    rng = np.random.default_rng(7)
    v = rng.normal(size=(300, 3))
    v[:100] *= 1e-8 / np.linalg.norm(v[:100], axis=1, keepdims=True)
    v[100:200] *= (np.pi - 1e-4) / np.linalg.norm(v[100:200], axis=1, keepdims=True)
    R = exp_map(v)
    np.testing.assert_allclose(soa.from_soa(soa.exp(v.T)), R, atol=1e-14)
    np.testing.assert_allclose(soa.log(soa.to_soa(R)).T, log_map(R), atol=1e-12)
    A, B = random_rotations(50, rng), random_rotations(50, rng)
    As, Bs = soa.to_soa(A), soa.to_soa(B)
    for ta in (False, True):
        for tb in (False, True):
            expected = (np.swapaxes(A, 1, 2) if ta else A) @ (np.swapaxes(B, 1, 2) if tb else B)
            np.testing.assert_allclose(soa.from_soa(soa.matmul(As, Bs, ta, tb)), expected,
                                       atol=1e-14)
    x = rng.normal(size=(3, 50))
    np.testing.assert_allclose(soa.apply(As, x).T, (A @ x.T[:, :, None])[:, :, 0], atol=1e-14)
    np.testing.assert_allclose(soa.apply(As, x, transpose=True).T,
                               (np.swapaxes(A, 1, 2) @ x.T[:, :, None])[:, :, 0], atol=1e-14)
    M = A + rng.normal(scale=1e-9, size=A.shape)
    M[:5] = rng.normal(size=(5, 3, 3))  # far off: projected by the SVD
    M[5] = -A[5]  # det -1
    out = soa.from_soa(soa.renormalize(soa.to_soa(M)))
    np.testing.assert_allclose(out, renormalize(M), atol=1e-14)
    assert _is_rotation(out)


def test_geodesic_midpoint_is_halfway_from_either_end() -> None:
    rng = np.random.default_rng(4)
    A, B = random_rotations(50, rng), random_rotations(50, rng)
    M = geodesic_midpoint(A, B)
    gap = geodesic_distance(A, B)
    assert np.allclose(geodesic_distance(M, A), gap / 2.0, atol=1e-9)
    assert np.allclose(geodesic_distance(M, B), gap / 2.0, atol=1e-9)
    assert np.allclose(geodesic_midpoint(B, A), M, atol=1e-9)  # the same from either end
    assert np.allclose(np.einsum("nab,nac->nbc", M, M), np.eye(3), atol=1e-12)
    assert np.allclose(geodesic_midpoint(A, A), A, atol=1e-12)
