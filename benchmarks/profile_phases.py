"""Benchmark: where the time of one solve goes, phase by phase, on a chosen device.

Loads a shared-data graph (Ellis Island by default), runs the edge filter and then each depth
candidate's DMF fit on its own (one after the other, so each time is that fit alone), and
prints filter time, per-depth fit time, iterations, ms per iteration and the error of that
depth's rotations against the reference. Then it times the whole ``RotationAverager.solve``
(candidates as the solver schedules them) ``--repeat`` times and prints each wall time.

    python -m benchmarks.profile_phases [--graph ellis] [--device cpu|cuda] [--dtype float32]

Needs the shared data (``../shared`` or ``$ROTAVG_SHARED``); exits with a message without it.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import torch

from benchmarks.datasets import load_ellis_island, load_se_sync, shared_dir_or_say
from rotavg_ros.core.depth_choice import rotations_from_factor
from rotavg_ros.core.dmf import FitSpec, fit_symmetric
from rotavg_ros.core.filter.edge_filter import filter_edges
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.solver import RotationAverager


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--graph", default="ellis")
    p.add_argument("--device", default="cpu")
    p.add_argument("--dtype", default=SolverOptions().dense.dtype)
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--no-cuda-graphs", action="store_true",
                   help="CUDA: launch every kernel from Python, one candidate at a time")
    args = p.parse_args()
    shared = shared_dir_or_say("profile_phases")
    if shared is None:
        return 0
    bench = load_ellis_island(shared) if args.graph == "ellis" else load_se_sync(shared,
                                                                                 args.graph)
    opt = SolverOptions.from_flat(device=args.device, dtype=args.dtype,
                                  cuda_graphs=not args.no_cuda_graphs)
    e = bench.graph.edge_arrays()
    n = bench.graph.num_nodes
    w = e.weight / np.mean(e.weight)
    print(f"{bench.name}: {n} nodes, {e.num_edges} edges, device {args.device}, "
          f"dtype {args.dtype}, CUDA graphs {opt.runtime.cuda_graphs}, "
          f"torch {torch.__version__}, threads {torch.get_num_threads()}")
    if args.device.startswith("cuda"):
        print(f"gpu: {torch.cuda.get_device_name()}")
    t0 = time.perf_counter()
    filt = filter_edges(e.i, e.j, e.R, w, n, opt.filter.sigma, opt.filter.use_support_count,
                        opt.filter.sigma_untested)
    print(f"filter: {time.perf_counter() - t0:.3f} s ({filt.num_removed} removed)")
    k = filt.kept
    width = opt.dense.width_for(n)
    for depth in opt.dense.depths:
        spec = FitSpec(depth=depth, hidden_width=width, seed=opt.runtime.seed + depth,
                       device=args.device, cuda_graph=opt.runtime.cuda_graphs)
        _sync(args.device)
        t0 = time.perf_counter()
        fit = fit_symmetric(n, e.i[k], e.j[k], e.R[k], w[k], opt.dense, spec)
        _sync(args.device)
        dt = time.perf_counter() - t0
        rot = rotations_from_factor(fit.H)
        st = evaluate(dict(zip(bench.graph.node_ids, rot, strict=True)), bench.reference)
        print(f"depth {depth}: {dt:.3f} s, {fit.iterations} iterations, "
              f"{dt / max(fit.iterations, 1) * 1e3:.3f} ms/iteration, "
              f"mean {st.mean_deg:.3f} median {st.median_deg:.3f}")
    for r in range(args.repeat):
        t0 = time.perf_counter()
        res = RotationAverager(opt).solve(bench.graph)
        wall = time.perf_counter() - t0
        st = evaluate(dict(zip(res.node_ids, res.rotations, strict=True)), bench.reference)
        print(f"full solve {r + 1}: {wall:.3f} s, depth {res.depth}, "
              f"mean {st.mean_deg:.3f} median {st.median_deg:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
