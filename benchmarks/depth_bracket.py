"""Evidence for ``DenseFitOptions.bracket_depths``: every depth candidate, or only the
shallowest and the deepest?

For each dense-mode regime case (family ``sfm`` of :mod:`benchmarks.regimes`) and the dense
graphs of :mod:`benchmarks.regime_stress` plus four more (300, 150, 600 and 250 nodes at
40%, 60%, 20% and 20% outliers), it solves with the default profile twice, with
``bracket_depths`` on (the default: depths 2 and 8) and off (2, 4, 6 and 8), and prints
each solve's mean / median error against the ground truth, the depth chosen and the wall
time in process. ``same`` marks a case whose two solves have the same errors to the printed
digit.

    python -m benchmarks.depth_bracket [--seed 0] [--noise-model folded] [--cases sfm,stress]

Needs the shared data (``../shared`` or ``$ROTAVG_SHARED``) for the Ellis Island cases.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from functools import partial

from benchmarks.datasets import shared_dir_or_say
from benchmarks.regime_cases import NOISE_MODELS, RegimeCase, all_cases, dense_case
from benchmarks.regime_stress import stress_cases
from benchmarks.regimes import our_options
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.solver import RotationAverager

AD_HOC_DENSE = (
    # (name, nodes, mean degree, outlier share, noise in deg): dense graphs beside the
    # stress variants' five
    ("adhoc/dense300-deg30/out40-noise3", 300, 30, 0.4, 3.0),
    ("adhoc/dense150-deg60/out60", 150, 60, 0.6, 2.0),
    ("adhoc/dense600-deg20/out20-noise8", 600, 20, 0.2, 8.0),
    ("adhoc/dense250-deg8/out20", 250, 8, 0.2, 2.0),
)


def solve(case: RegimeCase, bracket: bool) -> tuple[float, float, int, float]:
    """``(mean deg, median deg, depth chosen, wall s)`` of one default-profile solve."""
    g = case.view_graph(None)
    options = our_options("default", seed=0, device="cpu", bracket_depths=bracket)
    t0 = time.perf_counter()
    res = RotationAverager(options).solve(g)
    wall = time.perf_counter() - t0
    rot = {k: res.rotations[g.index_of(k)] for k in range(case.num_nodes)}
    st = evaluate(rot, dict(enumerate(case.gt)))
    return st.mean_deg, st.median_deg, res.depth, wall


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seed", type=int, default=0, help="the cases' draw")
    p.add_argument("--noise-model", choices=NOISE_MODELS, default="folded")
    p.add_argument("--cases", default="sfm,stress", help="sfm, stress or both")
    args = p.parse_args()
    shared = shared_dir_or_say("depth_bracket")
    if shared is None:
        return 0
    builders: list[tuple[str, Callable[[], RegimeCase]]] = []
    if "sfm" in args.cases:
        suite = all_cases(args.seed, args.noise_model)
        builders += [(n, partial(suite[n], shared)) for n in suite if n.startswith("sfm/")]
    if "stress" in args.cases:
        stress = [b() for b in stress_cases(shared, args.seed, args.noise_model)]
        builders += [(c.name, partial(lambda c: c, c)) for c in stress if "/dense" in c.name]
        builders += [(n, partial(dense_case, n, k, d, outliers=o, noise_deg=s, seed=args.seed,
                                 noise_model=args.noise_model))
                     for n, k, d, o, s in AD_HOC_DENSE]
    print("case: bracket (depths 2, 8) | every candidate (2, 4, 6, 8): mean / median deg, "
          "depth chosen, wall s")
    same_count = 0
    for name, build in builders:
        case = build()
        runs = [solve(case, bracket) for bracket in (True, False)]
        same = f"{runs[0][0]:.3f}/{runs[0][1]:.3f}" == f"{runs[1][0]:.3f}/{runs[1][1]:.3f}"
        same_count += same
        cells = [f"{m:.3f}/{med:.3f} d{d} {w:.1f}s" for m, med, d, w in runs]
        print(f"{name:36s} {cells[0]} | {cells[1]}{'  same' if same else ''}", flush=True)
    print(f"the same errors on {same_count} of {len(builders)} cases")
    return 0


if __name__ == "__main__":
    sys.exit(main())
