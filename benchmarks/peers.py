"""Wrappers around the peer rotation averagers that the benchmark compares against.

Every wrapper takes the project's problem format and returns the project's conventions:

* ``num_nodes`` nodes with unknown **world-to-node** rotations ``R_i``;
* edge ``k`` joins nodes ``i[k]`` and ``j[k]`` and carries ``R_ij[k] ~= R_i R_j^T``;
* an optional positive ``weight[k]`` per edge (inverse variance; ``None`` means all ones).

Each ``run_*`` function returns ``(rotations, wall_seconds)``: world-to-node rotations of all
``num_nodes`` nodes, shape ``(N, 3, 3)``, in the peer's own gauge (align before scoring), and
the wall time of the peer's solve call only (building its inputs and reading back its
outputs is not timed). The graph must be connected and have at most one edge per node pair.

The peers are optional dependencies (see ``requirements-bench.txt``); they are imported lazily
inside the functions, so this module imports without them. :func:`available_peers` says which
can run.

Peer conventions (each checked numerically on noise-free synthetic graphs with mixed edge
orientations: rotations recovered to < 1e-5 degrees; ``scripts/measure_peers.py --selfcheck``):

* **pycolmap** (COLMAP 4 / GLOMAP rotation averaging): ``Image.cam_from_world()`` is
  world-to-camera, like ours. A pose-graph edge ``(image_id1, image_id2)`` stores
  ``cam2_from_cam1 = R_2 R_1^T``, so our edge ``(i, j, R_ij)`` is added as
  ``image_id1 = j``, ``image_id2 = i`` with ``cam2_from_cam1 = R_ij`` (the other order
  fails).
* **GTSAM**: ``Rot3`` values are body-to-world, ``X_i = R_i^T``, and ``BetweenFactor`` /
  ``BinaryMeasurement(i, j, Z)`` measures ``Z ~= X_i^T X_j = R_i R_j^T``, so our ``R_ij`` is
  passed unchanged with keys ``(i, j)`` and the result is transposed back.
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from rotavg_ros.core.so3 import matrix_to_quat, project_to_so3
from rotavg_ros.core.types import FloatArray, IntArray

PeerFn = Callable[[int, ArrayLike, ArrayLike, ArrayLike, ArrayLike | None],
                  tuple[FloatArray, float]]
"""(num_nodes, i, j, R_ij, weight) -> (world-to-node rotations (N, 3, 3), wall seconds)."""

PEER_NAMES = ("pycolmap_half_norm", "gtsam_shonan_huber", "gtsam_chordal", "gtsam_gnc_tls")


def _has_module(name: str) -> Any:
    try:
        return importlib.import_module(name)
    except Exception:  # ImportError, or a binary that fails to load
        return None


def available_peers() -> dict[str, bool]:
    """Which peers can run here: ``{peer_name: importable_with_the_needed_api}``."""
    pycolmap = _has_module("pycolmap")
    gtsam = _has_module("gtsam")
    has_colmap = pycolmap is not None and all(
        hasattr(pycolmap, n)
        for n in ("run_rotation_averaging", "RotationEstimatorOptions", "PoseGraph")
    )
    has_shonan = gtsam is not None and hasattr(gtsam, "ShonanAveraging3")
    has_chordal = gtsam is not None and (
        hasattr(gtsam, "fastSyncRot3") or hasattr(gtsam, "InitializePose3")
    )
    return {
        "pycolmap_half_norm": has_colmap,
        "gtsam_shonan_huber": has_shonan,
        "gtsam_chordal": has_chordal,
        "gtsam_gnc_tls": has_chordal and gtsam is not None and hasattr(gtsam, "GncLMOptimizer"),
    }


def _prepare(
    num_nodes: int,
    i: ArrayLike,
    j: ArrayLike,
    R_ij: ArrayLike,
    weight: ArrayLike | None,
    parallel: bool = False,
) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
    """Validate the problem; returns int64 ``i, j``, float ``R`` (E,3,3) and weights (E,).
    ``parallel``: node pairs may be measured more than once (one factor each; GTSAM's
    factor graphs take them as they come)."""
    n = int(num_nodes)
    ii = np.asarray(i, dtype=np.int64).reshape(-1)
    jj = np.asarray(j, dtype=np.int64).reshape(-1)
    R = np.asarray(R_ij, dtype=np.float64)
    E = ii.shape[0]
    if n < 1:
        raise ValueError("num_nodes must be positive")
    if jj.shape[0] != E or R.shape != (E, 3, 3):
        raise ValueError(f"inconsistent shapes: i {ii.shape}, j {jj.shape}, R_ij {R.shape}")
    if E == 0 and n > 1:
        raise ValueError("no edges")
    if E and (min(ii.min(), jj.min()) < 0 or max(ii.max(), jj.max()) >= n):
        raise ValueError("node index out of range")
    if np.any(ii == jj):
        raise ValueError("self-loop edge")
    if not np.all(np.isfinite(R)):
        raise ValueError("non-finite relative rotation")
    if weight is None:
        w = np.ones(E)
    else:
        w = np.asarray(weight, dtype=np.float64).reshape(-1)
        if w.shape[0] != E or not np.all(np.isfinite(w)) or np.any(w <= 0):
            raise ValueError("weight must be E finite positive numbers")
    lo, hi = np.minimum(ii, jj), np.maximum(ii, jj)
    if not parallel and np.unique(lo * n + hi).shape[0] != E:
        raise ValueError("parallel edges: consolidate to one edge per node pair first")
    if n > 1:
        adj = coo_matrix((np.ones(E), (ii, jj)), shape=(n, n))
        ncomp, _ = connected_components(adj, directed=False)
        if ncomp != 1:
            raise ValueError(f"graph is not connected ({ncomp} components)")
    # Re-project so the peers see exact rotations (they normalise quaternions anyway).
    return ii, jj, project_to_so3(R), w


# --------------------------------------------------------------------------- pycolmap


def run_pycolmap_half_norm(
    num_nodes: int,
    i: ArrayLike,
    j: ArrayLike,
    R_ij: ArrayLike,
    weight: ArrayLike | None = None,
    *,
    random_seed: int = 0,
    max_rotation_error_deg: float = 180.0,
    quiet: bool = True,
    **options_overrides: Any,
) -> tuple[FloatArray, float]:
    """COLMAP/GLOMAP rotation averaging with IRLS half-norm (L1/2) weights.

    Calls ``pycolmap.run_rotation_averaging(options, pose_graph, reconstruction, [])`` with
    ``options.weight_type = RotationWeightType.HALF_NORM`` and otherwise COLMAP's defaults
    (maximum-spanning-tree initialisation, up to 5 L1 iterations, then up to 100 IRLS
    iterations). ``max_rotation_error_deg`` is COLMAP's post-solve pair filter, after which
    it keeps only the largest connected component; the default 180 disables it so that every
    node keeps a rotation (with COLMAP's own default, 10, Ellis Island loses a node).

    Known limitation (COLMAP's, not the wrapper's): the HALF_NORM IRLS weight is
    ``pow(|e|^2, -3/4)`` with no floor (``glomap/estimators/rotation_averaging_impl.cc``),
    so edges that the L1 phase fits exactly (bridges and other zero-residual edges of sparse
    SLAM graphs) get infinite or huge weights and COLMAP stops with "IRLS Cholesky
    factorization failed"; ``ridge_regularization`` does not help. This raises
    ``RuntimeError``. Any ``RotationEstimatorOptions`` field can be overridden by
    keyword (e.g. ``weight_type=pycolmap.RotationWeightType.GEMAN_MCCLURE``).

    Weights, when given, are passed as ``PoseGraphEdge.num_matches`` (scaled so the largest
    is 10^6) with ``reweighting = INLIER_MATCH_COUNT``, which multiplies each edge's IRLS
    weight by ``num_matches / max(num_matches)``; they also steer the spanning-tree
    initialisation. Without weights the reweighting is ``UNIFORM``.
    """
    import pycolmap

    ii, jj, R, w = _prepare(num_nodes, i, j, R_ij, weight)
    n = int(num_nodes)
    if quiet:
        pycolmap.logging.minloglevel = 2  # glog: ERROR and above only

    rec = pycolmap.Reconstruction()
    camera = pycolmap.Camera(
        camera_id=1, model="SIMPLE_PINHOLE", width=1, height=1, params=[1.0, 0.0, 0.0]
    )
    rec.add_camera_with_trivial_rig(camera)
    for k in range(n):
        # image_id = frame_id = node + 1 (COLMAP ids are 1-based by habit; 0 is also legal).
        rec.add_image_with_trivial_frame(pycolmap.Image(image_id=k + 1, camera_id=1))

    if weight is None:
        matches = np.ones(ii.shape[0], dtype=np.int64)
    else:
        matches = np.maximum(np.rint(w / w.max() * 1e6), 1).astype(np.int64)
    quats = matrix_to_quat(R)  # x, y, z, w
    pose_graph = pycolmap.PoseGraph()
    zero = np.zeros(3)
    for a, b, q, m in zip(ii.tolist(), jj.tolist(), quats, matches.tolist(), strict=True):
        edge = pycolmap.PoseGraphEdge(pycolmap.Rigid3d(pycolmap.Rotation3d(q), zero))
        edge.num_matches = int(m)
        # cam2_from_cam1 = R_2 R_1^T = R_ij  <=>  image 1 = node j, image 2 = node i.
        pose_graph.add_edge(b + 1, a + 1, edge)

    options = pycolmap.RotationEstimatorOptions()
    options.weight_type = pycolmap.RotationWeightType.HALF_NORM
    options.random_seed = int(random_seed)
    options.max_rotation_error_deg = float(max_rotation_error_deg)
    options.reweighting = (
        pycolmap.RotationAveragingReweighting.UNIFORM
        if weight is None
        else pycolmap.RotationAveragingReweighting.INLIER_MATCH_COUNT
    )
    for key, value in options_overrides.items():
        if not hasattr(options, key):
            raise TypeError(f"RotationEstimatorOptions has no field {key!r}")
        setattr(options, key, value)

    t0 = time.perf_counter()
    ok = pycolmap.run_rotation_averaging(options, pose_graph, rec, [])
    wall = time.perf_counter() - t0
    if not ok:
        raise RuntimeError(
            "pycolmap.run_rotation_averaging reported failure (see COLMAP's log, e.g. "
            "'IRLS Cholesky factorization failed')"
        )

    out = np.empty((n, 3, 3))
    for k in range(n):
        frame = rec.frame(k + 1)
        if not frame.has_pose():
            raise RuntimeError(f"pycolmap left node {k} without a rotation")
        out[k] = rec.image(k + 1).cam_from_world().rotation.matrix()
    return out, wall


# --------------------------------------------------------------------------- GTSAM


def _gtsam_rotations(values: Any, n: int) -> FloatArray:
    """World-to-node rotations from GTSAM ``Values`` of body-to-world ``Rot3`` keyed 0..n-1."""
    X = np.stack([np.asarray(values.atRot3(k).matrix(), dtype=np.float64) for k in range(n)])
    return np.ascontiguousarray(np.transpose(X, (0, 2, 1)))


def run_gtsam_shonan_huber(
    num_nodes: int,
    i: ArrayLike,
    j: ArrayLike,
    R_ij: ArrayLike,
    weight: ArrayLike | None = None,
    *,
    p: int = 3,
    sigma: float = 0.05,
    initial: str = "chordal",
    max_iterations: int | None = None,
) -> tuple[FloatArray, float]:
    """GTSAM Shonan averaging with a Huber loss (``ShonanAveragingParameters3.setUseHuber``).

    Measurements are ``BinaryMeasurementRot3(i, j, Rot3(R_ij), Isotropic.Sigma(3, s))`` and
    GTSAM wraps each noise model in ``Robust(Huber(k=1.345), ...)``. The Huber threshold is on
    the whitened Frobenius residual ``||X_j - X_i R_ij||_F / s``, so it sits at a chordal
    distance of ``1.345 s``. The noise scale ``s`` is ``sigma`` (radians) for every edge when
    ``weight`` is None, else ``1 / sqrt(weight)`` (weights are information values, as in g2o).
    The default ``sigma = 0.05`` puts the Huber corner at about 2.7 degrees.

    GTSAM cannot certify a robust cost, so certification is switched off and GTSAM then
    insists on a single rank (``pMin == pMax``; it throws otherwise): the problem is solved
    once, by Levenberg-Marquardt (``CeresDefaults``) on SO(p)^N, and rounded to SO(3). ``p``
    picks that rank. ``initial`` is ``"chordal"`` (``fastSyncRot3`` on the same
    measurements; deterministic; not timed) or ``"random"`` (GTSAM's ``initializeRandomly()``,
    whose generator is a process-wide static, so repeated calls differ).
    """
    import gtsam

    ii, jj, R, w = _prepare(num_nodes, i, j, R_ij, weight)
    n = int(num_nodes)
    sig = np.full(w.shape, float(sigma)) if weight is None else 1.0 / np.sqrt(w)

    measurements = gtsam.BinaryMeasurementsRot3()
    for a, b, M, s in zip(ii.tolist(), jj.tolist(), R, sig.tolist(), strict=True):
        noise = gtsam.noiseModel.Isotropic.Sigma(3, s)
        measurements.append(gtsam.BinaryMeasurementRot3(a, b, gtsam.Rot3(M), noise))

    lm = gtsam.LevenbergMarquardtParams.CeresDefaults()
    if max_iterations is not None:
        lm.setMaxIterations(int(max_iterations))
    params = gtsam.ShonanAveragingParameters3(lm)
    params.setUseHuber(True)
    params.setCertifyOptimality(False)
    shonan = gtsam.ShonanAveraging3(measurements, params)

    if initial == "random":
        init = shonan.initializeRandomly()
    elif initial == "chordal":
        init = gtsam.Values()
        R0, _ = run_gtsam_chordal(n, ii, jj, R, w)
        for k in range(n):
            init.insert(k, gtsam.Rot3(np.ascontiguousarray(R0[k].T)))
    else:
        raise ValueError(f"initial must be 'random' or 'chordal', not {initial!r}")

    t0 = time.perf_counter()
    values, _ = shonan.run(init, int(p), int(p))
    wall = time.perf_counter() - t0
    return _gtsam_rotations(values, n), wall


def run_gtsam_chordal(
    num_nodes: int,
    i: ArrayLike,
    j: ArrayLike,
    R_ij: ArrayLike,
    weight: ArrayLike | None = None,
    *,
    method: str = "auto",
    parallel: bool = False,
) -> tuple[FloatArray, float]:
    """GTSAM's chordal (linear, then projected) rotation initialisation.

    ``method="fastsync"`` calls ``gtsam.fastSyncRot3(graph)`` (FAST-Sync, METIS ordering, in
    the GTSAM 4.3 bindings) on ``BetweenFactorRot3`` factors with
    ``Isotropic.Sigma(3, 1/sqrt(weight))``. ``method="initialize_pose3"`` calls
    ``InitializePose3.computeOrientationsChordal(InitializePose3.buildPose3graph(graph))`` on
    ``BetweenFactorPose3`` factors with zero translation and a ``PriorFactorPose3`` anchoring
    node 0 (``buildPose3graph`` turns the prior into the anchor that the linear system needs).
    ``"auto"`` takes FAST-Sync when the bindings have it.
    """
    import gtsam

    ii, jj, R, w = _prepare(num_nodes, i, j, R_ij, weight, parallel)
    n = int(num_nodes)
    sig = 1.0 / np.sqrt(w)
    if method == "auto":
        method = "fastsync" if hasattr(gtsam, "fastSyncRot3") else "initialize_pose3"
    graph = gtsam.NonlinearFactorGraph()
    if method == "fastsync":
        for a, b, M, s in zip(ii.tolist(), jj.tolist(), R, sig.tolist(), strict=True):
            noise = gtsam.noiseModel.Isotropic.Sigma(3, s)
            graph.add(gtsam.BetweenFactorRot3(a, b, gtsam.Rot3(M), noise))
        t0 = time.perf_counter()
        values = gtsam.fastSyncRot3(graph)
        wall = time.perf_counter() - t0
        return _gtsam_rotations(values, n), wall
    if method != "initialize_pose3":
        raise ValueError(f"unknown method {method!r}")

    zero = np.zeros(3)
    for a, b, M, s in zip(ii.tolist(), jj.tolist(), R, sig.tolist(), strict=True):
        noise = gtsam.noiseModel.Isotropic.Sigma(6, s)
        graph.add(gtsam.BetweenFactorPose3(a, b, gtsam.Pose3(gtsam.Rot3(M), zero), noise))
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    t0 = time.perf_counter()
    values = gtsam.InitializePose3.computeOrientationsChordal(
        gtsam.InitializePose3.buildPose3graph(graph)
    )
    wall = time.perf_counter() - t0
    return _gtsam_rotations(values, n), wall


def run_gtsam_gnc_tls(
    num_nodes: int,
    i: ArrayLike,
    j: ArrayLike,
    R_ij: ArrayLike,
    weight: ArrayLike | None = None,
    *,
    sigma: float = np.radians(5.0),
    known_inliers: ArrayLike | None = None,
    inlier_probability: float = 0.99,
    max_iterations: int | None = None,
    parallel: bool = False,
) -> tuple[FloatArray, float]:
    """GTSAM graduated non-convexity with truncated least squares (``GncLMOptimizer``).

    Factors are ``BetweenFactorRot3(i, j, Rot3(R_ij), Isotropic.Sigma(3, s))`` (same key
    convention as :func:`run_gtsam_chordal`) plus a tight ``PriorFactorRot3`` fixing node 0
    at its chordal value (the gauge; it is passed as a known inlier). ``s`` is ``sigma``
    (radians, per tangent axis) for every edge when ``weight`` is None, else
    ``1 / sqrt(weight)``. ``GncLMParams`` get ``GncLossType.TLS`` and GTSAM's default number
    of GNC outer iterations (100) unless ``max_iterations`` is given; the TLS inlier
    threshold is GTSAM's chi-square bound at
    ``inlier_probability`` (``setInlierCostThresholdsAtProbability``; 0.99 with 3 degrees
    of freedom admits whitened residuals up to about 3.4, i.e. ``|log(R_ij^-1 R_i R_j^T)|
    <~ 3.4 s``). The start is the chordal solution (``fastSyncRot3`` on the same
    measurements; deterministic; not timed, like Shonan's start).

    ``known_inliers``: indices into the edge list (e.g. odometry edges) handed to
    ``GncLMParams.setKnownInliers`` (they keep weight 1 throughout). ``parallel``: node
    pairs may be measured more than once, each measurement its own factor.
    """
    import gtsam

    ii, jj, R, w = _prepare(num_nodes, i, j, R_ij, weight, parallel)
    n = int(num_nodes)
    sig = np.full(w.shape, float(sigma)) if weight is None else 1.0 / np.sqrt(w)
    R0, _ = run_gtsam_chordal(n, ii, jj, R, w, parallel=parallel)

    graph = gtsam.NonlinearFactorGraph()
    for a, b, M, s in zip(ii.tolist(), jj.tolist(), R, sig.tolist(), strict=True):
        noise = gtsam.noiseModel.Isotropic.Sigma(3, s)
        graph.add(gtsam.BetweenFactorRot3(a, b, gtsam.Rot3(M), noise))
    prior_index = ii.shape[0]
    graph.add(gtsam.PriorFactorRot3(0, gtsam.Rot3(np.ascontiguousarray(R0[0].T)),
                                    gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    init = gtsam.Values()
    for k in range(n):
        init.insert(k, gtsam.Rot3(np.ascontiguousarray(R0[k].T)))

    params = gtsam.GncLMParams(gtsam.LevenbergMarquardtParams())
    params.setLossType(gtsam.GncLossType.TLS)
    if max_iterations is not None:
        params.setMaxIterations(int(max_iterations))
    inliers = [prior_index]
    if known_inliers is not None:
        inliers += [int(k) for k in np.asarray(known_inliers, dtype=np.int64).reshape(-1)]
    params.setKnownInliers(sorted(set(inliers)))
    optimizer = gtsam.GncLMOptimizer(graph, init, params)
    optimizer.setInlierCostThresholdsAtProbability(float(inlier_probability))

    t0 = time.perf_counter()
    values = optimizer.optimize()
    wall = time.perf_counter() - t0
    return _gtsam_rotations(values, n), wall


PEERS: dict[str, PeerFn] = {
    "pycolmap_half_norm": run_pycolmap_half_norm,
    "gtsam_shonan_huber": run_gtsam_shonan_huber,
    "gtsam_chordal": run_gtsam_chordal,
    "gtsam_gnc_tls": run_gtsam_gnc_tls,
}
