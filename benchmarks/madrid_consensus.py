"""Benchmark: Madrid Metropolis (1DSfM, no ground truth), each method by the edges it explains.

Without ground truth the solutions are scored against the data and against each other: per
method, the median residual angle over all 23,784 measured relative rotations and the share
within 2, 5 and 10 deg (``R_ij ~= R_i R_j^T``, world-to-camera), then each pair's median and
mean angle after gauge alignment. Our default and ``paper`` profiles, and the installed peers
(GTSAM chordal, Shonan + Huber, GNC-TLS at 5 deg; pycolmap's L1/2, which may fail here).

    python -m benchmarks.madrid_consensus

Needs the shared data (``../shared`` or ``$ROTAVG_SHARED``); exits with a message without it.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from benchmarks import peers
from benchmarks.datasets import shared_dir_or_say
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.robust.gauss_newton import residual_angles
from rotavg_ros.core.solver import RotationAverager
from rotavg_ros.io.onedsfm import read_1dsfm_egs

PEER_METHODS = ("gtsam_chordal", "gtsam_shonan_huber", "gtsam_gnc_tls", "pycolmap_half_norm")


def main() -> int:
    shared = shared_dir_or_say("madrid_consensus")
    if shared is None:
        return 0
    graph = read_1dsfm_egs(shared / "data/1dsfm/Madrid_Metropolis/EGs.txt").graph
    e, n = graph.edge_arrays(), graph.num_nodes
    print(f"Madrid Metropolis: {n} cameras, {e.num_edges} edges (no ground truth)")
    solutions: dict[str, tuple[np.ndarray, float]] = {}
    for profile in ("default", "paper"):
        t0 = time.perf_counter()
        res = RotationAverager(SolverOptions.for_profile(profile, seed=0)).solve(graph)
        solutions[f"ours-{profile}"] = (np.stack([res.rotations[k] for k in range(n)]),
                                        time.perf_counter() - t0)
    available = peers.available_peers()
    for name in PEER_METHODS:
        if not available.get(name):
            print(f"{name}: not installed")
            continue
        try:
            solutions[name] = peers.PEERS[name](n, e.i, e.j, e.R, e.weight)
        except RuntimeError as exc:  # (pycolmap's IRLS Cholesky fails on this graph)
            print(f"{name}: failed ({exc})")
    print("\n| method | s | median residual ° | within 2° | within 5° | within 10° |")
    print("|---|---|---|---|---|---|")
    for name, (rot, wall) in solutions.items():
        r = np.degrees(residual_angles(rot, e.i, e.j, e.R))
        print(f"| {name} | {wall:.2f} | {np.median(r):.2f} | {np.mean(r < 2):.3f} | "
              f"{np.mean(r < 5):.3f} | {np.mean(r < 10):.3f} |")
    names = list(solutions)
    print("\nPairwise median / mean angle after alignment (°):\n")
    print("| | " + " | ".join(names) + " |")
    print("|---" * (len(names) + 1) + "|")
    for a in names:
        cells = []
        for b in names:
            st = evaluate(dict(enumerate(solutions[a][0])), dict(enumerate(solutions[b][0])))
            cells.append(f"{st.median_deg:.2f} / {st.mean_deg:.1f}")
        print(f"| {a} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
