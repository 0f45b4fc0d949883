"""Benchmark: solve time, time per iteration and peak memory against graph size.

Synthetic graphs (a chain plus random pairs, mean degree ``--degree``, 2 deg noise, 10% gross
outliers) of each size in ``--sizes`` are solved with the default options, each in a fresh
process so its peak RSS is its own. Prints one line per size: nodes, edges, solver mode,
wall time, time per DMF iteration, peak RSS, mean / median error against the ground truth.

    python -m benchmarks.bench_scale [--sizes 500,1000,2000,5000,10000] [--degree 20] [--device cpu]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import queue
import resource
import time
from typing import Any

import numpy as np


def _child(n: int, degree: float, seed: int, device: str, q: Any) -> None:
    try:  # python -m benchmarks.bench_scale from the repository root
        from benchmarks.bench_warm_start import measure, synthetic_edges
    except ImportError:  # cd benchmarks && python bench_scale.py
        from bench_warm_start import measure, synthetic_edges  # type: ignore[no-redef]

    from rotavg_ros.core.metrics import evaluate
    from rotavg_ros.core.options import SolverOptions
    from rotavg_ros.core.so3 import random_rotations
    from rotavg_ros.core.solver import RotationAverager

    rng = np.random.default_rng(seed)
    R = random_rotations(n, rng)
    g = measure(R, synthetic_edges(n, degree, rng), np.random.default_rng(seed + 1), 2.0, 0.1)
    marks: list[tuple[float, str]] = []
    opts = SolverOptions.from_flat(seed=seed, device=device,
                                   progress=lambda s: marks.append((time.perf_counter(), s)))
    averager = RotationAverager(opts)
    t0 = time.perf_counter()
    res = averager.solve(g)
    wall = time.perf_counter() - t0
    mode = next((s.split()[0] for _, s in marks if " mode:" in s), "?")
    fit_start = next((t for t, s in marks if " mode:" in s), t0)
    iters = sum(res.iterations_by_depth.values()) if mode == "dense" else 0
    per_iter = (t0 + wall - fit_start) / iters * 1e3 if iters else float("nan")
    st = evaluate(dict(zip(res.node_ids, res.rotations, strict=True)), dict(enumerate(R)))
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    gpu = 0.0
    if device.startswith("cuda"):
        import torch

        gpu = torch.cuda.max_memory_allocated() / 2**20
    q.put((n, g.edge_arrays().num_edges, mode, wall, per_iter, rss, st.mean_deg, st.median_deg,
           gpu))


def main() -> None:
    # The spawned children import numpy before rotavg_ros: give them the package's
    # single-threaded OpenBLAS (rotavg_ros.BLAS_THREADS_VARIABLES). Without it a 2,000-node
    # solve here ran for over 10 minutes at 3 GB instead of 10 s at 0.4 GB.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", default="500,1000,2000,5000,10000")
    p.add_argument("--degree", type=float, default=20.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="solver device: cpu, cuda or auto")
    args = p.parse_args()
    print("| nodes | edges | mode | wall s | ms / iteration (all depths) | peak RSS MB "
          "| mean ° | median ° |")
    print("|---|---|---|---|---|---|---|---|")
    ctx = mp.get_context("spawn")
    for n in (int(x) for x in args.sizes.split(",")):
        q = ctx.Queue()
        proc = ctx.Process(target=_child, args=(n, args.degree, args.seed, args.device, q))
        proc.start()
        while True:  # a child that dies (an import error, out of memory) must not hang us
            try:
                n_, e, mode, wall, per_iter, rss, mean, med, gpu = q.get(timeout=1.0)
                break
            except queue.Empty:
                if not proc.is_alive():
                    raise SystemExit(f"bench_scale: the {n}-node run died "
                                     f"(exit status {proc.exitcode})") from None
        proc.join()
        print(f"| {n_} | {e} | {mode} | {wall:.1f} | {per_iter:.2f} | {rss:.0f} | "
              f"{mean:.3f} | {med:.3f} |" + (f" GPU peak {gpu:.0f} MB" if gpu else ""),
              flush=True)


if __name__ == "__main__":
    main()
