"""Benchmark / investigation: which Ellis Island cameras carry the mean error, and why.

1. Solves Ellis Island with the defaults and prints, for the ``--top`` cameras with the
   largest error: their edge count, how many of their edges agree with the ground truth
   within 5 deg, how many the filter kept, and how many kept edges agree with it.
2. ``--restore-seeds``: the experiment "restore every edge of a node that the filter leaves
   with only its tree edge" (a node none of whose other edges agrees with the tree), solved
   with each seed next to the unchanged pipeline. Not part of the solver (see the README).

    python scripts/ellis_weak_nodes.py [--top 12] [--restore-seeds 0,1,2,3,4,5,6,7]
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from rotavg_ros.datasets import load_ellis_island, shared_dir_or_say
from rotavg_ros.edge_filter import filter_edges
from rotavg_ros.metrics import evaluate
from rotavg_ros.so3 import geodesic_distance
from rotavg_ros.solver import RotationAverager, average_rotations
from rotavg_ros.solver_types import SolverOptions


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--top", type=int, default=12)
    p.add_argument("--restore-seeds", default="")
    p.add_argument("--device", default="cpu")
    args = p.parse_args()
    shared = shared_dir_or_say("ellis_weak_nodes")
    if shared is None:
        return 0
    bench = load_ellis_island(shared)
    g, e, n = bench.graph, bench.graph.edge_arrays(), bench.graph.num_nodes
    ids = g.node_ids
    opt = SolverOptions(device=args.device)
    res = RotationAverager(opt).solve(g)
    est = dict(zip(ids, res.rotations, strict=True))
    stats = evaluate(est, bench.reference)
    err = dict(zip(bench.reference.keys(), stats.errors, strict=True))
    gt = np.stack([bench.reference[k] for k in ids])
    gt_err = np.degrees(geodesic_distance(e.R, np.einsum("eab,ecb->eac", gt[e.i], gt[e.j])))
    kept = res.edge_inlier
    print(f"defaults: mean {stats.mean_deg:.3f} median {stats.median_deg:.3f}")
    print("| camera | error ° | edges | edges within 5° of GT | kept | kept and within 5° |")
    print("|---|---|---|---|---|---|")
    for cam in sorted(err, key=lambda k: -err[k])[:args.top]:
        v = g.index_of(cam)
        on = (e.i == v) | (e.j == v)
        good = on & (gt_err < 5.0)
        print(f"| {cam} | {err[cam]:.1f} | {on.sum()} | {good.sum()} | {(on & kept).sum()} | "
              f"{(good & kept).sum()} |")
    if not args.restore_seeds:
        return 0
    w = e.weight / np.mean(e.weight)
    base = filter_edges(e.i, e.j, e.R, w, n, opt.sigma, opt.use_support_count,
                        opt.sigma_untested)
    deg = np.bincount(e.i, minlength=n) + np.bincount(e.j, minlength=n)
    kdeg = np.bincount(e.i[base.kept], minlength=n) + np.bincount(e.j[base.kept], minlength=n)
    weak = (kdeg == 1) & (deg >= 2)
    restored = base.kept | weak[e.i] | weak[e.j]
    print(f"\nnodes left with only their tree edge: {[ids[v] for v in np.flatnonzero(weak)]}, "
          f"{int(restored.sum() - base.kept.sum())} edges restored")
    for name, mask in (("filter as is", base.kept), ("weak nodes restored", restored)):
        means = []
        for seed in (int(s) for s in args.restore_seeds.split(",")):
            o = SolverOptions(device=args.device, seed=seed, use_filter=False)  # pre-filtered
            rot, *_, depth = average_rotations(n, e.i[mask], e.j[mask], e.R[mask], w[mask], o)[:4]
            st = evaluate(dict(zip(ids, rot, strict=True)), bench.reference)
            means.append(st.mean_deg)
            print(f"{name}, seed {seed}: depth {depth}, mean {st.mean_deg:.3f} "
                  f"median {st.median_deg:.3f}", flush=True)
        print(f"{name}: mean over seeds {np.mean(means):.3f}, "
              f"range {min(means):.3f}-{max(means):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
