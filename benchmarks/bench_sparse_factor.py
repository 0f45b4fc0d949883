"""Benchmark: SuperLU's supernode settings on the core's sparse SPD systems.

``python -m benchmarks.bench_sparse_factor [--repeats 20]``

For the graph Laplacians of the regime benchmark's SLAM and chain graphs (every edge at
weight 1, in the graph's shared fill-reducing order, as the Gauss-Newton and GNC steps
factor them) and for each graph's chordal relaxation (the 3N x 3N block system), prints
the time of one factorization with SciPy's default supernode settings and with
:func:`rotavg_ros.core.sparse_factor.factor_spd`'s, their ratio, the factor's size and the
largest difference between the two solutions of one right-hand side. Then, for the same
Laplacians and City10000's (where gtsam's data is installed), the time of one solve of 96
right-hand sides (the leverage probes' width) in one SuperLU call and in blocks of
:data:`~rotavg_ros.core.sparse_factor.SOLVE_COLUMNS` (:func:`solve_by_blocks`, which the
core uses since 2026-12-08 where the right-hand sides exceed ``WIDE_BYTES``), and whether
the two solutions are the same bit for bit. Needs the
shared data (``../shared`` or ``$ROTAVG_SHARED``); exits with a message without it.
"""

from __future__ import annotations

import argparse
import functools
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.sparse.linalg import splu

from benchmarks.datasets import shared_dir_or_say
from benchmarks.regime_cases import all_cases
from rotavg_ros.core import chordal_init
from rotavg_ros.core.robust.gauss_newton import EliminationOrder, anchored_laplacian
from rotavg_ros.core.sparse_factor import SOLVE_COLUMNS, factor_spd, solve_by_blocks

CASES = ("slam/smallGrid3D/rand10", "slam/parking-garage/rand5", "slam/sphere2500/rand5",
         "slam/torus3D/rand10", "chain/1000/grouped30", "chain/3000/mixed35")
WIDE_CASES = CASES + ("real/city10000",)
"""The graphs of the wide-solve table (City10000 where gtsam's data is installed)."""
PROBE_COLUMNS = 96
"""Right-hand sides of the wide-solve table: the leverage probes' (32 probes x 3)."""


def scipy_defaults(A: Any, ordered: bool = False, supernodes: bool = True) -> Any:
    """SuperLU as the core called it before: symmetric mode, SciPy's supernode settings
    (``supernodes``: accepted as :func:`factor_spd` takes it; these are SciPy's anyway)."""
    return splu(A, permc_spec="NATURAL" if ordered else "MMD_AT_PLUS_A",
                diag_pivot_thresh=0.0, options={"SymmetricMode": True})


def per_call(fn: Callable[[], Any], repeats: int) -> float:
    """Best of three means of ``repeats`` calls, in ms."""
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(repeats):
            fn()
        best = min(best, (time.perf_counter() - t0) / repeats * 1e3)
    return best


def chordal_time(case: Any, factor: Callable[..., Any], repeats: int) -> float:
    """ms per chordal relaxation of the case's graph with ``factor`` as its SuperLU."""
    saved = chordal_init.factor_spd
    chordal_init.factor_spd = factor  # type: ignore[assignment]
    try:
        w = np.ones(case.i.size)
        return per_call(lambda: chordal_init.chordal_rotations(
            case.num_nodes, case.i, case.j, case.R, w), max(1, repeats // 10))
    finally:
        chordal_init.factor_spd = saved


def ordered_laplacian(case: Any) -> Any:
    """The case's graph Laplacian, every edge at weight 1, in its shared elimination order
    (as the Gauss-Newton and GNC steps factor it), CSC."""
    n, i, j = case.num_nodes, case.i, case.j
    L, nodes = anchored_laplacian(n, i, j, np.ones(i.size))
    perm = np.argsort(EliminationOrder(n, i, j).rank[nodes], kind="stable")
    return L[perm][:, perm].tocsc()


def wide_solves(builders: dict[str, Any], shared: Any, repeats: int) -> None:
    """The wide-solve table (module docstring)."""
    print(f"\n| graph | N | columns | one call ms | blocks of {SOLVE_COLUMNS} ms | ratio | "
          "the same bits |")
    print("|---|---:|---:|---:|---:|---:|---|")
    rng = np.random.default_rng(1)
    for name in WIDE_CASES:
        if name not in builders:
            print(f"| {name} | – | – | – | – | – | not available (gtsam's data) |")
            continue
        case = builders[name](shared)
        lu = factor_spd(ordered_laplacian(case), ordered=True)
        b = rng.normal(size=(lu.shape[0], PROBE_COLUMNS))
        whole = per_call(functools.partial(lu.solve, b), max(1, repeats // 4))
        blocked = functools.partial(solve_by_blocks, lu, b, wide_bytes=0)  # blocks always
        blocks = per_call(blocked, max(1, repeats // 4))
        same = np.array_equal(lu.solve(b), blocked())
        print(f"| {name} | {case.num_nodes} | {PROBE_COLUMNS} | {whole:.2f} | {blocks:.2f} | "
              f"{blocks / whole:.2f} | {'yes' if same else 'no'} |", flush=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_sparse_factor",
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=20, help="factorizations per timing")
    args = p.parse_args(argv)
    shared = shared_dir_or_say("bench_sparse_factor")
    if shared is None:
        return 0
    builders = all_cases()
    print("| graph | N | E | system | SciPy defaults ms | factor_spd ms | ratio | "
          "factor nnz | max solution difference |")
    print("|---|---:|---:|---|---:|---:|---:|---:|---:|")
    rng = np.random.default_rng(0)
    for name in CASES:
        case = builders[name](shared)
        n, i = case.num_nodes, case.i
        A = ordered_laplacian(case)
        old = per_call(functools.partial(scipy_defaults, A, ordered=True), args.repeats)
        new = per_call(functools.partial(factor_spd, A, ordered=True), args.repeats)
        b = rng.normal(size=(A.shape[0], 3))
        diff = float(np.abs(factor_spd(A, ordered=True).solve(b)
                            - scipy_defaults(A, ordered=True).solve(b)).max())
        nnz = factor_spd(A, ordered=True).L.nnz
        print(f"| {name} | {n} | {i.size} | Laplacian | {old:.2f} | {new:.2f} | "
              f"{old / new:.2f} | {nnz} | {diff:.1e} |", flush=True)
        old_c = chordal_time(case, scipy_defaults, args.repeats)
        new_c = chordal_time(case, factor_spd, args.repeats)
        print(f"| {name} | {n} | {i.size} | chordal relaxation (whole) | {old_c:.1f} | "
              f"{new_c:.1f} | {old_c / new_c:.2f} | – | – |", flush=True)
    wide_solves(builders, shared, args.repeats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
