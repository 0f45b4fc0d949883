"""Benchmark: warm-started re-solve of a growing graph vs a cold solve (prints figures).

A synthetic view graph (default 2,000 nodes; a chain plus random pairs, 2 deg noise, 10%
gross outliers) is solved cold; then 1% more edges arrive and the graph is solved again,
once cold and once warm-started from the first solution (``RotationAverager.solve(...,
initial=..., initial_depth=...)``, as the node does). Prints wall times, their ratio and the
gauge-aligned errors against the ground truth.

    python -m benchmarks.bench_warm_start [--nodes 2000] [--degree 20] [--grow 0.01] [--device cpu]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.result import SolveResult
from rotavg_ros.core.so3 import random_rotations, rotation_about_axis
from rotavg_ros.core.solver import RotationAverager
from rotavg_ros.core.view_graph import ViewGraph


def synthetic_edges(n: int, degree: float, rng: np.random.Generator) -> list[tuple[int, int]]:
    pairs = {(k, k + 1) for k in range(n - 1)}
    want = int(degree * n / 2)
    while len(pairs) < want:
        a, b = rng.integers(0, n, size=2)
        if a != b:
            pairs.add((int(min(a, b)), int(max(a, b))))
    order = list(pairs)
    rng.shuffle(order)
    return order


def measure(R: np.ndarray, pairs: list[tuple[int, int]], rng: np.random.Generator,
            noise_deg: float, outliers: float) -> ViewGraph:
    g = ViewGraph()
    for k in range(R.shape[0]):
        g.add_node(k)
    i = np.array([p[0] for p in pairs])
    j = np.array([p[1] for p in pairs])
    Rij = R[i] @ R[j].transpose(0, 2, 1)
    axes = rng.normal(size=(len(pairs), 3))
    Rij = rotation_about_axis(axes, np.radians(rng.normal(0, noise_deg, len(pairs)))) @ Rij
    bad = rng.random(len(pairs)) < outliers
    Rij[bad] = random_rotations(int(bad.sum()), rng)
    for a, b, M in zip(i, j, Rij, strict=True):
        g.add_edge(a, b, M)
    return g


def timed(averager: RotationAverager, g: ViewGraph, **kw: object) -> tuple[SolveResult, float]:
    t0 = time.perf_counter()
    res = averager.solve(g, **kw)  # type: ignore[arg-type]
    return res, time.perf_counter() - t0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--nodes", type=int, default=2000)
    p.add_argument("--degree", type=float, default=20.0)
    p.add_argument("--grow", type=float, default=0.01)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="solver device: cpu, cuda or auto")
    args = p.parse_args()
    rng = np.random.default_rng(args.seed)
    R = random_rotations(args.nodes, rng)
    pairs = synthetic_edges(args.nodes, args.degree, rng)
    cut = int(len(pairs) / (1.0 + args.grow))
    gt = dict(enumerate(R))
    averager = RotationAverager(SolverOptions.from_flat(seed=args.seed, device=args.device))
    g0 = measure(R, pairs[:cut], np.random.default_rng(1), 2.0, 0.1)
    g1 = measure(R, pairs, np.random.default_rng(1), 2.0, 0.1)  # same first `cut` edges
    r0, t0 = timed(averager, g0)
    e0 = evaluate(dict(zip(r0.node_ids, r0.rotations, strict=True)), gt)
    prev = dict(zip(r0.node_ids, r0.rotations, strict=True))
    r_cold, t_cold = timed(averager, g1)
    r_warm, t_warm = timed(averager, g1, initial=prev, initial_depth=r0.depth)
    e_cold = evaluate(dict(zip(r_cold.node_ids, r_cold.rotations, strict=True)), gt)
    e_warm = evaluate(dict(zip(r_warm.node_ids, r_warm.rotations, strict=True)), gt)
    print(f"graph: {args.nodes} nodes, {cut} -> {len(pairs)} edges (+{args.grow:.0%})")
    print(f"first solve (cold):   {t0:7.2f} s  depth {r0.depth}  "
          f"mean {e0.mean_deg:.3f} deg  median {e0.median_deg:.3f} deg")
    print(f"re-solve cold:        {t_cold:7.2f} s  depth {r_cold.depth}  "
          f"mean {e_cold.mean_deg:.3f} deg  median {e_cold.median_deg:.3f} deg")
    print(f"re-solve warm:        {t_warm:7.2f} s  depth {r_warm.depth}  "
          f"mean {e_warm.mean_deg:.3f} deg  median {e_warm.median_deg:.3f} deg")
    print(f"warm / cold time: {t_warm / t_cold:.1%} (target <= 20%)  "
          f"median error warm - cold: {e_warm.median_deg - e_cold.median_deg:+.3f} deg")


if __name__ == "__main__":
    main()
