"""Large graphs (issue 14): ``python -m benchmarks.large_graphs``.

Five generated graphs of 2,000-10,648 nodes, larger than any case of the record
(:mod:`benchmarks.regimes`) or the stress variants (:mod:`benchmarks.regime_stress`), drawn
with the suite's generators (:mod:`benchmarks.regime_cases`): an odometry chain of 10,000
keyframes with 200 true loop closures and 30% false ones; a route driven ten times (10 x
1,000 keyframes, closures in 60 runs, 20% false); a robot walking a 40 x 40 grid city for
10,000 steps (2,000 true closures, 20% false); a 22^3 lattice pose graph (10,648 poses,
30,492 edges, grid3D's topology) with 10% false closures; a random view graph of 2,000
nodes, mean degree 20, 30% outliers. They check that the solver's accuracy and time carry
over to graphs of the size a long SLAM session or a large SfM scene produces.

Each case runs ours, the oracle (our solve on the true edges only) and GTSAM chordal by
default; ``--peers`` adds every installed peer (GNC-TLS takes minutes on the lattice:
``--timeout`` bounds each run). One line per case and method: mean / median error (deg)
and time, as :func:`benchmarks.regimes.run_method` measures them (a forked child per run).
No shared data needed.

    python -m benchmarks.large_graphs [--seed 0] [--cases chain,lattice] [--peers]
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from benchmarks import peers
from benchmarks.regime_cases import (
    RegimeCase,
    chain_case,
    dense_case,
    grid_walk_case,
    lattice_case,
    revisit_case,
)
from benchmarks.regimes import (
    OURS,
    OURS_NOFILTER,
    OURS_PAPER,
    methods_for,
    run_method,
)

DEFAULT_METHODS = (OURS, "oracle", "gtsam_chordal")
"""The methods run without ``--peers``."""


def large_cases(seed: int) -> list[Callable[[], RegimeCase]]:
    """The cases, as builders (each draws its graph when called)."""
    return [
        lambda: chain_case("large/chain/10000/rand30", 10_000, closures=200,
                           false_random=0.30, seed=seed),
        lambda: revisit_case("large/revisit/10x1000-rand20", 1000, 10, runs=60,
                             false_random=0.20, seed=seed),
        lambda: grid_walk_case("large/grid-walk/10000/rand20", 10_000, 40, closures=2000,
                               false_random=0.20, seed=seed),
        lambda: lattice_case("large/lattice/22/rand10", 22, random_false=0.10, seed=seed),
        lambda: dense_case("large/dense2000-deg20/out30", 2000, 20, outliers=0.3,
                           seed=seed),
    ]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cases", help="comma-separated substrings of the cases' names")
    p.add_argument("--peers", action="store_true", help="every installed peer too")
    p.add_argument("--timeout", type=float, default=600.0, help="per case and method, s")
    args = p.parse_args()
    wanted = args.cases.split(",") if args.cases else [""]
    available = peers.available_peers()
    for build in large_cases(args.seed):
        case = build()
        if not any(part in case.name for part in wanted):
            continue
        print(f"{case.name}: {case.num_nodes} nodes, {case.num_edges} edges", flush=True)
        for method, runnable in methods_for(case, available):
            if (not runnable or method in (OURS_PAPER, OURS_NOFILTER)
                    or not (args.peers or method in DEFAULT_METHODS)):
                continue
            r = run_method(case, method, args.timeout)
            cells = (f"{r.mean_deg:8.3f} {r.median_deg:8.3f} {r.wall_s:7.1f} s"
                     if r.status == "ok" else r.status)
            print(f"  {method:18s} {cells}  {r.note[:110]}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
