"""Investigation: would an early choice between the depth candidates cost accuracy?

For each dense regime case (family ``sfm``, and optionally the synthetic scale graphs of
:mod:`benchmarks.bench_scale`), the default profile's edge filter runs, then every depth
candidate is fitted alone on the kept edges to its end (as the solver fits it, same seed
and width). Printed per depth: the Eq. 3 selection cost at iterations 200, 400 and 600 and
at the end, the steps run, and the error of that depth's rotations against the ground
truth (DMF alone, before the verification). Per case: the depth the solver's rule picks
(lowest final cost) and the depth an early choice at iteration 400 would pick.

    python -m benchmarks.depth_halving [--cases sfm/ellis,...] [--scale 2000,10000]

Needs the shared data (``../shared`` or ``$ROTAVG_SHARED``); exits with a message without it.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable

import numpy as np

from benchmarks.bench_warm_start import measure, synthetic_edges
from benchmarks.datasets import shared_dir_or_say
from benchmarks.regime_cases import all_cases
from rotavg_ros.core.depth_choice import rotations_from_factor, selection_cost
from rotavg_ros.core.dmf import FitSpec, fit_symmetric
from rotavg_ros.core.filter.edge_filter import filter_edges
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.so3 import random_rotations
from rotavg_ros.core.types import FloatArray, IntArray
from rotavg_ros.core.view_graph import ViewGraph

CHECKPOINTS = (200, 400, 600)
EARLY = 400


def _recorder(costs: dict[int, float],
              edges: tuple[IntArray, IntArray, FloatArray, FloatArray]
              ) -> Callable[[int, FloatArray], bool]:
    """A fit monitor that records the Eq. 3 cost at :data:`CHECKPOINTS` into ``costs``."""

    def monitor(step: int, H: FloatArray) -> bool:
        if step in CHECKPOINTS:
            costs[step] = selection_cost(H, *edges)
        return False

    return monitor


def depth_table(name: str, g: ViewGraph, gt: FloatArray) -> None:
    """Fit every depth on the filtered edges of ``g`` (node ids ``0 .. N-1`` = indices of
    ``gt``) and print the table."""
    n = g.num_nodes
    e = g.edge_arrays()
    w = e.weight / np.mean(e.weight)
    opt = SolverOptions.for_profile("default", device="cpu")
    f = opt.filter
    kept = filter_edges(e.i, e.j, e.R, w, n, f.sigma, f.use_support_count,
                        f.sigma_untested).kept
    edges = (e.i[kept], e.j[kept], e.R[kept], w[kept])
    final: dict[int, float] = {}
    early: dict[int, float] = {}
    print(f"{name}: {n} nodes, {e.num_edges} edges, {int((~kept).sum())} filtered")
    for depth in opt.dense.depths:
        costs: dict[int, float] = {}
        monitor = _recorder(costs, edges)
        spec = FitSpec(depth=depth, hidden_width=opt.dense.width_for(n),
                       seed=opt.runtime.seed + depth, device="cpu", cuda_graph=False)
        t0 = time.perf_counter()
        fit = fit_symmetric(n, *edges, opt.dense, spec, monitor=monitor)
        wall = time.perf_counter() - t0
        final[depth] = selection_cost(fit.H, *edges)
        early[depth] = costs.get(EARLY, final[depth])
        st = evaluate(dict(enumerate(rotations_from_factor(fit.H))), dict(enumerate(gt)))
        shown = "  ".join(f"@{s} {costs[s]:.6g}" if s in costs else f"@{s} –"
                          for s in CHECKPOINTS)
        print(f"  depth {depth}: {shown}  end {final[depth]:.6g} ({fit.iterations} steps, "
              f"{wall:.1f} s)  mean {st.mean_deg:.3f} median {st.median_deg:.3f}")
    chosen = min(final, key=lambda d: final[d])
    at_early = min(early, key=lambda d: early[d])
    spread = (max(final.values()) - final[chosen]) / final[chosen]
    print(f"  chosen at the end: depth {chosen}; at iteration {EARLY}: depth {at_early}; "
          f"final costs within {100 * spread:.3f}% of each other")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", default=None, help="comma-separated regime case names "
                   "(default: every sfm case)")
    p.add_argument("--scale", default="", help="also bench_scale's synthetic graphs of these "
                   "sizes (mean degree 20, 2 deg noise, 10%% outliers), e.g. 2000,10000")
    args = p.parse_args()
    shared = shared_dir_or_say("depth_halving")
    if shared is None:
        return 0
    cases = all_cases()
    names = (args.cases.split(",") if args.cases
             else [c for c in cases if c.startswith("sfm/")])
    for name in names:
        c = cases[name](shared)
        depth_table(name, c.view_graph(), c.gt)
    for size in filter(None, args.scale.split(",")):
        n = int(size)
        rng = np.random.default_rng(0)
        truth = random_rotations(n, rng)
        g = measure(truth, synthetic_edges(n, 20.0, rng), np.random.default_rng(1), 2.0, 0.1)
        depth_table(f"synthetic {n}", g, truth)
    return 0


if __name__ == "__main__":
    sys.exit(main())
