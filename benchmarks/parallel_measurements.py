"""Node pairs measured more than once (``python -m benchmarks.parallel_measurements``).

A front end may send one pair twice: a loop closure re-observed (two true measurements), or
two hypotheses, one of them wrong (a false twin). The view graph merges each pair's
measurements into one edge (their chordal L1 median); option ``settle_parallel`` then sets
aside, after a first solve, those that disagree with the solution where others of their
pair agree, and solves again (:mod:`rotavg_ros.core.robust.parallel_measurements`).

Cases: regime cases (``benchmarks.regime_cases``) with a share of their true loop closures
sent a second time, false (``+false twins``) or true with fresh noise (``+true twins``),
each solved as is, and with the twins ``settle_parallel`` off and on; and gtsam's
City10000 with both hypotheses of its 200 two-hypothesis odometry steps sent (where the
``bench`` extra's gtsam ships its data). Prints mean / median error against the ground
truth, the solve's wall time, the measurements set aside and the pairs left undecided.
The peers take one edge per node pair and are not run here.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks import peers
from benchmarks import regime_cases as rc
from benchmarks.datasets import find_gtsam_data, load_city10000, shared_dir_or_say
from benchmarks.regimes import our_options
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.solver import RotationAverager
from rotavg_ros.core.types import FloatArray, IntArray
from rotavg_ros.core.view_graph import ViewGraph

TWIN_CASES = (
    (0, "folded", "chain/1000/rand40", 0.3),
    (0, "folded", "slam/sphere2500/rand5", 0.2),
    (1, "tangent", "chain/3000/mixed35", 0.3),
    (0, "folded", "slam/parking-garage/rand20", 0.2),
    (2, "anisotropic", "slam/smallGrid3D/rand10", 0.3),
    (3, "folded", "chain/300/rand20", 0.5),
)
"""(seed, noise model, regime case, share of its true loop closures sent twice)."""


def solve(num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, gt: FloatArray,
          settle: bool) -> str:
    """One solve of the measurements as given (parallel ones merged by the view graph)."""
    g = ViewGraph()
    for k in range(num_nodes):
        g.add_node(k)
    g.add_edges(i.tolist(), j.tolist(), R)
    options = our_options("default", seed=0, settle_parallel=settle)
    t0 = time.perf_counter()
    res = RotationAverager(options).solve(g)
    wall = time.perf_counter() - t0
    s = evaluate(dict(enumerate(res.rotations)), dict(enumerate(gt)))
    return (f"{s.mean_deg:.3f} / {s.median_deg:.3f} | {wall:.2f} | "
            f"{res.num_parallel_set_aside} | {res.num_parallel_undecided}")


def gnc_tls(num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, gt: FloatArray,
            sigma_deg: float) -> str:
    """GTSAM GNC-TLS with each measurement its own factor (the peer; ``bench`` extra)."""
    try:
        rot, wall = peers.run_gtsam_gnc_tls(num_nodes, i, j, R, None,
                                            sigma=float(np.radians(sigma_deg)), parallel=True)
    except ImportError:
        return "not installed | | | "
    s = evaluate(dict(enumerate(rot)), dict(enumerate(gt)))
    return f"{s.mean_deg:.3f} / {s.median_deg:.3f} | {wall:.2f} | – | –"


def twin_rows(shared: Path) -> list[str]:
    rows = []
    for seed, model, name, share in TWIN_CASES:
        case = rc.all_cases(seed, model)[name](shared)
        rng = np.random.default_rng(7)
        inlier = np.ones(case.num_edges, bool) if case.inlier is None else case.inlier
        loops = np.flatnonzero(inlier & (np.abs(case.i - case.j) != 1))
        pick = rng.choice(loops, int(share * loops.size), replace=False)
        gt = np.asarray(case.gt)
        truth = rc.relative(gt, case.i[pick], case.j[pick])
        twins = {"false": rc.false_rotations(truth, rng),
                 "true": rc.perturb(truth, case.noise_deg or 1.0, rng, model)}
        label = f"{name} ({model} {seed})"
        as_is = solve(case.num_nodes, case.i, case.j, case.R, gt, True)
        rows.append(f"| {label} as is | | {as_is} |")
        for kind, R2 in twins.items():
            i, j = np.r_[case.i, case.i[pick]], np.r_[case.j, case.j[pick]]
            R = np.concatenate([case.R, R2])
            for settle in (False, True):
                rows.append(f"| {label} + {pick.size} {kind} twins | {'on' if settle else 'off'}"
                            f" | {solve(case.num_nodes, i, j, R, gt, settle)} |")
            rows.append(f"| {label} + {pick.size} {kind} twins | GTSAM GNC-TLS | "
                        f"{gnc_tls(case.num_nodes, i, j, R, gt, case.sigma_deg)} |")
    return rows


def city_rows() -> list[str]:
    data = find_gtsam_data()
    if data is None:
        print("City10000: gtsam's data folder not found (the bench extra); skipped")
        return []
    h = load_city10000(data)
    z = np.array([0.0, 0.0, 1.0])
    gt = rc.rotation_about_axis(z, -h.truth)
    two = ~np.isnan(h.alternative)
    R = np.concatenate([rc.rotation_about_axis(z, h.measured),
                        rc.rotation_about_axis(z, h.alternative[two])])
    i, j = np.r_[h.i, h.i[two]], np.r_[h.j, h.j[two]]
    label = f"City10000, both hypotheses of {int(two.sum())} steps"
    sigma = rc.city10000_case("city", data).sigma_deg  # the true edges' spread
    return [f"| {label} | {'on' if settle else 'off'} | "
            f"{solve(h.truth.size, i, j, R, gt, settle)} |" for settle in (False, True)] + [
        f"| {label} | GTSAM GNC-TLS | {gnc_tls(h.truth.size, i, j, R, gt, sigma)} |"]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--no-city", action="store_true", help="skip City10000")
    args = ap.parse_args(argv)
    shared = shared_dir_or_say("parallel_measurements")
    print("| case | settle_parallel | mean / median deg | wall s | set aside | undecided |")
    print("|---|---|---|---|---|---|")
    rows = [] if shared is None else twin_rows(shared)
    for row in rows + ([] if args.no_city else city_rows()):
        print(row, flush=True)


if __name__ == "__main__":
    main()
