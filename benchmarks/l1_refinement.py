"""Probe: would an L1 refinement of the default solution help on clean sparse graphs?

``python -m benchmarks.l1_refinement [--seeds 0,5] [--noise-model folded] [--cases ...]``

On clean (no false edge) SLAM and chain cases of the regime benchmark, our sparse mode and
the verification fit least squares in effect (an entry-wise Huber loss whose delta is 30
median residuals), while pycolmap's L½ and GTSAM's Shonan with Huber beat it on some draws
under folded noise (an angle ``|N(0, s)|`` about a random axis: residuals peaked at zero).
For each case this solves with the default profile, then runs IRLS on the geodesic
residuals from that solution, ``w = max(r, eps)^(p - 2)`` (p = 1: L1; p = 0.5: L½), on the
edges within 15 median residuals, with ``eps`` a fraction of the median residual, and
prints the errors of each against the ground truth with the residual shape
(:func:`rotavg_ros.core.robust.noise.residual_shape`: 0.921 for Gaussian noise) that a
rule could gate the refinement on. Nothing here is used by the solver. Needs the shared
data (``../shared`` or ``$ROTAVG_SHARED``).
"""

from __future__ import annotations

import argparse

import numpy as np

from benchmarks.datasets import shared_dir_or_say
from benchmarks.regime_cases import NOISE_MODELS, all_cases
from benchmarks.regimes import our_options
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.robust.gauss_newton import gauss_newton_step, residual_angles
from rotavg_ros.core.robust.noise import residual_shape
from rotavg_ros.core.solver import RotationAverager
from rotavg_ros.core.types import FloatArray, IntArray

CASES = ("slam/smallGrid3D/noise1", "slam/smallGrid3D/noise10", "slam/smallGrid3D/noise20",
         "slam/parking-garage/noise5", "slam/sphere2500/noise10", "slam/torus3D/noise1",
         "chain/300/clean")
VARIANTS = ((1.0, 0.1), (1.0, 0.3), (0.5, 0.3))
"""(p, eps as a fraction of the median residual)."""


def irls(rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray, p: float,
         eps: float, iterations: int = 20) -> FloatArray:
    """IRLS for ``min sum w r^p`` on SO(3): one Gauss-Newton step per reweighting."""
    for _ in range(iterations):
        r = residual_angles(rot, i, j, R)
        rot, _ = gauss_newton_step(rot, i, j, R, w * np.maximum(r, eps) ** (p - 2.0))
    return rot


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.l1_refinement", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", default="0,5", help="comma-separated case seeds")
    p.add_argument("--noise-model", choices=NOISE_MODELS, default="folded")
    p.add_argument("--cases", default=",".join(CASES), help="comma-separated case names")
    args = p.parse_args(argv)
    shared = shared_dir_or_say("l1_refinement")
    if shared is None:
        return 0
    print("| seed | case | shape | default mean / median ° | "
          + " | ".join(f"p {q:g}, eps {e:g} median r" for q, e in VARIANTS) + " |")
    print("|---|---|---:|---|" + "---|" * len(VARIANTS))
    for seed in (int(s) for s in args.seeds.split(",")):
        builders = all_cases(seed, args.noise_model)
        for name in args.cases.split(","):
            case = builders[name](shared)
            g = case.view_graph(None)
            res = RotationAverager(our_options(seed=0)).solve(g)
            start = res.rotations[[g.index_of(k) for k in range(case.num_nodes)]]
            truth = dict(enumerate(case.gt))
            e = g.edge_arrays()
            ids = np.asarray(g.node_ids)
            i, j = ids[e.i], ids[e.j]
            r = residual_angles(start, i, j, e.R)
            scale = float(np.median(r))
            near = r < 15.0 * scale
            cells = []
            for exponent, eps in (VARIANTS):
                refined = irls(start, i[near], j[near], e.R[near], e.weight[near], exponent,
                               eps * scale)
                st = evaluate(dict(enumerate(refined)), truth)
                cells.append(f"{st.mean_deg:.3f} / {st.median_deg:.3f}")
            st0 = evaluate(dict(enumerate(start)), truth)
            shape = residual_shape(r / scale, near)
            print(f"| {seed} | {name} | {shape:.3f} | {st0.mean_deg:.3f} / {st0.median_deg:.3f} "
                  f"({res.verification}) | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
