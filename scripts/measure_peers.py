"""Measure the peer rotation averagers (rotavg_ros.peers) on the shared benchmark graphs.

Graphs:
* ``ellis``: 1DSfM Ellis Island, paper protocol (only the 227 cameras with ground truth and
  the 20,010 edges between them), scored against the Bundler ground truth.
* ``smallGrid3D``, ``parking-garage``, ``sphere2500``, ``torus3D``: SE-Sync g2o pose graphs
  (rotation part, weight = trace of the rotation information block / 3), scored against the
  certified optimum of the weighted rotation-only problem (``reference/se_sync_3d``).

Scoring: global gauge ``G`` (``R_est_i ~= R_ref_i G``) from the chordal L2 fit
``project_to_so3(sum_i R_ref_i^T R_est_i)``, refined by a few Weiszfeld (chordal L1)
iterations; then per-node angle ``||Log(R_est_i (R_ref_i G)^T)||`` in degrees.

Each (graph, peer) run happens in a spawned child process with a wall-clock cap
(``--timeout``); a run that exceeds it is reported as TIMEOUT.

Usage::

    python scripts/measure_peers.py                  # all graphs, all available peers
    python scripts/measure_peers.py --graphs ellis --peers pycolmap_half_norm
    python scripts/measure_peers.py --selfcheck      # noise-free convention check only
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing as mp
import os
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rotavg_ros import peers
from rotavg_ros.so3 import (
    geodesic_distance,
    project_to_so3,
    quat_to_matrix,
    random_rotations,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

SE_SYNC_GRAPHS = ("smallGrid3D", "parking-garage", "sphere2500", "torus3D")
ALL_GRAPHS = ("ellis", *SE_SYNC_GRAPHS)


def default_shared() -> Path:
    env = os.environ.get("ROTAVG_SHARED")
    if env:
        return Path(env)
    here = Path(__file__).resolve().parents[1]
    for cand in (here / "shared", here.parent / "shared", Path("/work/shared")):
        if (cand / "data").is_dir():
            return cand
    return Path("/work/shared")


@dataclass(frozen=True)
class Problem:
    name: str
    num_nodes: int
    i: IntArray
    j: IntArray
    R: FloatArray
    weight: FloatArray | None
    R_ref: FloatArray
    ref_kind: str


def load_ellis(shared: Path) -> Problem:
    d = np.load(shared / "data/1dsfm/Ellis_Island/Ellis_Island.npz")
    edges = d["edges"].astype(np.int64)
    has_gt = d["has_gt"].astype(bool)
    keep = has_gt[edges[:, 0]] & has_gt[edges[:, 1]]
    new_id = np.cumsum(has_gt) - 1
    e = new_id[edges[keep]]
    return Problem(
        name="ellis",
        num_nodes=int(has_gt.sum()),
        i=e[:, 0],
        j=e[:, 1],
        R=np.asarray(d["R_rel"][keep], dtype=np.float64),
        weight=None,
        R_ref=np.asarray(d["R_gt"][has_gt], dtype=np.float64),
        ref_kind="ground truth",
    )


def load_g2o_rotations(path: Path) -> tuple[int, IntArray, IntArray, FloatArray, FloatArray]:
    """Rotation part of an EDGE_SE3:QUAT g2o file: ``(n, i, j, R_ij, weight)``.

    The edge quaternion (x y z w) is ``R_i^T R_j`` for body-to-world vertices, i.e. our
    ``Q_i Q_j^T`` with world-to-body ``Q``. Weight is trace of the rotation information
    block (upper-triangular entries 15, 18, 20 of 21) divided by 3.
    """
    ii: list[int] = []
    jj: list[int] = []
    qs: list[list[float]] = []
    ws: list[float] = []
    vertices: set[int] = set()
    for line in path.read_text().splitlines():
        tok = line.split()
        if not tok:
            continue
        if tok[0].startswith("VERTEX_SE3"):
            vertices.add(int(tok[1]))
        elif tok[0].startswith("EDGE_SE3"):
            ii.append(int(tok[1]))
            jj.append(int(tok[2]))
            qs.append([float(x) for x in tok[6:10]])
            info = [float(x) for x in tok[10:31]]
            ws.append((info[15] + info[18] + info[20]) / 3.0)
    i = np.asarray(ii, dtype=np.int64)
    j = np.asarray(jj, dtype=np.int64)
    n = max(len(vertices), int(max(i.max(), j.max())) + 1)
    return n, i, j, quat_to_matrix(np.asarray(qs)), np.asarray(ws)


def load_se_sync(shared: Path, name: str) -> Problem:
    n, i, j, R, w = load_g2o_rotations(shared / f"data/se_sync_3d/{name}.g2o")
    R_ref = np.load(shared / f"reference/se_sync_3d/{name}.npz")["R_ref"]
    return Problem(name, n, i, j, R, w, np.asarray(R_ref, np.float64), "certified optimum")


def load(shared: Path, name: str) -> Problem:
    return load_ellis(shared) if name == "ellis" else load_se_sync(shared, name)


def align_gauge(R_est: FloatArray, R_ref: FloatArray, iters: int = 10) -> FloatArray:
    """``G`` in SO(3) with ``R_est_i ~= R_ref_i G``: chordal L2 fit, then Weiszfeld L1 steps."""
    P = np.transpose(R_ref, (0, 2, 1)) @ R_est  # each ~= G
    G = project_to_so3(P.sum(axis=0)[None])[0]
    for _ in range(iters):
        r = np.sqrt(np.einsum("kab,kab->k", P - G, P - G))
        w = 1.0 / np.maximum(r, 1e-9)
        G = project_to_so3(np.einsum("k,kab->ab", w, P)[None])[0]
    return G


def angular_errors_deg(R_est: FloatArray, R_ref: FloatArray) -> FloatArray:
    G = align_gauge(R_est, R_ref)
    return np.degrees(geodesic_distance(R_est, R_ref @ G))


PeerFn = Callable[..., tuple[FloatArray, float]]


@contextlib.contextmanager
def quiet_native_stdout() -> Iterator[None]:
    """Silence C-level writes to fd 1 (SuiteSparse's "CHOLMOD warning" lines from COLMAP)."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 1)
            yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def _child(fn: PeerFn, prob: Problem, kwargs: dict[str, Any], repeat: int, q: Any) -> None:
    try:
        walls = []
        for _ in range(max(repeat, 1)):
            with quiet_native_stdout():
                R, wall = fn(prob.num_nodes, prob.i, prob.j, prob.R, prob.weight, **kwargs)
            walls.append(wall)
        q.put(("ok", R, float(np.median(walls))))
    except Exception as exc:  # reported to the parent
        q.put(("error", f"{type(exc).__name__}: {exc}", 0.0))


def run_bounded(
    fn: PeerFn, prob: Problem, kwargs: dict[str, Any], timeout: float, repeat: int = 1
) -> tuple[str, Any, float]:
    """Run ``fn`` on ``prob`` in a fresh (spawned) child; ``("timeout", None, s)`` past the cap.

    Spawn, not fork: a forked child inherits the parent's already-started OpenMP/TBB thread
    pools (the self-check ran the peers in the parent), which made pycolmap ~10x slower.
    """
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    proc = ctx.Process(target=_child, args=(fn, prob, kwargs, repeat, q))
    t0 = time.perf_counter()
    proc.start()
    try:
        status, payload, wall = q.get(timeout=timeout)
    except Exception:
        proc.kill()
        proc.join()
        return "timeout", None, time.perf_counter() - t0
    proc.join()
    return status, payload, wall


def selfcheck(seed: int = 0) -> bool:
    """Noise-free synthetic graph: every peer must recover the rotations (< 1e-3 deg)."""
    rng = np.random.default_rng(seed)
    n = 40
    R = random_rotations(n, rng)
    pairs = np.array([(a, b) for a in range(n) for b in range(a + 1, n) if rng.random() < 0.25])
    # Make sure of connectivity with a chain, and mix edge orientations (i > j too).
    chain = np.array([(k, k + 1) for k in range(n - 1)])
    pairs = np.unique(np.concatenate([pairs, chain]), axis=0)
    flip = rng.random(len(pairs)) < 0.5
    pairs[flip] = pairs[flip][:, ::-1]
    i, j = pairs[:, 0], pairs[:, 1]
    Rij = R[i] @ np.transpose(R[j], (0, 2, 1))
    w = rng.uniform(0.5, 2.0, size=len(i))
    ok = True
    runs: list[tuple[str, PeerFn, dict[str, Any], FloatArray | None]] = [
        ("pycolmap_half_norm", peers.run_pycolmap_half_norm, {}, None),
        ("pycolmap_half_norm[weighted]", peers.run_pycolmap_half_norm, {}, w),
        ("gtsam_shonan_huber", peers.run_gtsam_shonan_huber, {}, None),
        ("gtsam_shonan_huber[weighted]", peers.run_gtsam_shonan_huber, {}, w),
        ("gtsam_chordal[fastsync]", peers.run_gtsam_chordal, {"method": "fastsync"}, w),
        (
            "gtsam_chordal[initialize_pose3]",
            peers.run_gtsam_chordal,
            {"method": "initialize_pose3"},
            w,
        ),
    ]
    avail = peers.available_peers()
    for label, fn, kw, weight in runs:
        if not avail.get(label.split("[")[0], False):
            print(f"  {label:34s} not available")
            continue
        with quiet_native_stdout():
            R_est, _ = fn(n, i, j, Rij, weight, **kw)
        err = angular_errors_deg(R_est, R).max()
        # The transposed (wrong-convention) reading must fail, so the check has teeth.
        bad = angular_errors_deg(np.transpose(R_est, (0, 2, 1)), R).max()
        good = err < 1e-3 and bad > 1.0
        ok &= good
        print(
            f"  {label:34s} max err {err:.2e} deg (transposed reading {bad:6.1f} deg) "
            f"{'OK' if good else 'FAIL'}"
        )
    return ok


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shared", type=Path, default=default_shared())
    ap.add_argument("--graphs", nargs="+", default=list(ALL_GRAPHS), choices=ALL_GRAPHS)
    ap.add_argument("--peers", nargs="+", default=list(peers.PEER_NAMES), choices=peers.PEER_NAMES)
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds per (graph, peer)")
    ap.add_argument("--repeat", type=int, default=3, help="solves per run; median wall reported")
    ap.add_argument("--shonan-p", type=int, default=3)
    ap.add_argument(
        "--shonan-sigma",
        type=float,
        default=0.05,
        help="Huber noise scale (rad) for unweighted graphs (Ellis)",
    )
    ap.add_argument("--shonan-init", choices=("random", "chordal"), default="chordal")
    ap.add_argument(
        "--threads",
        type=int,
        default=1,
        help="OMP_NUM_THREADS for the peer runs (0: leave the environment alone)",
    )
    ap.add_argument("--selfcheck", action="store_true", help="only the synthetic check")
    args = ap.parse_args(argv)
    if args.threads > 0:
        # Set before any peer starts its OpenMP pool; spawned children inherit it. On a busy
        # 2-core machine, COLMAP's multi-threaded IRLS spin-waits and runs ~10x slower.
        os.environ["OMP_NUM_THREADS"] = str(args.threads)
    print(f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', '(unset)')}, cpus={os.cpu_count()}")

    avail = peers.available_peers()
    print("available peers:", avail)
    print("noise-free convention check:")
    if not selfcheck():
        print("convention check FAILED")
        return 1
    if args.selfcheck:
        return 0

    peer_kwargs: dict[str, dict[str, Any]] = {
        "pycolmap_half_norm": {},
        "gtsam_shonan_huber": {
            "p": args.shonan_p,
            "sigma": args.shonan_sigma,
            "initial": args.shonan_init,
        },
        "gtsam_chordal": {},
    }
    header = (
        f"{'graph':15s} {'peer':20s} {'nodes':>6s} {'edges':>6s} "
        f"{'mean_deg':>9s} {'median_deg':>10s} {'wall_s':>8s}"
    )
    print(header)
    print("-" * len(header))
    for gname in args.graphs:
        prob = load(args.shared, gname)
        print(f"# {gname}: scored against the {prob.ref_kind}", flush=True)
        for pname in args.peers:
            if not avail[pname]:
                print(f"{gname:15s} {pname:20s} not installed")
                continue
            status, payload, wall = run_bounded(
                peers.PEERS[pname], prob, peer_kwargs[pname], args.timeout, args.repeat
            )
            row = f"{gname:15s} {pname:20s} {prob.num_nodes:6d} {len(prob.i):6d} "
            if status == "ok":
                err = angular_errors_deg(payload, prob.R_ref)
                print(row + f"{err.mean():9.3f} {np.median(err):10.3f} {wall:8.3f}", flush=True)
            elif status == "timeout":
                print(row + f"TIMEOUT after {wall:.0f} s", flush=True)
            else:
                print(row + f"ERROR {payload}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
