"""Sparse mode's fit: the Laplacian preconditioner and when it is used."""

from __future__ import annotations

import math
from dataclasses import replace
from unittest import mock

import numpy as np
import pytest
import torch

from benchmarks.regime_cases import lattice_case
from rotavg_ros.core import chordal_init, sparse_factor
from rotavg_ros.core.chordal_init import anchor_candidates, central_node, chordal_rotations
from rotavg_ros.core.dmf.common import FitSpec
from rotavg_ros.core.dmf.precondition import LaplacianPreconditioner
from rotavg_ros.core.dmf.sparse import fit_symmetric_lbfgs, huber_delta, shows_outliers
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.so3 import exp_map, geodesic_distance, random_rotations, rotation_about_axis


def _loop_chain(n: int, seed: int) -> tuple[np.ndarray, ...]:
    """A long chain with a few far loop closures, 1 deg noise per axis (a pose graph's
    worst conditioning: information crosses it one edge per step)."""
    rng = np.random.default_rng(seed)
    truth = random_rotations(n, rng)
    i = np.concatenate([np.arange(n - 1), rng.integers(0, n // 2, 12)])
    j = np.concatenate([np.arange(1, n), rng.integers(n // 2, n, 12)])
    R = np.einsum("eab,ecb->eac", truth[i], truth[j])
    noise = exp_map(rng.normal(size=(i.size, 3)) * math.radians(1.0))
    return i, j, noise @ R, truth


def _fit(n: int, i: np.ndarray, j: np.ndarray, R: np.ndarray, precondition: bool
         ) -> tuple[np.ndarray, int]:
    opt = SolverOptions.for_profile("default")
    w = np.ones(i.size)
    H0 = chordal_rotations(n, i, j, R, w)
    delta = huber_delta(H0, i, j, R, opt.sparse.huber_factor)
    fit = fit_symmetric_lbfgs(n, i, j, R, w, replace(opt.sparse, precondition=precondition),
                              opt.dense, FitSpec(2, 3 * n, 0, "cpu", False), H0, delta)
    return fit.H, fit.iterations


def test_preconditioned_fit_reaches_the_same_optimum_in_fewer_steps() -> None:
    n = 400
    i, j, R, _ = _loop_chain(n, seed=5)
    plain_H, plain_steps = _fit(n, i, j, R, precondition=False)
    pre_H, pre_steps = _fit(n, i, j, R, precondition=True)
    assert pre_steps * 4 < plain_steps, (pre_steps, plain_steps)
    # Same fit: the relative rotations agree to well under the noise.
    rel_plain = np.einsum("nab,cb->nac", plain_H, plain_H[0])
    rel_pre = np.einsum("nab,cb->nac", pre_H, pre_H[0])
    u, _, vt = np.linalg.svd(rel_plain)
    v, _, wt = np.linalg.svd(rel_pre)
    assert np.degrees(geodesic_distance(u @ vt, v @ wt)).max() < 0.05


def test_preconditioner_inverts_the_rotational_curvature() -> None:
    """On a consistent graph, a gradient that is a smooth rotation field (antisymmetric in
    the local frame) comes back as the Laplacian's solution: applying ``L`` again gives the
    field back."""
    rng = np.random.default_rng(2)
    n = 50
    H = random_rotations(n, rng)
    i, j = np.arange(n - 1), np.arange(1, n)
    c = 1.0 + rng.random(i.size)
    pre = LaplacianPreconditioner(H, i, j, c, diagonal_curvature=3.0)
    a = rng.normal(size=(n, 3))
    a -= a.mean(axis=0)  # no global rotation: the Laplacian's null direction
    skew = np.zeros((n, 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = a[:, 0], a[:, 1], a[:, 2]
    skew -= np.swapaxes(skew, 1, 2)
    g = torch.as_tensor((H @ skew).reshape(-1))  # U_i A_i: a rotation-only gradient
    z = pre(g).numpy().reshape(n, 3, 3)
    local = np.swapaxes(H, 1, 2) @ z
    upper = local[:, [0, 0, 1], [1, 2, 2]]
    L = np.zeros((n, n))
    np.add.at(L, (i, i), c)
    np.add.at(L, (j, j), c)
    np.add.at(L, (i, j), -c)
    np.add.at(L, (j, i), -c)
    np.testing.assert_allclose(L @ upper, a, atol=1e-6)
    np.testing.assert_allclose(local + np.swapaxes(local, 1, 2), 0.0, atol=1e-9)


def test_outliers_are_seen_at_the_start() -> None:
    n = 100
    i, j, R, truth = _loop_chain(n, seed=1)
    w = np.ones(i.size)
    assert not shows_outliers(truth, i, j, R, w, 5.0)
    R[-1] = random_rotations(1, np.random.default_rng(0))[0]  # one false closure
    assert shows_outliers(truth, i, j, R, w, 5.0)


def test_chordal_start_is_anchored_at_a_central_node_and_gauged_at_node_0() -> None:
    # A path 0-1-...-22 (node 0 at one end, as the first keyframe of a trajectory): node 11.
    i = np.arange(22)
    j = i + 1
    assert central_node(23, i, j) == 11
    # Exact measurements: the chordal solution is the truth, with node 0 the identity.
    truth = random_rotations(23, np.random.default_rng(0))
    truth = np.einsum("nab,cb->nac", truth, truth[0])
    R = np.einsum("eab,ecb->eac", truth[i], truth[j])
    out = chordal_rotations(23, i, j, R, np.ones(i.size))
    assert np.degrees(geodesic_distance(out, truth)).max() < 1e-5  # (arccos near 1)
    # The relaxation's anchors: the centre first, then a quarter and three quarters along.
    assert anchor_candidates(23, i, j) == [11, 5, 17]  # (the path runs from b back to a)


def _noisy_chain_with_closures(n: int, closures: int, noise_deg: float,
                               rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """A chain of ``n`` nodes plus ``closures`` random edges (self-loops dropped), every
    measurement ``R_ij = R_i R_j^T`` turned by ``N(0, noise_deg)`` per axis."""
    truth = random_rotations(n, rng)
    i = np.r_[np.arange(n - 1), rng.integers(0, n, closures)]
    j = np.r_[np.arange(1, n), rng.integers(0, n, closures)]
    keep = i != j
    i, j = i[keep], j[keep]
    R = np.einsum("eab,ecb->eac", truth[i], truth[j])
    noise = exp_map(rng.normal(0.0, math.radians(noise_deg), (i.size, 3)))
    return i, j, np.einsum("eab,ebc->eac", noise, R)


def test_chordal_start_keeps_the_anchor_of_the_lowest_chordal_cost() -> None:
    """At high noise the relaxation depends on its anchor; the kept solution's chordal cost
    is the lowest of the candidates', and below the central anchor's where that differs."""
    n = 300
    i, j, R = _noisy_chain_with_closures(n, 200, 25.0, np.random.default_rng(4))
    w = np.ones(i.size)

    def cost(rot: np.ndarray) -> float:
        miss = rot[i] - np.einsum("eab,ebc->eac", R, rot[j])
        return float(np.sum(miss * miss))

    chosen = cost(chordal_rotations(n, i, j, R, w))
    each = []
    for fraction in chordal_init.ANCHOR_FRACTIONS:
        with mock.patch.object(chordal_init, "ANCHOR_FRACTIONS", (fraction,)):
            each.append(cost(chordal_rotations(n, i, j, R, w)))
    assert chosen == pytest.approx(min(each), rel=1e-12)
    assert len(set(np.round(each, 6))) > 1  # the anchors differ here


def test_chordal_start_one_factorization_matches_eliminating_each_anchor() -> None:
    """Every anchor's relaxation comes from one factor of the softly pinned Laplacian; it is
    the minimiser that eliminating the anchor's block from the Laplacian gives."""
    rng = np.random.default_rng(7)
    n = 60
    i, j, R = _noisy_chain_with_closures(n, 40, 30.0, rng)
    w = rng.uniform(0.5, 2.0, i.size)
    L = np.zeros((3 * n, 3 * n))
    for e in range(i.size):
        a, b = slice(3 * i[e], 3 * i[e] + 3), slice(3 * j[e], 3 * j[e] + 3)
        L[a, a] += w[e] * np.eye(3)
        L[b, b] += w[e] * np.eye(3)
        L[a, b] -= w[e] * R[e]
        L[b, a] -= w[e] * R[e].T
    centre, *others = anchor_candidates(n, i, j)
    pin = 2.5
    M = L.copy()
    M[3 * centre:3 * centre + 3, 3 * centre:3 * centre + 3] += pin * np.eye(3)
    Q = np.asarray(np.linalg.solve(M, np.eye(3 * n)[:, 3 * centre:3 * centre + 3]), np.float64)
    for anchor in [centre, *others]:
        P = np.asarray(np.linalg.solve(M, np.eye(3 * n)[:, 3 * anchor:3 * anchor + 3]), np.float64)
        X = chordal_init._anchored_solution(P, Q, anchor, centre, pin)
        fixed = np.arange(3 * anchor, 3 * anchor + 3)
        free = np.setdiff1d(np.arange(3 * n), fixed)
        direct = np.empty((3 * n, 3))
        direct[fixed] = np.eye(3)
        direct[free] = np.linalg.solve(L[np.ix_(free, free)], -L[np.ix_(free, fixed)])
        assert np.abs(X - direct).max() < 1e-9
    assert len(others) == 2


def _lattice(side: int, seed: int) -> tuple[np.ndarray, ...]:
    """The regime benchmark's ``side``^3 lattice pose graph (grid3D's topology, 1 deg of
    noise): ``(i, j, R, truth)``. Its factors fill in heavily."""
    case = lattice_case(f"test/lattice/{side}", side, seed=seed)
    return case.i, case.j, case.R, case.gt


def test_chordal_start_takes_supernodes_where_the_factor_fills_in_heavily() -> None:
    """A 3D lattice's factor fills in past SUPERNODE_MIN_FILL entries per node, a long
    chain's does not; with or without the supernode settings the relaxation is the same."""
    i, j, R, truth = _lattice(16, 3)
    n, w = truth.shape[0], np.ones(i.size)
    deg = np.bincount(i, w, n) + np.bincount(j, w, n)
    assert n >= chordal_init.SUPERNODE_MIN_NODES
    assert chordal_init.fills_heavily(n, i, j, w, deg, 0, 1.0)
    ci, cj, cR, _ = _loop_chain(3000, 4)
    cw = np.ones(ci.size)
    cdeg = np.bincount(ci, cw, 3000) + np.bincount(cj, cw, 3000)
    assert not chordal_init.fills_heavily(3000, ci, cj, cw, cdeg, 0, 1.0)
    assert not chordal_init.fills_heavily(n // 4, i[:10], j[:10], w[:10], deg, 0, 1.0)

    si, sj, sR, struth = _lattice(6, 5)  # small: compare both settings on it
    sw = np.ones(si.size)
    with mock.patch.object(chordal_init, "SUPERNODE_MIN_NODES", 0):
        with mock.patch.object(sparse_factor, "SUPERNODE_MIN_FILL", 0.0):
            heavy = chordal_rotations(struth.shape[0], si, sj, sR, sw)
        with mock.patch.object(sparse_factor, "SUPERNODE_MIN_FILL", math.inf):
            light = chordal_rotations(struth.shape[0], si, sj, sR, sw)
    assert np.abs(heavy - light).max() < 1e-9
    assert np.median(np.degrees(geodesic_distance(heavy, np.einsum(
        "nab,cb->nac", struth, struth[0])))) < 3.0  # (node 0's own error in every node)


def test_reused_relaxations_solve_each_input_once() -> None:
    """Within reused_relaxations the same input is relaxed once (the same result, a copy
    each time); another input, or a call outside the block, is solved."""
    i, j, R, truth = _loop_chain(80, 6)
    n, w = truth.shape[0], np.ones(i.size)
    solved = []
    real = chordal_init._chordal_rotations

    def counting(*args: object) -> np.ndarray:
        solved.append(1)
        return real(*args)  # type: ignore[arg-type]

    with mock.patch.object(chordal_init, "_chordal_rotations", counting):
        plain = chordal_rotations(n, i, j, R, w)
        with chordal_init.reused_relaxations():
            first = chordal_rotations(n, i, j, R, w)
            first[:] = 0.0  # the caller's copy
            with chordal_init.reused_relaxations():  # nested: the outer block's results
                again = chordal_rotations(n, i.copy(), j.copy(), R.copy(), w.copy())
            other = chordal_rotations(n, i, j, R, 2.0 * w)
        after = chordal_rotations(n, i, j, R, w)
    assert len(solved) == 4  # plain, first, other, after
    assert np.array_equal(again, plain) and np.array_equal(after, plain)
    assert np.abs(other - plain).max() < 1e-9  # (scaled weights: the same relaxation)


def _planar_loop_chain(n: int, seed: int, noise_deg: float
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``_loop_chain``'s edges on a planar robot: every rotation about z, heading noise
    ``N(0, noise_deg)`` on every edge."""
    rng = np.random.default_rng(seed)
    heading = np.cumsum(rng.normal(0.0, 0.1, n))
    i = np.concatenate([np.arange(n - 1), rng.integers(0, n // 2, 12)])
    j = np.concatenate([np.arange(1, n), rng.integers(n // 2, n, 12)])
    delta = heading[i] - heading[j] + rng.normal(0.0, math.radians(noise_deg), i.size)
    return i, j, rotation_about_axis(np.array([0.0, 0.0, 1.0]), delta)


def test_huber_delta_counts_only_the_entries_that_carry_noise() -> None:
    """Rotations about one axis leave five of nine residual entries at zero: the median over
    all of them was 0 (an L1 fit); over the others it is the noise's. On a 3D graph every
    entry counts, as before."""
    n = 200
    i, j, R = _planar_loop_chain(n, seed=3, noise_deg=5.0)
    H0 = chordal_rotations(n, i, j, R, np.ones(i.size))
    residual = np.abs(np.einsum("eab,ecb->eac", H0[i], H0[j]) - R)
    assert float(np.median(residual)) <= 1e-12  # the structural zeros outnumber the rest
    assert np.all(residual[:, 2, :] <= 1e-12) and np.all(residual[:, :, 2] <= 1e-12)
    delta = huber_delta(H0, i, j, R, 30.0)
    assert delta == 30.0 * float(np.median(residual[:, :2, :2]))
    assert delta > 30.0 * 1e-3  # the noise's scale (5 deg), not the floor
    # A 3D chain with loop closures: the chordal start fits some edges exactly (the
    # bridges), but no entry is zero on every edge: every entry counts, as before.
    i3, j3, R3, _ = _loop_chain(n, seed=3)
    H3 = chordal_rotations(n, i3, j3, R3, np.ones(i3.size))
    residual3 = np.abs(np.einsum("eab,ecb->eac", H3[i3], H3[j3]) - R3)
    assert residual3.min() <= 1e-12
    assert huber_delta(H3, i3, j3, R3, 30.0) == 30.0 * float(np.median(residual3))


def test_loose_rounds_reach_the_same_fit_in_fewer_steps() -> None:
    """Noise whose level differs from edge to edge (lognormal): the reweighting rounds run
    several times. Rounds that another follows end once their L-BFGS stalls; the fit is the
    fully converged one to well under the noise, with the same edges down-weighted."""
    rng = np.random.default_rng(1)
    n, loops = 600, 150
    truth = random_rotations(n, rng)
    i = np.concatenate([np.arange(n - 1), rng.integers(0, n // 2, loops)])
    j = np.concatenate([np.arange(1, n), rng.integers(n // 2, n, loops)])
    R = np.einsum("eab,ecb->eac", truth[i], truth[j])
    sigma = math.radians(2.0) * np.exp(0.7 * rng.normal(size=i.size))
    R = exp_map(rng.normal(size=(i.size, 3)) * sigma[:, None]) @ R
    opt = SolverOptions.for_profile("default")
    w = np.ones(i.size)
    H0 = chordal_rotations(n, i, j, R, w)
    delta = huber_delta(H0, i, j, R, opt.sparse.huber_factor)
    fits = {loose: fit_symmetric_lbfgs(n, i, j, R, w, replace(opt.sparse, loose_rounds=loose),
                                       opt.dense, FitSpec(2, 3 * n, 0, "cpu", False), H0, delta,
                                       trusted_start=True)
            for loose in (False, True)}
    assert fits[True].iterations < 0.9 * fits[False].iterations, (
        fits[True].iterations, fits[False].iterations)
    rotations = {}
    for loose, fit in fits.items():
        u, _, vt = np.linalg.svd(np.einsum("nab,cb->nac", fit.H, fit.H[0]))
        rotations[loose] = u @ vt
    assert np.degrees(geodesic_distance(rotations[False], rotations[True])).max() < 0.01
    assert np.array_equal(fits[False].weights < 0.9, fits[True].weights < 0.9)
    assert (fits[True].weights < 0.9).any()  # the rounds did reweight
