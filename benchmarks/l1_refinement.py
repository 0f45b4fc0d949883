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

``--cross-validate`` asks instead whether cross-validation could make the choice: for each
case, least squares (Gauss-Newton from our solution) against the L1 IRLS (p 1, eps 0.3),
each refitted without one fold of the edges at a time and scored by the sum of the held-out
edges' weighted squared residual angles (whose expectation is the noise plus the estimate's
own error: the lower sum is the better estimator, whatever the noise). Two fold rules:
10 random folds of every edge (a fold that cuts the graph apart: "n/a"), and 5 folds of
the edges off a maximum spanning tree (the graph stays connected).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import minimum_spanning_tree

from benchmarks.datasets import shared_dir_or_say
from benchmarks.regime_cases import NOISE_MODELS, all_cases
from benchmarks.regimes import our_options
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.robust.gauss_newton import (
    gauss_newton_step,
    refine_least_squares,
    residual_angles,
)
from rotavg_ros.core.robust.l1_choice import held_out_difference, l1_fit, l1_floor
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


def cross_validation(start: FloatArray, i: IntArray, j: IntArray, R: FloatArray,
                     w: FloatArray, median: float, folds: IntArray) -> float | None:
    """Held-out ``sum w (r_L1^2 - r_LS^2)`` over the folds (negative: L1 predicts better;
    ``median``: the least-squares median standardized residual, whose fraction
    ``L1_FLOOR`` is the L1 fit's floor); None where a fold leaves the graph in pieces (a
    singular normal matrix)."""
    total = 0.0
    for k in range(int(folds.max()) + 1):
        try:  # the solver's fold (rotavg_ros.core.robust.l1_choice), on these fold labels
            total += held_out_difference(start, i, j, R, w, median, folds == k)
        except RuntimeError:  # SuperLU: exactly singular
            return None
    return total


def off_tree_folds(n: int, i: IntArray, j: IntArray, r: FloatArray, count: int) -> IntArray:
    """Fold labels 0..count-1 of the edges off a spanning tree (preferring small residuals
    ``r``), -1 on the tree: every fold's complement keeps the graph connected."""
    tree = minimum_spanning_tree(coo_matrix((1.0 + r / max(float(np.median(r)), 1e-12),
                                             (i, j)), shape=(n, n)).tocsr())
    tree = tree + tree.T
    on_tree = np.asarray(tree[i, j]).ravel() > 0
    folds = np.full(i.size, -1)
    off = np.flatnonzero(~on_tree)
    folds[off] = np.random.default_rng(0).permutation(off.size) % count
    return folds


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.l1_refinement", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", default="0,5", help="comma-separated case seeds")
    p.add_argument("--noise-model", choices=NOISE_MODELS, default="folded")
    p.add_argument("--cases", default=",".join(CASES), help="comma-separated case names")
    p.add_argument("--cross-validate", action="store_true",
                   help="print the cross-validation verdicts instead (module docstring)")
    args = p.parse_args(argv)
    shared = shared_dir_or_say("l1_refinement")
    if shared is None:
        return 0
    if args.cross_validate:
        return _cross_validate(shared, args)
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


def _solved(case: Any, shared: Path) -> tuple[FloatArray, IntArray, IntArray, FloatArray,
                                               FloatArray, FloatArray]:
    """Our default solution of ``case`` and its edges within 15 median residuals."""
    g = case.view_graph(None)
    res = RotationAverager(our_options(seed=0)).solve(g)
    start = res.rotations[[g.index_of(k) for k in range(case.num_nodes)]]
    e = g.edge_arrays()
    ids = np.asarray(g.node_ids)
    i, j = ids[e.i], ids[e.j]
    r = residual_angles(start, i, j, e.R)
    near = r < 15.0 * float(np.median(r))
    return start, i[near], j[near], e.R[near], e.weight[near], r[near]


def _cross_validate(shared: Path, args: argparse.Namespace) -> int:
    print("| seed | case | least squares / L1 median ° | better | 10 random folds | "
          "5 off-tree folds |")
    print("|---|---|---|---|---|---|")
    for seed in (int(s) for s in args.seeds.split(",")):
        builders = all_cases(seed, args.noise_model)
        for name in args.cases.split(","):
            case = builders[name](shared)
            start, i, j, R, w, r = _solved(case, shared)
            eps = l1_floor(r, w)  # as the solver's choice
            truth = dict(enumerate(case.gt))
            ls = refine_least_squares(start, i, j, R, w, iterations=20)
            l1 = l1_fit(ls, i, j, R, w, eps)
            m_ls = evaluate(dict(enumerate(ls)), truth).median_deg
            m_l1 = evaluate(dict(enumerate(l1)), truth).median_deg
            rand = np.random.default_rng(1).integers(0, 10, i.size)
            cells = []
            for folds in (rand, off_tree_folds(case.num_nodes, i, j, r, 5)):
                d = cross_validation(ls, i, j, R, w, float(np.median(np.sqrt(w) * r)), folds)
                cells.append("n/a" if d is None else
                             f"{'L1' if d < 0 else 'LS'} ({d / float(np.sum(w * r ** 2)):+.3f})")
            print(f"| {seed} | {name} | {m_ls:.3f} / {m_l1:.3f} | "
                  f"{'L1' if m_l1 < m_ls else 'LS'} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
