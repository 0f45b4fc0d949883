"""The DMF at each candidate depth, and the choice between the depths by Eq. 3.

The paper's dynamic depth selection: a DMF is fitted at every candidate depth, each factor
``H`` is projected onto rotations (:func:`rotations_from_factor`), and the depth whose
rotations have the lowest :func:`observation_cost` wins. Dense mode fits depths 2, 4, 6, 8
from the DMF's own start (the default profile: the shallowest and the deepest only, and a
race that stops a candidate falling behind; a warm start: the previous choice only,
briefly); sparse mode fits its candidates (depth 2 by default) by L-BFGS from the
chordal solution. Conventions: world-to-node rotations ``R_i``, edges ``R_ij ~= R_i
R_j^T``; the chosen rotations are returned with node 0 at identity.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
import torch

from rotavg_ros.core.chordal_init import chordal_rotations
from rotavg_ros.core.dmf import (
    CandidateRace,
    DMFFit,
    FitSpec,
    fit_symmetric,
    fit_symmetric_lbfgs,
    fit_vanilla,
)
from rotavg_ros.core.dmf.sparse import huber_delta
from rotavg_ros.core.options import DenseFitOptions, SolverOptions
from rotavg_ros.core.so3 import geodesic_distance, project_to_so3
from rotavg_ros.core.threads import cpu_count
from rotavg_ros.core.types import FloatArray, IntArray
from rotavg_ros.errors import SolverError


@dataclass
class DepthChoice:
    """The chosen depth's rotations and what the candidates cost (:func:`choose_depth`)."""

    rotations: FloatArray
    """(N, 3, 3) world-to-node rotations of the chosen depth, node 0 = identity."""
    depth: int
    costs: dict[int, float]
    """Eq. 3 cost of each candidate whose factor was finite."""
    iterations: dict[int, int]
    """Iterations each candidate's fit ran."""
    pruned: tuple[int, ...]
    """Candidates the race stopped early (never chosen while another is left)."""


def rotations_from_factor(H: FloatArray) -> FloatArray:
    """Project H's 3x3 blocks onto SO(3), resolving the reflection in H -> H Q.

    ``H_i ~= R_i Q`` with Q in O(3). If most blocks have det < 0, Q is a reflection: flip
    the sign of H's last column (H diag(1, 1, -1) gives the same H H^T) before projecting.
    """
    dets = np.linalg.det(H)
    if np.count_nonzero(dets < 0) > dets.size / 2:
        H = H * np.array([1.0, 1.0, -1.0])
    return project_to_so3(H)


def observation_cost(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray
) -> float:
    """Eq. 3 with p = 1: sum_ij w_ij d(R_ij, R_i R_j^T), in radians."""
    pred = np.einsum("eab,ecb->eac", rot[i], rot[j])
    return float(np.sum(w * geodesic_distance(R, pred)))


def selection_cost(
    H: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray
) -> float:
    """The cost a depth candidate is chosen by: :func:`observation_cost` of the rotations
    of its factor ``H`` (N, 3, 3); NaN when ``H`` is not finite."""
    if not np.all(np.isfinite(H)):
        return math.nan
    return observation_cost(rotations_from_factor(H), i, j, R, w)


def resolve_device(name: str) -> str:
    """``auto`` picks CUDA when available; an unavailable CUDA request raises SolverError."""
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise SolverError(f"device {name!r} requested but CUDA is not available here")
    return name


def choose_depth(
    options: SolverOptions, n: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    sparse: bool, warm: FloatArray | None = None, warm_depth: int | None = None,
    chordal: FloatArray | None = None,
) -> DepthChoice:
    """The DMF at each candidate depth (:func:`fit_depths`) and the choice between them by
    Eq. 3 (:func:`observation_cost` of each candidate's rotations; a candidate the race
    stopped only where no other is left). A candidate whose factor is not finite raises
    (numpy's LinAlgError, from the projection onto SO(3)); FloatingPointError where no
    candidate has finite rotations."""
    fits = fit_depths(options, n, i, j, R, w, sparse, warm, warm_depth, chordal)
    costs: dict[int, float] = {}
    rots: dict[int, FloatArray] = {}
    iterations = {depth: fit.iterations for depth, fit in fits.items()}
    pruned = tuple(depth for depth, fit in fits.items() if fit.stopped)
    for depth, fit in fits.items():
        rot = rotations_from_factor(fit.H)
        if not np.all(np.isfinite(rot)):
            continue
        rots[depth] = rot
        costs[depth] = observation_cost(rot, i, j, R, w)
    if not costs:
        raise FloatingPointError("every DMF candidate diverged (non-finite factors)")
    # A stopped candidate's cost is of an unfinished fit: only a fallback.
    eligible = [d for d in costs if d not in pruned] or list(costs)
    best = min(eligible, key=lambda d: costs[d])
    if pruned:
        _say(options, f"candidate race: stopped depth(s) {', '.join(map(str, pruned))} at "
                  f"iteration(s) {', '.join(str(iterations[d]) for d in pruned)}")
    rot = rots[best]
    rot = project_to_so3(np.einsum("nab,cb->nac", rot, rot[0]))  # gauge: R_i R_0^T
    rot[0] = np.eye(3)  # exactly, not up to the SVD's rounding
    return DepthChoice(rot, best, costs, iterations, pruned)


def fit_depths(
    options: SolverOptions, n: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    sparse: bool, warm: FloatArray | None = None, warm_depth: int | None = None,
    chordal: FloatArray | None = None,
) -> dict[int, DMFFit]:
    """Each depth candidate's fit (a cold dense fit with ``bracket_depths``: the
    shallowest and the deepest candidate only). ``warm``: start rotations near the answer
    (a previous solution): dense mode then fits the depth ``warm_depth`` only, briefly;
    sparse mode judges the edges at it first. ``chordal``: the chordal solution of these
    edges, if already computed (sparse mode's start without ``warm``)."""
    dense, runtime = options.dense, options.runtime
    device = resolve_device(runtime.device)
    width = dense.width_for(n)
    depths = list(dict.fromkeys(options.sparse.depths if sparse else dense.depths))
    if warm is not None and not sparse:
        depths = [warm_depth if warm_depth in depths else depths[0]]
    elif not sparse and dense.bracket_depths:  # the shallowest and the deepest only
        depths = [d for d in depths if d in (min(depths), max(depths))]
    H0: FloatArray | None = warm
    delta = 0.0
    if sparse and dense.explicit_constraint:
        if H0 is None:
            H0 = chordal if chordal is not None else chordal_rotations(n, i, j, R, w)
        delta = huber_delta(H0, i, j, R, options.sparse.huber_factor)
    graphed = runtime.cuda_graphs and dense.explicit_constraint and not sparse
    workers, intra = _thread_plan(len(depths), runtime.threads, device, graphed)
    race = None
    if (dense.prune_ratio is not None and len(depths) > 1 and not sparse
            and warm is None and dense.explicit_constraint):
        race = CandidateRace(min(depths), dense.prune_ratio)

    def run(depth: int) -> DMFFit:
        fit = FitSpec(depth=depth, hidden_width=width, seed=runtime.seed + depth,
                      device=device, cuda_graph=runtime.cuda_graphs)

        def report(step: int, loss: float) -> None:
            _say(options, f"depth {depth}: iteration {step}, loss {loss:.4g}")

        if not dense.explicit_constraint:
            return fit_vanilla(n, i, j, R, w, dense, fit, report)
        if sparse and H0 is not None:
            return fit_symmetric_lbfgs(n, i, j, R, w, options.sparse, dense, fit, H0, delta,
                                       progress=report, trusted_start=warm is not None)
        if warm is not None:  # a short fit from the warm start, no warm-up
            short = replace(dense, iterations=options.warm.iterations, lr=options.warm.lr, warmup=0)
            return fit_symmetric(n, i, j, R, w, short, fit, report, H0=warm)
        if race is not None:
            return _race_fit(race, depth, dense, (i, j, R, w), lambda monitor: fit_symmetric(
                n, i, j, R, w, dense, fit, report, monitor=monitor))
        return fit_symmetric(n, i, j, R, w, dense, fit, report)

    # Largest depth first so the slow candidates start early; in a race, the
    # pace-setter first (the others wait for it: it must have started).
    order = sorted(depths, reverse=True)
    if race is not None:
        order = [race.pacer] + [d for d in order if d != race.pacer]
    previous = torch.get_num_threads()
    torch.set_num_threads(intra)
    try:
        if workers == 1:
            done = {d: run(d) for d in (order if race is not None else depths)}
            return {d: done[d] for d in depths}
        with ThreadPoolExecutor(max_workers=workers) as pool:
            futures = {d: pool.submit(run, d) for d in order}
            return {d: futures[d].result() for d in depths}
    finally:
        torch.set_num_threads(previous)


def _race_fit(
    race: CandidateRace, depth: int, dense: DenseFitOptions,
    edges: tuple[IntArray, IntArray, FloatArray, FloatArray],
    fit: Callable[[Callable[[int, FloatArray], bool]], DMFFit],
) -> DMFFit:
    """Run ``fit(monitor)``, the candidate ``depth`` of ``race``: at the race's checkpoints
    (``dense.prune_after``, then every ``dense.prune_every`` iterations) the monitor reports
    the :func:`selection_cost` on ``edges`` ``(i, j, R, w)`` and stops the fit when told."""

    def monitor(step: int, H: FloatArray) -> bool:
        if step < dense.prune_after or (step - dense.prune_after) % dense.prune_every:
            return False
        return race.report(depth, step, selection_cost(H, *edges))

    cost: float | None = None
    try:
        result = fit(monitor)
        cost = selection_cost(result.H, *edges)
        return result
    finally:  # always, or the later candidates wait for this one for ever
        race.finish(depth, cost)


def _thread_plan(
    candidates: int, threads: int | None, device: str, graphed: bool = True,
) -> tuple[int, int]:
    """``(parallel candidate fits, torch threads per fit)``.

    CUDA: fits whose step is a replayed CUDA graph (``graphed``: the dense fit with
    ``cuda_graphs``) get a thread each, on a stream of their own, since a replay leaves the
    host idle; other fits on CUDA run one at a time.

    ``threads=None``: one thread per fit, as many fits at once as there are CPUs. The fits
    are sequences of small tensor operations; torch's OpenMP threads spin-wait between them
    and collapse when the CPU is shared (Ellis Island, one depth, beside one busy process:
    3.7 s with one thread, 68.7 s with two), and a node runs beside a SLAM front end.
    An explicit ``threads`` is split among the parallel fits.
    """
    if device != "cpu":
        return (candidates if graphed else 1), torch.get_num_threads()
    if threads is None:
        return max(1, min(candidates, cpu_count())), 1
    workers = max(1, min(candidates, threads))
    return workers, max(1, threads // workers)


def _say(options: SolverOptions, text: str) -> None:
    """Report progress through ``options.runtime.progress``, where set."""
    if options.runtime.progress is not None:
        options.runtime.progress(text)
