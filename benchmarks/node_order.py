"""The same graphs, with their nodes named in different orders (issue 14: graphs nobody tuned on).

``python -m benchmarks.node_order [--seed 0] [--cases chain/,slam/parking-garage/rand5]
[--stress]``

The default profile trusts the odometry (option ``odometry``, ``auto``): edges between
nodes consecutive in the graph's sequence (:mod:`rotavg_ros.core.node_sequence`). A user's
input need not name the nodes in that order. Each record case
(:func:`~benchmarks.regime_cases.all_cases`, default: the chains and three SLAM graphs with
false closures; ``--stress``: instead, every chain-family variant of
:mod:`benchmarks.regime_stress`) is solved in process as:

- ``in order``: its nodes added first, in id order (as :mod:`benchmarks.regimes` does);
- ``sorted edges``: edges only, sorted by ``(i, j)``, so each closure names its far end
  early (the order first named breaks two steps per closure);
- ``names``: the same sorted edges with the ids written as ``kf_<id>``;
- ``labels``: the nodes relabelled by a random permutation, then added in order of the new
  ids. No order then tells the odometry: the limit of what the sequence can do.

Against them, GTSAM GNC-TLS on the same measurements (plain: it takes no odometry, so the
order is nothing to it; its sigma the case's, as :mod:`benchmarks.regimes` sets it) and
the oracle (ours in order, on the true edges only). One line per case: mean / median error
(deg) and the odometry edges trusted, per order. Needs the shared data for the SLAM cases
(skipped with a message without it) and gtsam for the peer (a dash without it).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Hashable, Iterator
from pathlib import Path

import numpy as np

from benchmarks import peers
from benchmarks.datasets import shared_dir_or_say
from benchmarks.regime_cases import RegimeCase, all_cases, rng_for
from benchmarks.regime_stress import stress_cases
from benchmarks.regimes import our_options
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.solver import RotationAverager
from rotavg_ros.core.view_graph import ViewGraph

DEFAULT_CASES = ("chain/", "slam/parking-garage/rand5", "slam/sphere2500/rand5",
                 "slam/torus3D/rand10")

Name = Callable[[int], Hashable]


def graphs(case: RegimeCase, seed: int) -> dict[str, tuple[ViewGraph, Name]]:
    """The case's graph in each order of the module docstring, with each node's id."""
    def weight(order: np.ndarray) -> np.ndarray | None:
        return None if case.weight is None else case.weight[order]

    def edges_only(name: Name, order: np.ndarray) -> ViewGraph:
        g = ViewGraph()
        g.add_edges([name(int(k)) for k in case.i[order]],
                    [name(int(k)) for k in case.j[order]], case.R[order], weight(order))
        return g

    by_id = np.lexsort((np.maximum(case.i, case.j), np.minimum(case.i, case.j)))
    label = rng_for(case.name + "/labels", seed).permutation(case.num_nodes)
    relabelled = ViewGraph()
    for node in np.argsort(label):  # in order of the new labels
        relabelled.add_node(int(label[node]))
    relabelled.add_edges(label[case.i].tolist(), label[case.j].tolist(), case.R,
                         weight(np.arange(case.num_edges)))

    def kf(k: int) -> Hashable:
        return f"kf_{k}"

    def new_label(k: int) -> Hashable:
        return int(label[k])

    return {"in order": (case.view_graph(), int), "sorted edges": (edges_only(int, by_id), int),
            "names": (edges_only(kf, by_id), kf), "labels": (relabelled, new_label)}


def solve(g: ViewGraph, name: Name, case: RegimeCase) -> tuple[float, float, int]:
    """Ours (default profile): mean and median error (deg), odometry edges trusted."""
    res = RotationAverager(our_options("default", seed=0, device="cpu")).solve(g)
    stats = evaluate(dict(zip(res.node_ids, res.rotations, strict=True)),
                     {name(k): case.gt[k] for k in range(case.num_nodes)})
    return stats.mean_deg, stats.median_deg, res.num_trusted_odometry


def peer(case: RegimeCase) -> str:
    if not peers.available_peers().get("gtsam_gnc_tls"):
        return "-"
    rot, _ = peers.run_gtsam_gnc_tls(case.num_nodes, case.i, case.j, case.R, case.weight,
                                     sigma=float(np.radians(case.sigma_deg)))
    stats = evaluate(dict(enumerate(rot)), dict(enumerate(case.gt)))
    return f"{stats.mean_deg:.3f} / {stats.median_deg:.3f}"


def _cases(args: argparse.Namespace) -> Iterator[RegimeCase]:
    """The cases ``args`` ask for, drawn one at a time."""
    if args.stress:
        shared = shared_dir_or_say("benchmarks.node_order")
        if shared is None:
            return
        for draw in stress_cases(shared, args.seed, "folded"):
            case = draw()
            if case.family == "chain":
                yield case
        return
    wanted = args.cases.split(",")
    builders = {k: b for k, b in all_cases(args.seed).items()
                if any(k.startswith(w) for w in wanted)}
    found: Path | None = None
    if any(not k.startswith("chain/") for k in builders):
        found = shared_dir_or_say("benchmarks.node_order")
        if found is None:
            builders = {k: b for k, b in builders.items() if k.startswith("chain/")}
    for build in builders.values():
        yield build(found if found is not None else Path("."))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cases", default=",".join(DEFAULT_CASES),
                    help="comma-separated prefixes of record case names")
    ap.add_argument("--stress", action="store_true",
                    help="the chain-family variants of benchmarks.regime_stress instead")
    args = ap.parse_args()
    print("| case | in order | sorted edges | names | labels | oracle | GNC-TLS |")
    print("|---|---|---|---|---|---|---|")
    for case in _cases(args):
        key = case.name
        cells = []
        for g, name in graphs(case, args.seed).values():
            mean, median, trusted = solve(g, name, case)
            cells.append(f"{mean:.3f} / {median:.3f} ({trusted})")
        oracle = solve(case.view_graph(case.inlier), int, case)
        print(f"| {key} | {' | '.join(cells)} | {oracle[0]:.3f} / {oracle[1]:.3f} "
              f"| {peer(case)} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
