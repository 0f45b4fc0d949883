"""Generators and the case list of the regime benchmark (``python -m benchmarks.regimes``).

Conventions (as everywhere in the project): node rotations ``R_i`` are **world-to-node**;
edge ``k`` joins ``i[k] < j[k]`` and carries ``R[k] ~= R_i R_j^T``. Angles are in degrees
unless a name says ``rad``.

Noise models (:data:`NOISE_MODELS`): a measurement is ``R_i R_j^T`` multiplied on the right
by a small rotation. ``folded`` (the default, and the recorded runs): a rotation about a
uniformly random axis through an angle ``|N(0, sigma)|`` (so ``sigma`` is the standard
deviation of the error angle's normal before folding; mean error angle ``0.80 sigma``); its
density in the tangent space peaks sharply at zero, which favours L1-like estimators.
``tangent``: ``exp`` of an isotropic Gaussian tangent vector, ``N(0, sigma / sqrt(3))`` per
axis (the same RMS error angle ``sigma``): the model of a g2o information matrix, for which
least squares is the maximum-likelihood estimator. ``anisotropic``: ``exp`` of a Gaussian
tangent vector three times larger about the measurement frame's z axis than about x and y
(``sigma (1, 1, 3) / sqrt(11)`` per axis, the same RMS angle): a SLAM front end whose heading
is its least certain angle. ``--noise-model`` and ``--seed`` of
``python -m benchmarks.regimes`` draw the same regimes afresh: a held-out check that the
recorded results do not depend on one draw.
False edges are Haar-random rotations, redrawn until they are at least
:data:`MIN_FALSE_DEG` away from the truth. Grouped false loop closures (perceptual aliasing,
as in the Vertigo / switchable-constraints generators) are runs of ``k`` new edges
``(a + t, b + t)``, ``t < k``, all equal to ``R_{a+t} W R_{b+t}^T`` (times noise) for one
wrong world rotation ``W`` per group: they agree with each other and with the odometry, and
disagree with the truth by the angle of ``W``.

Every case is built from a fixed seed, so the same name, seed and noise model give the same
edges bit for bit.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import csr_matrix

from benchmarks.datasets import (
    PlanarHeadings,
    find_gtsam_data,
    load_city10000,
    load_ellis_island,
    load_manhattan,
    load_se_sync,
)
from rotavg_ros.core.so3 import (
    exp_map,
    random_rotations,
    rotation_about_axis,
    rotation_angle,
)
from rotavg_ros.core.view_graph import ViewGraph

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

MIN_FALSE_DEG = 30.0
"""Every generated false edge is at least this far (geodesic angle) from the truth."""

FAMILIES = ("slam", "chain", "sfm", "real")

NOISE_MODELS = ("folded", "tangent", "anisotropic")
"""How measurement noise is drawn (see the module docstring); ``folded`` is the default."""

ANISOTROPY = np.array([1.0, 1.0, 3.0]) / np.sqrt(11.0)
"""Per-axis standard deviations of the ``anisotropic`` noise model, over ``sigma``."""


@dataclass
class RegimeCase:
    """One benchmark problem: edges, ground truth and what is known about the edges."""

    name: str
    family: str
    """``slam`` (regenerated on SLAM topologies), ``chain`` (synthetic odometry chains),
    ``sfm`` (Ellis Island and dense synthetic graphs), ``real`` (SE-Sync as measured)."""
    num_nodes: int
    i: IntArray
    j: IntArray
    R: FloatArray
    gt: FloatArray
    """(N, 3, 3) world-to-node ground-truth rotations (or certified reference)."""
    weight: FloatArray | None = None
    """Edge information weights (g2o data, :func:`weighted_case`); None = unweighted."""
    inlier: BoolArray | None = None
    """True for the edges that are not deliberately false; None when unknown (real data:
    no oracle row)."""
    noise_deg: float | None = None
    """The generating noise level, if known (GNC-TLS takes its sigma from it)."""
    description: str = ""
    sigma_deg: float = 5.0
    """Noise scale handed to GNC-TLS for unweighted edges: the generating noise level
    floored at 1 deg; the g2o information's ``1/sqrt(w)`` for SE-Sync as measured; a fixed
    5 deg for Ellis Island."""

    @property
    def num_edges(self) -> int:
        return int(self.i.shape[0])

    @property
    def odometry(self) -> BoolArray:
        """Edges between consecutive ids (``|i - j| == 1``): odometry in SLAM graphs."""
        return np.abs(self.i - self.j) == 1

    @property
    def has_odometry(self) -> bool:
        return self.family in ("slam", "chain", "real") and bool(self.odometry.any())

    def view_graph(self, keep: BoolArray | None = None) -> ViewGraph:
        """The case as a graph: nodes ``0 .. N-1`` in order (so node id = ground-truth
        index), then the edges ``keep`` (default all) in case order, with their weights."""
        sel = np.ones(self.num_edges, bool) if keep is None else keep
        g = ViewGraph()
        for k in range(self.num_nodes):
            g.add_node(k)
        w = None if self.weight is None else self.weight[sel]
        g.add_edges(self.i[sel].tolist(), self.j[sel].tolist(), self.R[sel], w)
        return g


# ----------------------------------------------------------------------------- generators


def rng_for(name: str, seed: int = 0) -> np.random.Generator:
    """A generator seeded from the case name and ``seed`` (stable across runs)."""
    return np.random.default_rng([zlib.crc32(name.encode()), seed])


def relative(gt: FloatArray, i: IntArray, j: IntArray) -> FloatArray:
    """Exact measurements ``R_i R_j^T``."""
    return gt[i] @ np.swapaxes(gt[j], -1, -2)


def random_axes(n: int, rng: np.random.Generator) -> FloatArray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def perturb(R: FloatArray, sigma_deg: float | FloatArray, rng: np.random.Generator,
            model: str = "folded") -> FloatArray:
    """``R_k N_k``: ``N_k`` a rotation by ``|N(0, sigma)|`` about a random axis (``folded``),
    or ``exp`` of a tangent vector with ``N(0, sigma / sqrt(3))`` per axis (``tangent``) or
    ``N(0, sigma ANISOTROPY)`` (``anisotropic``). ``sigma_deg``: one level for every edge,
    or one per edge (the same draws as one level where they are equal)."""
    if model not in NOISE_MODELS:
        raise ValueError(f"noise model must be one of {NOISE_MODELS}, got {model!r}")
    n = R.shape[0]
    sigma = np.radians(np.asarray(sigma_deg, dtype=float))
    if n == 0 or not np.any(sigma > 0):
        return R.copy()
    column = sigma[:, None] if sigma.ndim else sigma
    if model == "tangent":
        omega = rng.normal(0.0, column / np.sqrt(3.0), size=(n, 3))
        return R @ exp_map(omega)
    if model == "anisotropic":
        omega = rng.normal(0.0, 1.0, size=(n, 3)) * column * ANISOTROPY
        return R @ exp_map(omega)
    angles = np.abs(rng.normal(0.0, sigma, size=n))
    return R @ rotation_about_axis(random_axes(n, rng), angles)


def false_rotations(truth: FloatArray, rng: np.random.Generator,
                    min_deg: float = MIN_FALSE_DEG) -> FloatArray:
    """Haar-random rotations, each redrawn until it is ``>= min_deg`` from ``truth[k]``."""
    out = random_rotations(truth.shape[0], rng)
    bad = np.degrees(rotation_angle(out @ np.swapaxes(truth, -1, -2))) < min_deg
    while bad.any():
        out[bad] = random_rotations(int(bad.sum()), rng)
        bad = np.degrees(rotation_angle(out @ np.swapaxes(truth, -1, -2))) < min_deg
    return out


def sorted_edges(i: IntArray, j: IntArray) -> tuple[IntArray, IntArray]:
    return np.minimum(i, j).astype(np.int64), np.maximum(i, j).astype(np.int64)


def replace_with_false(R: FloatArray, true_R: FloatArray, candidates: IntArray,
                       fraction: float, rng: np.random.Generator) -> BoolArray:
    """Replace ``round(fraction * len(candidates))`` of the candidate edges (in place) by
    false rotations; returns the inlier mask."""
    inlier = np.ones(R.shape[0], dtype=bool)
    count = int(round(fraction * candidates.shape[0]))
    if count:
        pick = rng.choice(candidates, size=count, replace=False)
        R[pick] = false_rotations(true_R[pick], rng)
        inlier[pick] = False
    return inlier


def grouped_false_edges(gt: FloatArray, existing: set[tuple[int, int]], groups: int,
                        size_range: tuple[int, int], min_gap: int, noise_deg: float,
                        rng: np.random.Generator, stride: int = 1,
                        forbid: Callable[[int, int], bool] | None = None,
                        noise_model: str = "folded",
                        ) -> tuple[IntArray, IntArray, FloatArray]:
    """``groups`` runs of mutually consistent false closures (see the module docstring).

    Each run joins ``a + stride*t`` to ``b + stride*t`` for ``t < k``, ``k`` uniform in
    ``size_range``, ``|a - b| >= min_gap``, all with ``R_{a'} W R_{b'}^T`` for one ``W`` at
    least :data:`MIN_FALSE_DEG` from identity. Pairs already in ``existing`` (updated) or
    refused by ``forbid(a', b')`` are skipped.
    """
    n = gt.shape[0]
    ii: list[int] = []
    jj: list[int] = []
    Rs: list[FloatArray] = []
    made = 0
    tries = 0
    while made < groups and tries < 1000 * max(groups, 1):
        tries += 1
        k = int(rng.integers(size_range[0], size_range[1] + 1))
        span = stride * (k - 1) + 1
        if n - span < 1:
            break
        a, b = (int(x) for x in rng.integers(0, n - span + 1, size=2))
        if abs(a - b) < min_gap:
            continue
        W = false_rotations(np.eye(3)[None], rng)[0]
        pairs = [(a + stride * t, b + stride * t) for t in range(k)]
        pairs = [(min(p), max(p)) for p in pairs]
        if any(p in existing or (forbid is not None and forbid(*p)) for p in pairs):
            continue
        for p, q in pairs:
            existing.add((p, q))
            ii.append(p)
            jj.append(q)
            Rs.append(gt[p] @ W @ gt[q].T)
        made += 1
    if not ii:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3, 3))
    R = perturb(np.stack(Rs), noise_deg, rng, noise_model)
    return np.asarray(ii, np.int64), np.asarray(jj, np.int64), R


def triangle_count(n: int, i: IntArray, j: IntArray) -> int:
    """Number of triangles of the undirected simple graph (``trace(A^3) / 6``)."""
    A = csr_matrix((np.ones(2 * i.shape[0]), (np.r_[i, j], np.r_[j, i])), shape=(n, n))
    A.data[:] = 1.0
    return int(round((A @ A).multiply(A).sum() / 6.0))


# ----------------------------------------------------------------------- SLAM topologies


def slam_case(name: str, shared: Path, graph: str, *, noise_deg: float = 1.0,
              random_false: float = 0.0, groups: int = 0, seed: int = 0,
              noise_model: str = "folded") -> RegimeCase:
    """Measurements regenerated on a real SLAM graph's edges, against its reference.

    ``random_false``: fraction of the non-odometry edges replaced by false rotations;
    ``groups``: runs of 5-10 grouped false closures added (min gap 50 ids).
    """
    bench = load_se_sync(shared, graph)
    n = bench.graph.num_nodes
    ids = bench.graph.node_ids
    gt = np.stack([bench.reference[k] for k in ids])
    e = bench.graph.edge_arrays()
    i, j = sorted_edges(e.i, e.j)
    rng = rng_for(name, seed)
    truth = relative(gt, i, j)
    R = perturb(truth, noise_deg, rng, noise_model)
    loop = np.flatnonzero(np.abs(i - j) != 1)
    inlier = replace_with_false(R, truth, loop, random_false, rng)
    if groups:
        existing = set(zip(i.tolist(), j.tolist(), strict=True))
        gi, gj, gR = grouped_false_edges(gt, existing, groups, (5, 10), 50, noise_deg, rng,
                                         noise_model=noise_model)
        i, j, R = np.r_[i, gi], np.r_[j, gj], np.concatenate([R, gR])
        inlier = np.r_[inlier, np.zeros(gi.shape[0], bool)]
    desc = f"{graph} edges, noise {noise_deg:g} deg"
    if random_false:
        desc += f", {random_false:.0%} of loop closures false"
    if groups:
        desc += f", {groups} groups ({gi.shape[0]} edges) of grouped false closures"
    return RegimeCase(name, "slam", n, i, j, R, gt, None, inlier, noise_deg, desc,
                      max(noise_deg, 1.0))


# ---------------------------------------------------------------------------- chains


def chain_trajectory(n: int, rng: np.random.Generator, step_deg: float = 4.0) -> FloatArray:
    """Smooth random-walk world-to-node rotations: the angular velocity is an AR(1)
    process with a stationary per-step angle of about ``step_deg``."""
    omega = np.zeros(3)
    R = np.empty((n, 3, 3))
    R[0] = random_rotations(1, rng)[0]
    scale = np.radians(step_deg) / np.sqrt(3.0)
    for k in range(1, n):
        omega = 0.9 * omega + np.sqrt(1 - 0.81) * rng.normal(0.0, scale, size=3)
        R[k] = exp_map(omega[None])[0] @ R[k - 1]
    return R


CAR_TURNS_DEG = (90.0, -90.0, 90.0, -90.0, 45.0, -45.0, 180.0)
"""The turns :func:`car_trajectory` draws from (right angles twice as often)."""


def car_trajectory(n: int, rng: np.random.Generator) -> FloatArray:
    """A car's world-to-node rotations between sparse keyframes: straight runs of 8-39
    keyframes (heading noise 0.5 deg a step), each followed by a turn from
    :data:`CAR_TURNS_DEG` spread over 2-4 keyframes (steps of 11-90 deg); pitch and roll a
    slow random walk of 0.06 deg a step (a road's slopes), about a random heading. What
    this tests, against :func:`chain_trajectory`'s smooth walk: steps of two sizes, most
    small and one in ten large, as parking-garage's own trajectory has (422 of its 1,660
    steps more than 5 robust spreads above the median step), so that a large step is no
    sign of a lost track."""
    yaw = np.empty(n)
    heading, k = float(rng.uniform(-np.pi, np.pi)), 0
    while k < n:
        for _ in range(int(rng.integers(8, 40))):
            if k == n:
                break
            heading += np.radians(rng.normal(0.0, 0.5))
            yaw[k], k = heading, k + 1
        turn = np.radians(float(rng.choice(CAR_TURNS_DEG)))
        spread = int(rng.integers(2, 5))
        for _ in range(spread):
            if k == n:
                break
            heading += turn / spread
            yaw[k], k = heading, k + 1
    tilt = np.cumsum(rng.normal(0.0, np.radians(0.06), (n, 2)), axis=0)
    body_to_world = (exp_map(np.stack([np.zeros(n), np.zeros(n), yaw], axis=1))
                     @ exp_map(np.concatenate([tilt, np.zeros((n, 1))], axis=1)))
    return np.ascontiguousarray(np.swapaxes(body_to_world, 1, 2))


TRAJECTORIES: dict[str, Callable[[int, np.random.Generator], FloatArray]] = {
    "smooth": chain_trajectory, "car": car_trajectory}
"""The chain generators' ground-truth rotations by name (``trajectory``)."""


def _closure_rules(num_nodes: int, odometry: list[tuple[int, int]]) -> tuple[
        Callable[[int, int], bool], Callable[[int, int], None], set[tuple[int, int]]]:
    """``(bad, add, used)``: the placement rules for loop closures (ends at least 20 apart,
    no triangle, not within 1 id of an earlier closure at both ends) over the given
    odometry pairs, the call that records a placed closure, and the closures placed."""
    nbrs: list[set[int]] = [set() for _ in range(num_nodes)]
    for a, b in odometry:
        nbrs[a].add(b)
        nbrs[b].add(a)
    used: set[tuple[int, int]] = set()

    def bad(a: int, b: int) -> bool:
        if a == b or abs(a - b) < 20 or (a, b) in used or nbrs[a] & nbrs[b]:
            return True
        return any((a + da, b + db) in used for da in (-1, 0, 1) for db in (-1, 0, 1))

    def add(a: int, b: int) -> None:
        used.add((a, b))
        nbrs[a].add(b)
        nbrs[b].add(a)

    return bad, add, used


PLACEMENT_TRIES = 1000
"""Random draws per closure before a generator gives up (a clear error, not a hang)."""
GROUP_TRIES = 100
"""Failed placements of a group of false closures (each of up to 1,000 draws) before
:func:`chain_case` gives up."""


def _random_pairs(num_nodes: int, count: int, rng: np.random.Generator,
                  bad: Callable[[int, int], bool], add: Callable[[int, int], None]
                  ) -> list[tuple[int, int]]:
    """``count`` random node pairs ``(a, b)``, ``a < b``, that ``bad`` allows (each added)."""
    out: list[tuple[int, int]] = []
    for _ in range(PLACEMENT_TRIES * max(count, 1)):
        if len(out) == count:
            return out
        a, b = sorted(int(x) for x in rng.integers(0, num_nodes, size=2))
        if not bad(a, b):
            add(a, b)
            out.append((a, b))
    if len(out) < count:
        raise ValueError(f"could not place {count} loop closures on {num_nodes} keyframes "
                         f"under the placement rules (placed {len(out)})")
    return out


def chain_case(name: str, num_nodes: int, *, closures: int, false_random: float = 0.0,
               false_grouped: float = 0.0, odo_noise_deg: float = 1.5,
               loop_noise_deg: float = 2.0, seed: int = 0,
               noise_model: str = "folded", trajectory: str = "smooth") -> RegimeCase:
    """An odometry chain ``(k, k+1)`` plus sparse loop closures and no triangles, along
    ``trajectory`` (:data:`TRAJECTORIES`).

    ``closures`` true loop closures between keyframes at least 20 apart, each rejected
    when it would close a triangle (its ends share a neighbour) or when it shares both
    ends' neighbourhoods (within 1 id) with an earlier closure. False closures: a fraction
    ``false_random`` (random rotations, same placement rules) and ``false_grouped``
    (runs of 4-8 mutually consistent ones with stride 2, see the module docstring) of all
    closures; these fractions are of the final closure count.
    """
    rng = rng_for(name, seed)
    gt = TRAJECTORIES[trajectory](num_nodes, rng)
    n_false = false_random + false_grouped
    total = int(round(closures / max(1e-9, 1.0 - n_false)))
    n_rand = int(round(false_random * total))
    n_grp = total - closures - n_rand
    bad, add, used = _closure_rules(num_nodes, [(k, k + 1) for k in range(num_nodes - 1)])
    true_pairs = _random_pairs(num_nodes, closures, rng, bad, add)
    rand_pairs = _random_pairs(num_nodes, n_rand, rng, bad, add)
    gi_l: list[int] = []
    gj_l: list[int] = []
    g_R: list[FloatArray] = []
    failed = 0
    while len(gi_l) < n_grp:
        k = min(int(rng.integers(4, 9)), n_grp - len(gi_l))
        gi, gj, gR = grouped_false_edges(gt, set(used), 1, (k, k), 40, loop_noise_deg, rng,
                                         stride=2, forbid=bad, noise_model=noise_model)
        if gi.size == 0:
            failed += 1
            if failed >= GROUP_TRIES:  # (else this loop would never end)
                raise ValueError(f"could not place a group of {k} false closures on "
                                 f"{num_nodes} keyframes under the placement rules")
        for a, b in zip(gi.tolist(), gj.tolist(), strict=True):
            add(a, b)
        gi_l += gi.tolist()
        gj_l += gj.tolist()
        g_R += list(gR)
    odo_i = np.arange(num_nodes - 1, dtype=np.int64)
    R_odo = perturb(relative(gt, odo_i, odo_i + 1), odo_noise_deg, rng, noise_model)
    ti = np.asarray([p[0] for p in true_pairs], np.int64)
    tj = np.asarray([p[1] for p in true_pairs], np.int64)
    R_true = perturb(relative(gt, ti, tj), loop_noise_deg, rng, noise_model)
    ri = np.asarray([p[0] for p in rand_pairs], np.int64)
    rj = np.asarray([p[1] for p in rand_pairs], np.int64)
    R_rand = false_rotations(relative(gt, ri, rj), rng)
    i = np.r_[odo_i, ti, ri, np.asarray(gi_l, np.int64)]
    j = np.r_[odo_i + 1, tj, rj, np.asarray(gj_l, np.int64)]
    R = np.concatenate([R_odo, R_true, R_rand, np.stack(g_R) if g_R else np.zeros((0, 3, 3))])
    inlier = np.r_[np.ones(num_nodes - 1 + closures, bool),
                   np.zeros(n_rand + len(gi_l), bool)]
    desc = (f"chain {num_nodes} keyframes, odo noise {odo_noise_deg:g} deg, {closures} true "
            f"closures ({loop_noise_deg:g} deg), {n_rand} random + {len(gi_l)} grouped false")
    noise = max(odo_noise_deg, loop_noise_deg)
    return RegimeCase(name, "chain", num_nodes, i, j, R, gt, None, inlier, noise, desc,
                      max(noise, 1.0))


def lattice_case(name: str, side: int, *, noise_deg: float = 1.0,
                 random_false: float = 0.0, seed: int = 0,
                 noise_model: str = "folded") -> RegimeCase:
    """A pose graph on a ``side``^3 lattice, grid3D's topology (SE-Sync's grid3D: 20^3
    poses, 22,236 edges; smallGrid3D: 5^3): ids along a snake through the lattice (the
    odometry, consecutive ids), every other lattice neighbour a loop closure, a fraction
    ``random_false`` of the closures false. The rotations turn about 20 deg a step
    (:func:`chain_trajectory`). What this tests: a graph with thousands of nodes, six
    edges a node and little else than loops, whose sparse factors fill in heavily."""
    rng = rng_for(name, seed)
    cells = [(x if (y + side * z) % 2 == 0 else side - 1 - x,
              y if z % 2 == 0 else side - 1 - y, z)
             for z in range(side) for y in range(side) for x in range(side)]
    index = {c: k for k, c in enumerate(cells)}
    pairs = sorted({(min(k, index[c2]), max(k, index[c2])) for c, k in index.items()
                    for c2 in ((c[0] + 1, c[1], c[2]), (c[0], c[1] + 1, c[2]),
                               (c[0], c[1], c[2] + 1)) if c2 in index})
    i = np.asarray([p[0] for p in pairs], np.int64)
    j = np.asarray([p[1] for p in pairs], np.int64)
    n = len(cells)
    gt = chain_trajectory(n, rng, step_deg=20.0)
    truth = relative(gt, i, j)
    R = perturb(truth, noise_deg, rng, noise_model)
    inlier = replace_with_false(R, truth, np.flatnonzero(np.abs(i - j) != 1), random_false,
                                rng)
    desc = f"{side}^3 lattice, noise {noise_deg:g} deg"
    if random_false:
        desc += f", {random_false:.0%} of loop closures false"
    return RegimeCase(name, "slam", n, i, j, R, gt, None, inlier, noise_deg, desc,
                      max(noise_deg, 1.0))


# ----------------------------------------------------------------------------- planar


def planar_case(name: str, base: RegimeCase, *, odo_noise_deg: float,
                loop_noise_deg: float, seed: int = 0,
                min_false_deg: float = MIN_FALSE_DEG) -> RegimeCase:
    """``base``'s edges and true / false split on a planar robot: every rotation about z.

    Headings are a random walk (``N(0, 4 deg)`` per id); a true edge measures the heading
    difference plus ``N(0, sigma)`` (odometry ``|i - j| = 1`` at ``odo_noise_deg``, the
    others at ``loop_noise_deg``); a false one is off by a heading drawn uniformly from
    ``min_false_deg`` to 180 deg, either sign, as a 2D front end's wrong match is. The
    noise is one-dimensional, so the noise models agree here. What this tests: noise and
    errors on one axis (the verification's noise model assumes three), and false closures
    that the odometry's drift can partly explain.
    """
    rng = rng_for(name, seed)
    heading = np.cumsum(rng.normal(0.0, np.radians(4.0), base.num_nodes))
    z = np.array([0.0, 0.0, 1.0])
    gt = rotation_about_axis(z, heading)
    i, j = base.i, base.j
    inlier = np.ones(i.size, bool) if base.inlier is None else base.inlier
    sigma = np.radians(np.where(np.abs(i - j) == 1, odo_noise_deg, loop_noise_deg))
    delta = heading[i] - heading[j] + rng.normal(0.0, 1.0, i.size) * sigma
    false = np.flatnonzero(~inlier)
    off = rng.uniform(np.radians(min_false_deg), np.pi, false.size)
    delta[false] = heading[i[false]] - heading[j[false]] + off * rng.choice([-1.0, 1.0],
                                                                            false.size)
    noise = max(odo_noise_deg, loop_noise_deg)
    desc = (f"planar: {base.description or base.name}'s edges, headings only, noise "
            f"{odo_noise_deg:g} / {loop_noise_deg:g} deg, {false.size} false")
    return RegimeCase(name, base.family, base.num_nodes, i, j,
                      rotation_about_axis(z, delta), gt, None, base.inlier, noise, desc,
                      max(noise, 1.0))


def weighted_case(name: str, base: RegimeCase, *, odo_noise_deg: float,
                  loop_noise_deg: float, seed: int = 0,
                  noise_model: str = "folded") -> RegimeCase:
    """``base``'s edges, truth and false edges, measured as a SLAM front end reports them:
    true odometry edges (``|i - j| = 1``) drawn again at ``odo_noise_deg``, true loop
    closures at ``loop_noise_deg``, and every edge weighted by its information
    ``1 / sigma^2`` (radians; a false closure carries a loop closure's weight, as its front
    end would report it). What this tests: weights that differ by ``(loop / odo)^2``
    between edges, which the noise scale, the thresholds and the choices must read as
    standardized residuals."""
    rng = rng_for(name, seed)
    inlier = np.ones(base.num_edges, bool) if base.inlier is None else base.inlier
    odo = base.odometry
    sigma = np.where(odo, odo_noise_deg, loop_noise_deg)
    R = base.R.copy()
    for mask, noise in ((odo & inlier, odo_noise_deg), (~odo & inlier, loop_noise_deg)):
        R[mask] = perturb(relative(base.gt, base.i[mask], base.j[mask]), noise, rng,
                          noise_model)
    desc = (f"weighted: {base.description or base.name}, odometry {odo_noise_deg:g} deg, "
            f"loop closures {loop_noise_deg:g} deg, weights 1 / sigma^2")
    return RegimeCase(name, base.family, base.num_nodes, base.i, base.j, R, base.gt,
                      1.0 / np.radians(sigma) ** 2, base.inlier,
                      max(odo_noise_deg, loop_noise_deg), desc, max(loop_noise_deg, 1.0))


def unweighted_case(name: str, base: RegimeCase, *, odo_noise_deg: float,
                    loop_noise_deg: float, seed: int = 0,
                    noise_model: str = "folded") -> RegimeCase:
    """:func:`weighted_case`'s measurements sent without their weights, as a front end that
    reports no covariances sends them: every edge at weight 1 (GNC-TLS gets the larger of the
    two noise levels). What this tests: odometry far more precise than the loop closures,
    which nothing in the input says."""
    case = weighted_case(name, base, odo_noise_deg=odo_noise_deg,
                         loop_noise_deg=loop_noise_deg, seed=seed, noise_model=noise_model)
    desc = (f"unweighted: {base.description or base.name}, odometry {odo_noise_deg:g} deg, "
            f"loop closures {loop_noise_deg:g} deg, every weight 1")
    return replace(case, weight=None, description=desc,
                   sigma_deg=max(odo_noise_deg, loop_noise_deg, 1.0))


def heteroscedastic_case(name: str, base: RegimeCase, *, sigma_deg: float,
                         spread: float = 0.7, seed: int = 0,
                         noise_model: str = "folded") -> RegimeCase:
    """``base``'s edges, truth and false edges, its true edges drawn again, each at its own
    noise level ``sigma_deg exp(N(0, spread))`` (lognormal: at ``spread`` 0.7 the middle
    half of the edges between 0.62 and 1.6 ``sigma_deg``, one in twenty above 3.2), and sent
    unweighted. What this tests: noise whose scale differs from edge to edge and which
    nothing reports, as a front end's matches of varying quality give it: heavy tails
    that are no outliers, where least squares in the bulk loses to a robust estimator."""
    rng = rng_for(name, seed)
    inlier = np.ones(base.num_edges, bool) if base.inlier is None else base.inlier
    sigma = sigma_deg * np.exp(rng.normal(0.0, spread, base.num_edges))
    R = base.R.copy()
    R[inlier] = perturb(relative(base.gt, base.i[inlier], base.j[inlier]), sigma[inlier],
                        rng, noise_model)
    desc = (f"heteroscedastic: {base.description or base.name}, each true edge at "
            f"{sigma_deg:g} deg x lognormal({spread:g}), unweighted")
    return RegimeCase(name, base.family, base.num_nodes, base.i, base.j, R, base.gt, None,
                      base.inlier, sigma_deg, desc, max(sigma_deg, 1.0))


def near_false_case(name: str, base: RegimeCase, *, low_deg: float = 5.0,
                    high_deg: float = 30.0, seed: int = 0) -> RegimeCase:
    """``base`` with each false edge drawn again ``U(low_deg, high_deg)`` off the truth
    (about a random axis) instead of Haar-random at least :data:`MIN_FALSE_DEG` off. What
    this tests: wrong matches close to the truth, as a registration stuck in a nearby
    minimum gives them; on a chain the odometry's drift explains most of them."""
    rng = rng_for(name, seed)
    bad = np.flatnonzero(~base.inlier) if base.inlier is not None else np.zeros(0, np.int64)
    angles = np.radians(rng.uniform(low_deg, high_deg, bad.size))
    R = base.R.copy()
    R[bad] = relative(base.gt, base.i[bad], base.j[bad]) @ rotation_about_axis(
        random_axes(bad.size, rng), angles)
    desc = (f"near: {base.description or base.name}, its false edges "
            f"{low_deg:g}-{high_deg:g} deg off the truth")
    return replace(base, name=name, R=R, description=desc)


def broken_odometry_case(name: str, base: RegimeCase, *, steps: int,
                         seed: int = 0) -> RegimeCase:
    """``base`` with ``steps`` of its odometry edges (consecutive ids), drawn at random,
    replaced by false rotations (at least :data:`MIN_FALSE_DEG` off the truth) and marked
    false. What this tests: a front end that lost its track and reported a wrong step,
    where the solver trusts the odometry (``odometry`` option, default ``auto``)."""
    rng = rng_for(name, seed)
    odometry = np.flatnonzero(base.odometry)
    if steps > odometry.size:
        raise ValueError(f"{steps} broken steps asked of {odometry.size} odometry edges")
    bad = np.sort(rng.choice(odometry, steps, replace=False))
    R = base.R.copy()
    R[bad] = false_rotations(relative(base.gt, base.i[bad], base.j[bad]), rng)
    inlier = np.ones(base.num_edges, bool) if base.inlier is None else base.inlier.copy()
    inlier[bad] = False
    desc = f"{base.description or base.name}, {steps} odometry steps false"
    return replace(base, name=name, R=R, inlier=inlier, description=desc)


def biased_odometry_case(name: str, base: RegimeCase, *, bias_deg: float) -> RegimeCase:
    """``base`` with every odometry measurement (consecutive ids) turned ``bias_deg``
    further about the z axis of its frame ``i`` (``R_ij <- Rz(bias) R_ij``), as a gyro's yaw
    bias turns an integrated odometry; the loop closures stay as measured, and the true /
    false split stays (a bias is no false edge: the oracle solves the biased odometry too).
    What this tests: odometry whose error grows along the chain linearly, where the loop
    tests assume a random walk's square root."""
    step = np.abs(base.i - base.j) == 1
    R = base.R.copy()
    R[step] = rotation_about_axis(np.array([0.0, 0.0, 1.0]), np.radians(bias_deg)) @ R[step]
    desc = f"{base.description or base.name}, odometry biased {bias_deg:g} deg a step"
    return replace(base, name=name, R=R, description=desc)


def identity_false_case(name: str, base: RegimeCase) -> RegimeCase:
    """``base`` with each false edge the identity rotation. What this tests: a front end
    that reports identity where a match failed; identity edges agree with each other around
    any loop of them, and with the truth wherever the true turn between the two ends is
    small."""
    bad = np.flatnonzero(~base.inlier) if base.inlier is not None else np.zeros(0, np.int64)
    R = base.R.copy()
    R[bad] = np.eye(3)
    desc = f"{base.description or base.name}, its false edges identity"
    return replace(base, name=name, R=R, description=desc)


def reversed_case(name: str, base: RegimeCase, *, seed: int = 0) -> RegimeCase:
    """``base`` with half its edges, drawn at random, given the other way round:
    ``(j, i, R_ij^T)``, the same measurement. What this tests: the input's edge direction,
    which the solver must read, not assume (odometry given as ``(k + 1, k)``)."""
    flip = rng_for(name, seed).random(base.num_edges) < 0.5
    i, j, R = base.i.copy(), base.j.copy(), base.R.copy()
    i[flip], j[flip] = base.j[flip], base.i[flip]
    R[flip] = np.swapaxes(base.R[flip], 1, 2)
    desc = f"{base.description or base.name}, half its edges given reversed"
    return replace(base, name=name, i=i, j=j, R=R, description=desc)


# ------------------------------------------------------- chains in pieces, revisited routes


def _measured_case(name: str, gt: FloatArray, odometry: list[tuple[int, int]],
                   true_pairs: list[tuple[int, int]], false_pairs: list[tuple[int, int]],
                   odo_noise_deg: float, loop_noise_deg: float, rng: np.random.Generator,
                   noise_model: str, desc: str) -> RegimeCase:
    """A chain-family case: noisy odometry and true closures, random false closures."""
    def arrays(pairs: list[tuple[int, int]]) -> tuple[IntArray, IntArray]:
        ij = np.asarray(pairs, np.int64).reshape(-1, 2)
        return ij[:, 0], ij[:, 1]

    (oi, oj), (ti, tj), (fi, fj) = arrays(odometry), arrays(true_pairs), arrays(false_pairs)
    R = np.concatenate([perturb(relative(gt, oi, oj), odo_noise_deg, rng, noise_model),
                        perturb(relative(gt, ti, tj), loop_noise_deg, rng, noise_model),
                        false_rotations(relative(gt, fi, fj), rng)])
    inlier = np.r_[np.ones(oi.size + ti.size, bool), np.zeros(fi.size, bool)]
    noise = max(odo_noise_deg, loop_noise_deg)
    return RegimeCase(name, "chain", gt.shape[0], np.r_[oi, ti, fi], np.r_[oj, tj, fj], R,
                      gt, None, inlier, noise, desc, max(noise, 1.0))


def pieces_case(name: str, num_nodes: int, *, closures: int, sessions: int = 1,
                dropped_odometry: float = 0.0, false_random: float = 0.0,
                odo_noise_deg: float = 1.5, loop_noise_deg: float = 2.0, seed: int = 0,
                noise_model: str = "folded") -> RegimeCase:
    """An odometry chain in pieces that only loop closures join. ``sessions`` independent
    trajectories of equal length, in turn (a multi-session map: no odometry between them);
    within them each odometry edge is missing with probability ``dropped_odometry`` (a lost
    track; but no gap within 4 ids of another or of a session's end), and each such gap is
    bridged by up to two short closures across it (the front end relocalizing: ends 0-2
    ids before the gap and 1-3 after it). Then ``closures`` random true closures and random
    false ones, ``false_random`` of all the closures, placed by chain_case's rules."""
    rng = rng_for(name, seed)
    length = num_nodes // sessions
    gt = np.concatenate([chain_trajectory(length, rng) for _ in range(sessions)])
    n = gt.shape[0]
    boundary = np.zeros(n - 1, bool)
    boundary[length - 1::length] = True  # no odometry between sessions
    drawn = rng.random(n - 1) < dropped_odometry
    linked = ~boundary
    for k in np.flatnonzero(drawn).tolist():  # gaps at least 5 ids from gaps and sessions'
        near = slice(max(0, k - 4), k + 5)  # ends: each piece has 5 nodes, each bridge
        if linked[near].all():  # stays in its session
            linked[k] = False
    odometry = [(k, k + 1) for k in np.flatnonzero(linked).tolist()]
    bad, add, _ = _closure_rules(n, odometry)
    true_pairs: list[tuple[int, int]] = []
    for k in np.flatnonzero(~linked).tolist():
        if (k + 1) % length == 0:
            continue  # a session boundary: nothing bridges it
        for _ in range(2):
            a = max(0, k - int(rng.integers(0, 3)))
            b = min(n - 1, k + 1 + int(rng.integers(1, 4)))
            if (a, b) not in true_pairs:
                true_pairs.append((a, b))
                add(a, b)
    true_pairs += _random_pairs(n, closures, rng, bad, add)
    total = int(round(len(true_pairs) / max(1e-9, 1.0 - false_random)))
    false_pairs = _random_pairs(n, total - len(true_pairs), rng, bad, add)
    desc = (f"chain of {n} keyframes in {sessions} session(s), {n - 1 - len(odometry)} "
            f"odometry gaps, {len(true_pairs)} true closures, {len(false_pairs)} false")
    return _measured_case(name, gt, odometry, true_pairs, false_pairs, odo_noise_deg,
                          loop_noise_deg, rng, noise_model, desc)


def revisit_case(name: str, lap_nodes: int, laps: int, *, runs: int,
                 false_random: float = 0.0, odo_noise_deg: float = 1.0,
                 loop_noise_deg: float = 2.0, seed: int = 0,
                 noise_model: str = "folded", trajectory: str = "smooth") -> RegimeCase:
    """A route driven ``laps`` times: every lap's rotations are the first lap's (along
    ``trajectory``, :data:`TRAJECTORIES`), each turned by a random 3 deg (RMS) rotation.
    The true closures come in ``runs`` runs, as a front end finds them on a revisited
    stretch: 6-19 closures from every second keyframe of a stretch of one lap to the same
    place (give or take 2 keyframes) on another. Random false closures are
    ``false_random`` of all the closures."""
    rng = rng_for(name, seed)
    first = TRAJECTORIES[trajectory](lap_nodes, rng)
    turn = np.radians(3.0) / np.sqrt(3.0)
    gt = np.concatenate([exp_map(rng.normal(0.0, turn, (lap_nodes, 3))) @ first
                         for _ in range(laps)])
    n = gt.shape[0]
    odometry = [(k, k + 1) for k in range(n - 1)]
    used: set[tuple[int, int]] = set()
    true_pairs: list[tuple[int, int]] = []
    made = 0
    while made < runs:
        la, lb = sorted(int(x) for x in rng.choice(laps, 2, replace=False))
        t0, k = int(rng.integers(0, lap_nodes - 40)), int(rng.integers(6, 20))
        shift = int(rng.integers(-2, 3))
        run = [(la * lap_nodes + t0 + 2 * s,
                lb * lap_nodes + min(lap_nodes - 1, max(0, t0 + 2 * s + shift)))
               for s in range(k)]
        if any(p in used for p in run):
            continue
        used.update(run)
        true_pairs += run
        made += 1
    count = int(round(len(true_pairs) * false_random / max(1e-9, 1.0 - false_random)))
    false_pairs = _random_pairs(
        n, count, rng, lambda a, b: b - a < 20 or (a, b) in used, lambda a, b: used.add((a, b)))
    desc = (f"route of {lap_nodes} keyframes driven {laps} times, {runs} runs of "
            f"{len(true_pairs)} true closures, {len(false_pairs)} false")
    return _measured_case(name, gt, odometry, true_pairs, false_pairs, odo_noise_deg,
                          loop_noise_deg, rng, noise_model, desc)


def grid_walk_case(name: str, num_nodes: int, side: int, *, closures: int,
                   false_random: float = 0.0, odo_noise_deg: float = 1.0,
                   loop_noise_deg: float = 2.0, seed: int = 0,
                   noise_model: str = "folded") -> RegimeCase:
    """A robot walking the streets of a ``side`` x ``side`` grid city, as the Manhattan
    datasets (M3500: 3,500 poses, 5,453 edges) are drawn: one block a step, turning left or
    right with probability 0.3, back where it meets the edge. ``closures`` true loop
    closures join poses at the same corner at least 6 steps apart, drawn from every such
    pair; random false closures are ``false_random`` of all the closures (ends at least 20
    apart). Rotations from :func:`chain_trajectory` (wrap it in :func:`planar_case` for a
    planar robot). What this tests: a pose graph whose closures come from revisits all
    over it, at every range of ids, many short loops and a few long ones."""
    rng = rng_for(name, seed)
    pos = np.zeros((num_nodes, 2), np.int64)
    step = np.array([1, 0])
    for k in range(1, num_nodes):
        if rng.random() < 0.3:
            step = np.array([-step[1], step[0]]) * (1 if rng.random() < 0.5 else -1)
        if not np.all((0 <= pos[k - 1] + step) & (pos[k - 1] + step < side)):
            step = -step
        pos[k] = pos[k - 1] + step
    at: dict[int, list[int]] = {}
    for k, cell in enumerate((pos[:, 0] * side + pos[:, 1]).tolist()):
        at.setdefault(cell, []).append(k)
    candidates = [(a, b) for ks in at.values() for x, a in enumerate(ks) for b in ks[x + 1:]
                  if b - a > 5]
    if len(candidates) < closures:
        raise ValueError(f"only {len(candidates)} revisits to draw {closures} closures from")
    pick = rng.choice(len(candidates), size=closures, replace=False)
    true_pairs = sorted(candidates[int(p)] for p in pick)
    used = set(true_pairs)
    count = int(round(closures * false_random / max(1e-9, 1.0 - false_random)))
    false_pairs = _random_pairs(num_nodes, count, rng,
                                lambda a, b: b - a < 20 or (a, b) in used,
                                lambda a, b: used.add((a, b)))
    gt = chain_trajectory(num_nodes, rng)
    desc = (f"grid walk of {num_nodes} poses on a {side} x {side} city, {closures} true "
            f"closures at revisited corners, {len(false_pairs)} false")
    case = _measured_case(name, gt, [(k, k + 1) for k in range(num_nodes - 1)], true_pairs,
                          false_pairs, odo_noise_deg, loop_noise_deg, rng, noise_model, desc)
    return replace(case, family="slam")


# ----------------------------------------------------------------------- SfM / dense


def dense_case(name: str, num_nodes: int, degree: float, *, outliers: float,
               noise_deg: float = 2.0, seed: int = 0,
               noise_model: str = "folded") -> RegimeCase:
    """Erdos-Renyi graph with mean degree ``degree`` (plus a random Hamiltonian path so it
    is connected), Haar ground truth, ``noise_deg`` noise, and a fraction ``outliers`` of
    all edges replaced by false rotations."""
    rng = rng_for(name, seed)
    n = num_nodes
    gt = random_rotations(n, rng)
    p = min(1.0, degree / (n - 1))
    a, b = np.triu_indices(n, 1)
    keep = rng.random(a.shape[0]) < p
    perm = rng.permutation(n)
    path = set(zip(np.minimum(perm[:-1], perm[1:]).tolist(),
                   np.maximum(perm[:-1], perm[1:]).tolist(), strict=True))
    pairs = set(zip(a[keep].tolist(), b[keep].tolist(), strict=True)) | path
    ij = np.asarray(sorted(pairs), np.int64)
    i, j = ij[:, 0], ij[:, 1]
    truth = relative(gt, i, j)
    R = perturb(truth, noise_deg, rng, noise_model)
    inlier = replace_with_false(R, truth, np.arange(i.shape[0]), outliers, rng)
    desc = (f"random graph N={n}, mean degree {2 * i.shape[0] / n:.0f}, noise "
            f"{noise_deg:g} deg, {outliers:.0%} outlier edges")
    return RegimeCase(name, "sfm", n, i, j, R, gt, None, inlier, noise_deg, desc,
                      max(noise_deg, 1.0))


def survey_case(name: str, strips: int, per_strip: int, *, false: float,
                grouped: bool = False, noise_deg: float = 2.0, overlap: int = 3,
                cross: int = 2, seed: int = 0, noise_model: str = "folded") -> RegimeCase:
    """A drone's lawnmower survey, a photogrammetry view graph: ``strips`` strips of
    ``per_strip`` nadir images, ids in capture order, every other strip flown the other
    way (heading turned 180 deg; each image's yaw, roll and pitch jittered by 5, 3 and 3
    deg). Images match the next ``overlap`` along the strip and those of the next strip
    within ``cross`` positions of the same ground spot (mean degree about 15). False
    matches are ``false`` of all edges: random pairs with random rotations, or where
    ``grouped`` (repetitive texture: fields, roofs) runs of five images matched to five
    of another place, one wrong rotation per run, so each run is mutually consistent.
    What this tests: a banded view graph between the SLAM and the dense SfM regimes, whose
    consecutive ids are true matches but no odometry."""
    rng = rng_for(name, seed)
    down = rotation_about_axis(np.array([[1.0, 0.0, 0.0]]), np.array([np.pi]))[0]
    x_axis, y_axis, z_axis = np.eye(3)
    ground: list[tuple[int, int]] = []
    gt = []
    for k in range(strips):
        for s in range(per_strip):
            ground.append((k, s if k % 2 == 0 else per_strip - 1 - s))
            yaw = np.pi * (k % 2) + np.radians(rng.normal(0.0, 5.0))
            roll, pitch = np.radians(rng.normal(0.0, 3.0, 2))
            body = (rotation_about_axis(x_axis[None], np.array([roll]))[0]
                    @ rotation_about_axis(y_axis[None], np.array([pitch]))[0]
                    @ rotation_about_axis(z_axis[None], np.array([yaw]))[0])
            gt.append((down @ body).T)
    truth = np.asarray(gt)
    n = truth.shape[0]
    image = {spot: k for k, spot in enumerate(ground)}
    pairs: set[tuple[int, int]] = set()
    for a, (strip, x) in enumerate(ground):
        near = [(strip, x + d) for d in range(1, overlap + 1)]
        near += [(strip + 1, x + d) for d in range(-cross, cross + 1)]
        for b in (image[spot] for spot in near if spot in image):
            pairs.add((min(a, b), max(a, b)))
    ti, tj = (np.asarray(v, np.int64) for v in zip(*sorted(pairs), strict=True))
    count = int(round(ti.size * false / max(1e-9, 1.0 - false)))
    if grouped:
        fi, fj, false_R = grouped_false_edges(truth, pairs, -(-count // 5), (5, 5), 30,
                                              noise_deg, rng, noise_model=noise_model)
    else:
        placed = _random_pairs(n, count, rng, lambda a, b: a == b or (a, b) in pairs,
                               lambda a, b: pairs.add((a, b)))
        fi, fj = np.asarray(placed, np.int64).reshape(-1, 2).T
        false_R = false_rotations(relative(truth, fi, fj), rng)
    R = np.concatenate([perturb(relative(truth, ti, tj), noise_deg, rng, noise_model),
                        false_R])
    inlier = np.r_[np.ones(ti.size, bool), np.zeros(fi.size, bool)]
    desc = (f"lawnmower survey, {strips} strips of {per_strip} images, {ti.size} true "
            f"matches, {fi.size} false ({'grouped' if grouped else 'random'})")
    return RegimeCase(name, "sfm", n, np.r_[ti, fi], np.r_[tj, fj], R, truth, None,
                      inlier, noise_deg, desc, max(noise_deg, 1.0))


def ellis_case(name: str, shared: Path, *, extra: float = 0.0, seed: int = 0) -> RegimeCase:
    """Ellis Island (GT cameras only), optionally with ``extra * E`` false edges: random
    unobserved pairs carrying random rotations; the original edges count as inliers. The
    graph is nearly complete (5,641 unobserved pairs, 28% of E), so beyond that the rest
    replace the measurements of random existing edges (which then count as outliers)."""
    bench = load_ellis_island(shared)
    ids = bench.graph.node_ids
    n = len(ids)
    gt = np.stack([bench.reference[k] for k in ids])
    e = bench.graph.edge_arrays()
    i, j, R = e.i.astype(np.int64), e.j.astype(np.int64), e.R.copy()
    inlier: BoolArray | None = None
    if extra:
        rng = rng_for(name, seed)
        observed = set(zip(i.tolist(), j.tolist(), strict=True))
        a, b = np.triu_indices(n, 1)
        free = np.asarray([k for k, p in enumerate(zip(a.tolist(), b.tolist(), strict=True))
                           if p not in observed])
        count = int(round(extra * i.shape[0]))
        added = min(count, free.shape[0])
        pick = np.sort(rng.choice(free, size=added, replace=False))
        ni, nj = a[pick].astype(np.int64), b[pick].astype(np.int64)
        nR = false_rotations(relative(gt, ni, nj), rng)
        inlier = np.r_[np.ones(i.shape[0], bool), np.zeros(added, bool)]
        if count > added:  # nearly complete graph: corrupt existing edges for the rest
            old = np.sort(rng.choice(i.shape[0], size=count - added, replace=False))
            R[old] = false_rotations(relative(gt, i[old], j[old]), rng)
            inlier[old] = False
        i, j, R = np.r_[i, ni], np.r_[j, nj], np.concatenate([R, nR])
    desc = "Ellis Island, 1DSfM measurements, GT cameras only"
    if extra:
        desc += f", + {extra:.0%} random edges"
    return RegimeCase(name, "sfm", n, i, j, R, gt, None, inlier, None, desc)


# ---------------------------------------------------------------------- real SE-Sync


def real_case(name: str, shared: Path, graph: str) -> RegimeCase:
    """An SE-Sync graph as measured (g2o rotations and information weights)."""
    bench = load_se_sync(shared, graph)
    ids = bench.graph.node_ids
    gt = np.stack([bench.reference[k] for k in ids])
    e = bench.graph.edge_arrays()
    w = None if np.all(e.weight == e.weight[0]) else e.weight.copy()
    sigma = float(np.degrees(1.0 / np.sqrt(np.median(e.weight))))
    return RegimeCase(name, "real", len(ids), e.i.astype(np.int64), e.j.astype(np.int64),
                      e.R.copy(), gt, w, None, None, f"{graph} as measured (g2o)", sigma)


def city10000_case(name: str, data: Path, wrong_hypotheses: bool = False) -> RegimeCase:
    """gtsam's City10000 (:func:`~benchmarks.datasets.load_city10000`), a planar robot's
    pose graph with ground truth, as headings (rotations about z: world-to-node ``R_i =
    Rz(-theta_i)``, so an edge measures ``R_i R_j^T = Rz(theta_j - theta_i)``). At each of
    the 200 steps where the front end gave two hypotheses, the one the ground truth agrees
    with (a real graph as measured, family ``real``), or with ``wrong_hypotheses`` the other
    one: a front end that lost its track 200 times, 2% of the steps (family ``slam``, the
    200 steps false). The noise scale handed to GNC-TLS is the true edges' spread about
    the ground truth (0.58 deg)."""
    h = load_city10000(data)
    gt = rotation_about_axis(np.array([0.0, 0.0, 1.0]), -h.truth)
    truth = h.truth[h.j] - h.truth[h.i]

    def off(theta: FloatArray) -> FloatArray:
        return np.abs(np.angle(np.exp(1j * (theta - truth))))

    two = ~np.isnan(h.alternative)
    right = np.where(two & (off(h.alternative) < off(h.measured)), h.alternative, h.measured)
    wrong = np.where(two & (off(h.alternative) < off(h.measured)), h.measured, h.alternative)
    theta = np.where(two, wrong, right) if wrong_hypotheses else right
    R = rotation_about_axis(np.array([0.0, 0.0, 1.0]), theta)
    sigma = float(np.degrees(np.std(np.angle(np.exp(1j * (right - truth))))))
    if not wrong_hypotheses:
        return RegimeCase(name, "real", h.truth.size, h.i, h.j, R, gt, None, None, None,
                          "City10000 as measured (gtsam data; headings)", sigma)
    return RegimeCase(name, "slam", h.truth.size, h.i, h.j, R, gt, None, ~two, None,
                      "City10000, its 200 two-hypothesis odometry steps at the wrong one",
                      sigma)


def city10000_regenerated_case(name: str, data: Path, *, noise_deg: float,
                               random_false: float = 0.0, groups: int = 0,
                               seed: int = 0) -> RegimeCase:
    """Headings regenerated on City10000's real topology against its ground truth
    (:func:`planar_topology_case`). The 200 two-hypothesis steps take the true heading
    difference too."""
    return planar_topology_case(name, load_city10000(data), "City10000's edges and truth",
                                noise_deg=noise_deg, random_false=random_false,
                                groups=groups, seed=seed)


def manhattan_regenerated_case(name: str, data: Path, *, noise_deg: float,
                               random_false: float = 0.0, groups: int = 0,
                               seed: int = 0) -> RegimeCase:
    """Headings regenerated on the Manhattan world's real topology
    (:func:`~benchmarks.datasets.load_manhattan`: 10,000 poses, 54,312 loop closures, mean
    degree 12.9), its file's headings taken as the truth (:func:`planar_topology_case`)."""
    return planar_topology_case(name, load_manhattan(data),
                                "the Manhattan world's edges, its headings as truth",
                                noise_deg=noise_deg, random_false=random_false,
                                groups=groups, seed=seed)


def planar_topology_case(name: str, h: PlanarHeadings, what: str, *, noise_deg: float,
                         random_false: float = 0.0, groups: int = 0,
                         seed: int = 0) -> RegimeCase:
    """Headings regenerated on a real planar graph's edges ``h.i, h.j`` against the headings
    ``h.truth`` (a planar robot: every rotation about z). Each edge measures the true heading
    difference plus ``N(0, noise_deg)``; ``random_false`` of the loop closures (``|i - j| !=
    1``) are off by a heading drawn uniformly from ``MIN_FALSE_DEG`` to 180 deg, either sign;
    ``groups`` runs of 5-10 closures are added between two stretches at least 50 ids apart,
    ``(a + s, b + s)``, all off by one heading of 20-180 deg (a 2D front end's repeated wrong
    match: perceptual aliasing). Family ``slam``: every generated false edge is known (the
    oracle row)."""
    n = h.truth.size
    rng = rng_for(name, seed)
    i, j = h.i, h.j
    theta = h.truth[j] - h.truth[i] + np.radians(noise_deg) * rng.standard_normal(i.size)
    inlier = np.ones(i.size, bool)
    loop = np.flatnonzero(np.abs(i - j) != 1)
    false = rng.choice(loop, int(round(random_false * loop.size)), replace=False)
    theta[false] += (rng.uniform(np.radians(MIN_FALSE_DEG), np.pi, false.size)
                     * rng.choice([-1.0, 1.0], false.size))
    inlier[false] = False
    gi: list[int] = []
    gj: list[int] = []
    for _ in range(groups):
        length = int(rng.integers(5, 11))
        a, b = 0, 0
        while b - a <= 50:
            a, b = sorted(int(x) for x in rng.integers(0, n - length, 2))
        gi.extend(range(a, a + length))
        gj.extend(range(b, b + length))
        theta = np.r_[theta, np.full(length, rng.uniform(np.radians(20.0), np.pi)
                                     * rng.choice([-1.0, 1.0]))]
    if groups:
        gi_, gj_ = np.array(gi, np.int64), np.array(gj, np.int64)
        theta[i.size:] += (h.truth[gj_] - h.truth[gi_]
                           + np.radians(noise_deg) * rng.standard_normal(gi_.size))
        i, j = np.r_[i, gi_], np.r_[j, gj_]
        inlier = np.r_[inlier, np.zeros(gi_.size, bool)]
    z = np.array([0.0, 0.0, 1.0])
    desc = f"{what}, headings at {noise_deg:g} deg"
    if random_false:
        desc += f", {random_false:.0%} of loop closures false"
    if groups:
        desc += f", {groups} runs ({len(gi)} closures) of grouped false closures"
    return RegimeCase(name, "slam", n, i, j, rotation_about_axis(z, theta),
                      rotation_about_axis(z, -h.truth), None, inlier, noise_deg, desc,
                      max(noise_deg, 1.0))


# ------------------------------------------------------------------------ case list

CaseBuilder = Callable[[Path], RegimeCase]


def all_cases(seed: int = 0, noise_model: str = "folded") -> dict[str, CaseBuilder]:
    """Every case of the suite, by name, in run order (cheap to call: builds nothing).

    ``seed`` and ``noise_model`` (:data:`NOISE_MODELS`) draw every generated case afresh;
    Ellis Island's own measurements and the ``real/`` cases do not change with them.
    """
    if noise_model not in NOISE_MODELS:
        raise ValueError(f"noise model must be one of {NOISE_MODELS}, got {noise_model!r}")
    def slam(name: str, graph: str, **kw: Any) -> tuple[str, CaseBuilder]:
        return name, lambda shared: slam_case(name, shared, graph, seed=seed,
                                              noise_model=noise_model, **kw)

    def chain(name: str, nodes: int, **kw: Any) -> tuple[str, CaseBuilder]:
        return name, lambda shared: chain_case(name, nodes, seed=seed,
                                               noise_model=noise_model, **kw)

    def dense(name: str, nodes: int, degree: float, outliers: float) -> tuple[str, CaseBuilder]:
        return name, lambda shared: dense_case(name, nodes, degree, outliers=outliers,
                                               seed=seed, noise_model=noise_model)

    def ellis(name: str, extra: float = 0.0) -> tuple[str, CaseBuilder]:
        return name, lambda shared: ellis_case(name, shared, extra=extra, seed=seed)

    def real(graph: str) -> tuple[str, CaseBuilder]:
        return f"real/{graph}", lambda shared: real_case(f"real/{graph}", shared, graph)

    def city(name: str, data: Path, wrong: bool) -> tuple[str, CaseBuilder]:
        return name, lambda shared: city10000_case(name, data, wrong)

    gtsam_data = find_gtsam_data()
    # gtsam's City10000 where the bench extra installed it (else absent: ``--list`` says so)
    city_cases = [] if gtsam_data is None else [
        city("real/city10000", gtsam_data, False),
        city("slam/city10000/lost-track200", gtsam_data, True)]

    cases: list[tuple[str, CaseBuilder]] = [
        # SLAM topologies, regenerated measurements. Outlier-only cases carry 1 deg noise.
        slam("slam/smallGrid3D/noise1", "smallGrid3D", noise_deg=1.0),
        slam("slam/smallGrid3D/noise5", "smallGrid3D", noise_deg=5.0),
        slam("slam/smallGrid3D/noise10", "smallGrid3D", noise_deg=10.0),
        slam("slam/smallGrid3D/noise20", "smallGrid3D", noise_deg=20.0),
        slam("slam/smallGrid3D/rand10", "smallGrid3D", random_false=0.10),
        slam("slam/smallGrid3D/rand20", "smallGrid3D", random_false=0.20),
        slam("slam/smallGrid3D/grouped", "smallGrid3D", groups=3),
        slam("slam/smallGrid3D/noise10+rand10", "smallGrid3D", noise_deg=10.0,
             random_false=0.10),
        slam("slam/parking-garage/noise5", "parking-garage", noise_deg=5.0),
        slam("slam/parking-garage/noise20", "parking-garage", noise_deg=20.0),
        slam("slam/parking-garage/rand5", "parking-garage", random_false=0.05),
        slam("slam/parking-garage/rand20", "parking-garage", random_false=0.20),
        slam("slam/parking-garage/grouped", "parking-garage", groups=8),
        slam("slam/parking-garage/noise5+rand5", "parking-garage", noise_deg=5.0,
             random_false=0.05),
        slam("slam/sphere2500/noise10", "sphere2500", noise_deg=10.0),
        slam("slam/sphere2500/rand5", "sphere2500", random_false=0.05),
        slam("slam/sphere2500/noise5+grouped", "sphere2500", noise_deg=5.0, groups=10),
        slam("slam/torus3D/noise1", "torus3D", noise_deg=1.0),
        slam("slam/torus3D/rand10", "torus3D", random_false=0.10),
        # Plain chains: odometry + sparse closures, no triangles.
        chain("chain/300/clean", 300, closures=20),
        chain("chain/300/rand20", 300, closures=16, false_random=0.20),
        chain("chain/1000/rand40", 1000, closures=36, false_random=0.40),
        chain("chain/1000/grouped30", 1000, closures=42, false_grouped=0.30),
        chain("chain/3000/mixed35", 3000, closures=100, false_random=0.15,
              false_grouped=0.20),
        # SfM / dense.
        ellis("sfm/ellis"),
        ellis("sfm/ellis+15", extra=0.15),
        ellis("sfm/ellis+30", extra=0.30),
        dense("sfm/dense100/out10", 100, 50, outliers=0.1),
        dense("sfm/dense100/out50", 100, 50, outliers=0.5),
        dense("sfm/dense400/out10", 400, 40, outliers=0.1),
        dense("sfm/dense400/out30", 400, 40, outliers=0.3),
        dense("sfm/dense400/out50", 400, 40, outliers=0.5),
        dense("sfm/dense1000/out30", 1000, 16, outliers=0.3),
        dense("sfm/sparse200/out30", 200, 10, outliers=0.3),
        # Real measurements.
        *(real(g) for g in ("smallGrid3D", "parking-garage", "sphere2500", "torus3D")),
        *city_cases,
    ]
    return dict(cases)


QUICK = ("slam/smallGrid3D/noise5", "slam/smallGrid3D/grouped", "chain/300/rand20",
         "sfm/dense100/out50", "real/smallGrid3D")
"""A small fast subset (``--quick``)."""
