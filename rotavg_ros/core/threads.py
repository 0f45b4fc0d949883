"""How many threads the solver's CPU work takes, and independent pieces of it run on them.

The verification's pieces (GNC re-solves from several starts, the cross-validation's
folds) are numpy and SciPy work whose sparse products, factorizations and einsums release
the interpreter lock, so two run on two cores at once; their results are the same as one
after the other, bit for bit.
"""

from __future__ import annotations

import contextvars
import os
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def cpu_count() -> int:
    """CPUs this process may run on (its affinity mask where the platform has one)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


PARALLEL_MIN_EDGES = 5000
"""Graphs of at least this many edges run the verification's re-solves side by side. On
smaller ones each GNC step is a few small array operations, mostly interpreter time, and
two threads contend for the interpreter lock instead (chain/300/rand20: 40 -> 52 ms a
solve, smallGrid3D grouped 141 -> 156 ms); from parking-garage's 6,275 edges on they gain
or break even (in process, median of 5, 2026-12-03: torus3D rand10 1.84 -> 1.76 s,
sfm/dense1000/out30 2.22 -> 2.14 s, Ellis Island 2.64 -> 2.48 s, parking-garage noise5 +
rand5 2.64 -> 2.57 s; sphere2500 rand5, 4,949 edges, 0.555 -> 0.561 s). The
cross-validation's folds (:func:`~rotavg_ros.core.robust.l1_choice.choose_by_cross_validation`)
run two at a time from the same size on (all ten folds, 2026-12-05: smallGrid3D's 297 edges
1.99x the time on two threads, a 1,035-edge chain 1.43x, sphere2500's 4,827 0.83x,
parking-garage's 6,275 0.82x, torus3D's 9,048 0.71x)."""


def verify_workers(num_edges: int, threads: int | None) -> int:
    """Threads for the verification's independent re-solves and folds: ``threads``
    (``RuntimeOptions.threads``), or one per CPU when it is None; one below
    :data:`PARALLEL_MIN_EDGES` edges."""
    if num_edges < PARALLEL_MIN_EDGES:
        return 1
    return max(1, cpu_count() if threads is None else threads)


def map_in_threads(fn: Callable[[T], R], items: Iterable[T], workers: int) -> list[R]:
    """``[fn(x) for x in items]``, on up to ``workers`` threads; results in ``items``' order.

    Each call runs in a copy of the caller's context, so context variables set around it
    (:data:`~rotavg_ros.core.robust.gauss_newton.WELL_CONNECTED`, the shared elimination
    order) hold in the threads too. An exception in any call is raised here.
    """
    todo = list(items)
    if workers <= 1 or len(todo) <= 1:
        return [fn(x) for x in todo]
    with ThreadPoolExecutor(max_workers=min(workers, len(todo))) as pool:
        futures = [pool.submit(contextvars.copy_context().run, fn, x) for x in todo]
        return [f.result() for f in futures]
