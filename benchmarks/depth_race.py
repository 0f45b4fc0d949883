"""Benchmark: evidence for the depth candidates' race (``prune_ratio``, ``prune_after``).

For each dense-mode regime case (family ``sfm``) it solves with the default profile, and at
every dense-mode choice between depths (the filtered DMF, and the verification's refit when
it runs one) fits every depth to the end, one after the other, recording the Eq. 3 cost the
choice uses every ``check_every`` iterations. Then it prints, per choice, the depth chosen
and, from each checkpoint T on, how far the chosen depth's cost was at worst above the
pace-setter's (the shallowest depth) at the same iteration: the race must stop no winner,
so ``prune_ratio`` must stay above these; and which candidates ``--ratio``, ``--after`` and
``--every`` stop.

    python -m benchmarks.depth_race [--cases sfm/ellis,...] [--ratio 0.3] [--after 400]

Needs the shared data (``../shared`` or ``$ROTAVG_SHARED``) for the Ellis Island cases.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np
import torch

from benchmarks.datasets import shared_dir_or_say
from benchmarks.regime_cases import all_cases
from rotavg_ros.core import depth_choice
from rotavg_ros.core.depth_choice import selection_cost
from rotavg_ros.core.dmf import DMFFit, FitSpec, fit_symmetric
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.solver import RotationAverager
from rotavg_ros.core.types import FloatArray, IntArray

Trace = dict[int, tuple[dict[int, float], float, int]]
"""depth -> (cost by checkpoint, final cost, iterations)"""


def record_choices(case_name: str, shared: Any) -> list[Trace]:
    """Solve ``case_name`` (default profile, race off); the traces of every dense choice."""
    case = all_cases()[case_name](shared)
    choices: list[Trace] = []
    original = depth_choice.fit_depths

    def fit_all(options: SolverOptions, n: int, i: IntArray, j: IntArray, R: FloatArray,
                w: FloatArray, sparse: bool, warm: FloatArray | None = None,
                warm_depth: int | None = None,
                chordal: FloatArray | None = None) -> dict[int, DMFFit]:
        if sparse or warm is not None:
            return original(options, n, i, j, R, w, sparse, warm, warm_depth, chordal)
        dense = options.dense
        width = dense.width_for(n)
        fits, trace = {}, {}
        for depth in dense.depths:
            costs: dict[int, float] = {}

            def monitor(step: int, H: FloatArray, costs: dict[int, float] = costs) -> bool:
                costs[step] = selection_cost(H, i, j, R, w)
                return False

            spec = FitSpec(depth=depth, hidden_width=width,
                           seed=options.runtime.seed + depth, device="cpu",
                           cuda_graph=False)
            fits[depth] = fit_symmetric(n, i, j, R, w, dense, spec, monitor=monitor)
            trace[depth] = (costs, selection_cost(fits[depth].H, i, j, R, w),
                            fits[depth].iterations)
        choices.append(trace)
        return fits

    g = case.view_graph()
    depth_choice.fit_depths = fit_all
    try:
        RotationAverager(SolverOptions.from_flat(prune_ratio=None, device="cpu")).solve(g)
    finally:
        depth_choice.fit_depths = original
    return choices


def cost_at(trace: Trace, depth: int, step: int) -> float | None:
    costs, final, iterations = trace[depth]
    return costs.get(step, final if step > iterations else None)


def winner_excess(trace: Trace, start: int) -> float:
    """Largest ``cost(winner) / cost(pace-setter) - 1`` at the checkpoints from ``start``
    (the pace-setter: the shallowest depth; -inf when it is the winner)."""
    winner, pacer = min(trace, key=lambda d: trace[d][1]), min(trace)
    worst = -np.inf
    for step, cost in sorted(trace[winner][0].items()):
        ref = cost_at(trace, pacer, step)
        if step >= start and ref is not None and winner != pacer:
            worst = max(worst, cost / ref - 1.0)
    return float(worst)


def stopped(trace: Trace, ratio: float, after: int, every: int) -> dict[int, int]:
    """What the race would stop: depth -> checkpoint."""
    out: dict[int, int] = {}
    pacer = min(trace)
    for step in range(after, max(t[2] for t in trace.values()) + 1, every):
        ref = cost_at(trace, pacer, step)
        for depth in sorted(trace):
            cost = trace[depth][0].get(step)
            if depth == pacer or depth in out or cost is None or ref is None:
                continue
            if np.isfinite(ref) and cost > (1.0 + ratio) * ref:
                out[depth] = step
    return out


def _percent(x: float) -> str:
    return f"{100 * x:6.1f}%" if np.isfinite(x) else "    n/a"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", default=",".join(n for n in all_cases() if n.startswith("sfm/")))
    d = SolverOptions().dense
    p.add_argument("--ratio", type=float, default=d.prune_ratio)
    p.add_argument("--after", type=int, default=d.prune_after)
    p.add_argument("--every", type=int, default=d.prune_every)
    args = p.parse_args()
    shared = shared_dir_or_say("depth_race")
    if shared is None:
        return 0
    torch.set_num_threads(1)
    starts = (300, 400, 500, 600)
    print("case#choice: chosen depth, final cost by depth; winner's worst excess over the "
          f"pace-setter from iteration {starts}; stopped by the race")
    for name in args.cases.split(","):
        for k, trace in enumerate(record_choices(name, shared)):
            winner = min(trace, key=lambda d: trace[d][1])
            excess = " ".join(_percent(winner_excess(trace, t)) for t in starts)
            out = stopped(trace, args.ratio, args.after, args.every)
            finals = " ".join(f"d{dd} {trace[dd][1]:.2f}/{trace[dd][2]}" for dd in trace)
            flag = "  WINNER STOPPED" if winner in out else ""
            print(f"{name}#{k}: d{winner} ({finals}) excess {excess}; stopped {out}{flag}",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
