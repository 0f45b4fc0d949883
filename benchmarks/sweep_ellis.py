"""Benchmark: random search over the dense-mode choices on Ellis Island (a GPU makes it cheap).

Samples ``--configs`` settings of (sigma, lr, init_scale, reweight_every, warmup,
iterations, tolerance) around the defaults, runs the whole pipeline for each (filter cached
per sigma; every depth candidate, the Eq. 3 choice) over ``--seeds`` seeds, and prints one
line per setting with the mean / median error against ground truth (worst and average over
seeds), sorted by the worst-seed mean. The defaults are always the first setting.

    python -m benchmarks.sweep_ellis --device cuda [--configs 100] [--seeds 0,1,2]

This is a search on the benchmark itself: a setting that wins here must also win over
seeds (and on other data) before it becomes a default.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import numpy as np

from benchmarks.datasets import load_ellis_island, shared_dir_or_say
from rotavg_ros.core.filter.edge_filter import filter_edges
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.solver import average_rotations

SPACE: dict[str, list[Any]] = {
    "sigma": [0.15, 0.2, 0.25, 0.3],
    "lr": [0.005, 0.01, 0.02],
    "init_scale": [1e-3, 1e-2, 1e-1],
    "reweight_every": [10, 25, 50],
    "warmup": [100, 200, 400],
    "iterations": [1000, 2000],
    "tolerance": [5e-4, 0.0],
}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--configs", type=int, default=100)
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--sample-seed", type=int, default=0)
    args = p.parse_args()
    shared = shared_dir_or_say("sweep_ellis")
    if shared is None:
        return 0
    bench = load_ellis_island(shared)
    e = bench.graph.edge_arrays()
    n = bench.graph.num_nodes
    w = e.weight / np.mean(e.weight)
    base = SolverOptions.from_flat(device=args.device)
    rng = np.random.default_rng(args.sample_seed)
    configs = [{k: getattr(base, k) for k in SPACE}]
    while len(configs) < args.configs:
        c = {k: v[rng.integers(len(v))] for k, v in SPACE.items()}
        if c not in configs:
            configs.append(c)
    filters = {}
    seeds = [int(s) for s in args.seeds.split(",")]
    rows = []
    t_start = time.perf_counter()
    for c in configs:
        sig = c["sigma"]
        if sig not in filters:
            filters[sig] = filter_edges(e.i, e.j, e.R, w, n, sig, True,
                                        base.filter.sigma_untested).kept
        k = filters[sig]
        means, medians = [], []
        for seed in seeds:
            opt = base.replace_flat(seed=seed, use_filter=False, **c)  # filtered above
            rot = average_rotations(n, e.i[k], e.j[k], e.R[k], w[k], opt).rotations
            st = evaluate(dict(zip(bench.graph.node_ids, rot, strict=True)), bench.reference)
            means.append(st.mean_deg)
            medians.append(st.median_deg)
        rows.append((max(means), float(np.mean(means)), max(medians), float(np.mean(medians)),
                     c))
        print(f"{len(rows):4d} worst mean {max(means):.3f} avg {np.mean(means):.3f} | worst "
              f"median {max(medians):.3f} | {c} | {time.perf_counter() - t_start:.0f} s",
              flush=True)
    print("\nbest by worst-seed mean (median <= 0.45 in every seed):")
    for worst, avg, wmed, amed, c in sorted(rows, key=lambda r: r[0])[:15]:
        if wmed <= 0.45:
            print(f"mean worst {worst:.3f} avg {avg:.3f}, median worst {wmed:.3f} avg "
                  f"{amed:.3f}: {c}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
