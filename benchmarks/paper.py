"""Benchmark on the shared real data: ``python -m benchmarks.paper``.

Prints a markdown table (dataset, nodes, edges, method, mean / median error in degrees,
wall time, peak RSS). Each run happens in a fresh spawned process, so the wall time includes
no start-up, and the peak RSS is that process's own high-water mark (torch included).

* Ellis Island (1DSfM, paper protocol: GT cameras only) is scored against ground truth, next
  to the paper's Table I row (``shared/reference/paper_table1.csv``).
* SE-Sync graphs are scored against the certified optimum of their rotation problem.
* ``--peers`` adds pycolmap HALF_NORM, GTSAM Shonan+Huber and GTSAM chordal where installed
  (``pip install -r requirements-bench.txt``); ``--ablations`` adds the paper's Table II
  switches (a)-(d) on Ellis Island.
"""

from __future__ import annotations

import argparse
import csv
import multiprocessing as mp
import resource
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import peers
from benchmarks.datasets import (
    SE_SYNC_GRAPHS,
    Benchmark,
    load_ellis_island,
    load_se_sync,
    shared_dir_or_say,
)
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.options import PROFILES, SolverOptions
from rotavg_ros.core.solver import RotationAverager

GRAPHS = ("ellis", *SE_SYNC_GRAPHS)
OURS = "filtered-DMF (ours)"
"""Our row with the ``paper`` profile (the reproduction); other profiles are named."""
ABLATIONS: dict[str, dict[str, Any]] = {
    "(a) w/o edge filter": {"use_filter": False},
    "(b) w/o support count": {"use_support_count": False},
    "(c) w/o explicit constraint": {"explicit_constraint": False},
    "(d) w/o reweighting": {"reweighting": False},
}


@dataclass
class Row:
    dataset: str
    nodes: int
    edges: int
    method: str
    mean_deg: float
    median_deg: float
    wall_s: float
    peak_rss_mb: float
    note: str = ""
    errors: list[float] | None = None


def load(shared: Path, name: str) -> Benchmark:
    return load_ellis_island(shared) if name == "ellis" else load_se_sync(shared, name)


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _run_ours(shared: Path, name: str, overrides: dict[str, Any], q: Any) -> None:
    try:
        bench = load(shared, name)
        overrides = dict(overrides)
        options = SolverOptions.for_profile(overrides.pop("profile", "paper"), **overrides)
        t0 = time.perf_counter()
        result = RotationAverager(options).solve(bench.graph)
        wall = time.perf_counter() - t0
        stats = evaluate(dict(zip(result.node_ids, result.rotations, strict=True)),
                         bench.reference)
        note = f"depth {result.depth}, {result.num_filtered} filtered"
        if result.verification:
            note += f"; verification kept {result.verification}"
        q.put(("ok", stats.mean_deg, stats.median_deg, wall, _peak_rss_mb(), note,
               stats.errors.tolist()))
    except Exception as exc:  # reported as a row, the benchmark goes on
        q.put(("error", 0.0, 0.0, 0.0, _peak_rss_mb(), f"{type(exc).__name__}: {exc}", None))


def _run_peer(shared: Path, name: str, peer: str, q: Any) -> None:
    try:
        bench = load(shared, name)
        e = bench.graph.edge_arrays()
        # Unweighted graphs go in unweighted (a peer's robust scale may depend on weights).
        weight = None if np.all(e.weight == e.weight[0]) else e.weight
        rot, wall = peers.PEERS[peer](bench.graph.num_nodes, e.i, e.j, e.R, weight)
        stats = evaluate(dict(zip(bench.graph.node_ids, rot, strict=True)), bench.reference)
        q.put(("ok", stats.mean_deg, stats.median_deg, wall, _peak_rss_mb(), "",
               stats.errors.tolist()))
    except Exception as exc:
        q.put(("error", 0.0, 0.0, 0.0, _peak_rss_mb(), f"{type(exc).__name__}: {exc}", None))


def run_child(target: Any, args: tuple[Any, ...], timeout: float) -> tuple[Any, ...]:
    """Run ``target(*args, queue)`` in a spawned process; a time-out becomes an error row."""
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    proc = ctx.Process(target=target, args=(*args, q))
    proc.start()
    try:
        out = q.get(timeout=timeout)
    except Exception:
        proc.kill()
        out = ("error", 0.0, 0.0, 0.0, 0.0, f"timeout after {timeout:.0f} s", None)
    proc.join()
    return tuple(out)


def paper_rows(shared: Path) -> list[tuple[str, float, float]]:
    """Paper Table I rows for Ellis Island (ELS): (method, mean, median)."""
    path = shared / "reference/paper_table1.csv"
    if not path.exists():
        return []
    with path.open() as fh:
        rows = [r for r in csv.reader(line for line in fh if not line.startswith("#"))]
    return [(r[1], float(r[2]), float(r[3])) for r in rows[1:] if r[0] == "ELS"]


def format_table(rows: list[Row]) -> str:
    out = ["| dataset | nodes | edges | method | mean ° | median ° | wall s | peak RSS MB | note |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r.wall_s or r.mean_deg:
            nums = f"{r.mean_deg:.3f} | {r.median_deg:.3f} | {r.wall_s:.2f} | {r.peak_rss_mb:.0f}"
        else:
            nums = "– | – | – | –"
        out.append(f"| {r.dataset} | {r.nodes} | {r.edges} | {r.method} | {nums} | {r.note} |")
    return "\n".join(out)


def format_ratios(rows: list[Row]) -> str:
    """Ours vs each peer, per dataset: time ratio and error ratios (< 1: ours is better)."""
    out = ["| dataset | peer | time ours/peer | mean err ours/peer | median err ours/peer |",
           "|---|---|---|---|---|"]
    ours = {r.dataset: r for r in rows if r.method == OURS and r.errors is not None}
    for r in rows:
        o = ours.get(r.dataset)
        if o is None or r.method not in peers.PEER_NAMES or r.errors is None:
            continue
        out.append(f"| {r.dataset} | {r.method} | {o.wall_s / max(r.wall_s, 1e-9):.2f} | "
                   f"{o.mean_deg / max(r.mean_deg, 1e-12):.2f} | "
                   f"{o.median_deg / max(r.median_deg, 1e-12):.2f} |")
    return "\n".join(out)


def write_plots(rows: list[Row], folder: Path) -> list[Path]:
    """Error CDF per dataset and wall time against graph size (needs matplotlib)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for dataset in dict.fromkeys(r.dataset for r in rows):
        fig, ax = plt.subplots(figsize=(5, 3.5))
        for r in rows:
            if r.dataset == dataset and r.errors:
                e = np.sort(np.asarray(r.errors))
                ax.plot(e, np.arange(1, e.size + 1) / e.size, label=r.method)
        ax.set_xscale("log")
        ax.set_xlabel("angular error (deg)")
        ax.set_ylabel("fraction of nodes")
        ax.set_title(dataset)
        ax.legend(fontsize=7)
        path = folder / f"cdf_{dataset.replace(' ', '_')}.png"
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for method in dict.fromkeys(r.method for r in rows if r.errors):
        pts = sorted((r.nodes, r.wall_s) for r in rows if r.method == method and r.errors)
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=method)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("nodes")
    ax.set_ylabel("wall time (s)")
    ax.legend(fontsize=7)
    path = folder / "time_vs_size.png"
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)
    return written


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.paper", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--graphs", default=",".join(GRAPHS),
                   help="comma-separated subset of: " + ", ".join(GRAPHS))
    p.add_argument("--peers", action="store_true", help="also run the installed peers")
    p.add_argument("--ablations", action="store_true",
                   help="Table II ablations on Ellis (paper profile)")
    p.add_argument("--profiles", default="paper",
                   help="comma-separated solver profiles to run: paper (Algorithm 1 + DMF, the "
                   "reproduction) and/or default (the product) (default %(default)s)")
    p.add_argument("--timeout", type=float, default=900.0, help="per run, seconds")
    p.add_argument("--device", default="cpu",
                   help="solver device for our runs: cpu, cuda or auto (peers run on the CPU)")
    p.add_argument("--markdown", help="also write the table to this file")
    p.add_argument("--plots", help="folder for PNG plots (error CDFs, time vs size; "
                   "needs matplotlib from requirements-bench.txt)")
    args = p.parse_args(argv)
    shared = shared_dir_or_say("benchmark")
    if shared is None:
        return 0
    names = [g.strip() for g in args.graphs.split(",") if g.strip()]
    unknown = sorted(set(names) - set(GRAPHS))
    if unknown:
        p.error(f"unknown graphs: {', '.join(unknown)}")
    profiles = [x.strip() for x in args.profiles.split(",") if x.strip()]
    bad = sorted(set(profiles) - set(PROFILES))
    if bad:
        p.error(f"unknown profiles: {', '.join(bad)} (known: {', '.join(PROFILES)})")
    available = peers.available_peers() if args.peers else {}
    rows: list[Row] = []
    for name in names:
        bench = load(shared, name)
        n, m = bench.graph.num_nodes, bench.graph.edge_arrays().num_edges
        dev = {"device": args.device}
        runs: list[tuple[str, Any, tuple[Any, ...]]] = [
            (OURS if prof == "paper" else f"filtered-DMF (ours, {prof})", _run_ours,
             (shared, name, {**dev, "profile": prof})) for prof in profiles]
        if name == "ellis" and args.ablations:
            runs += [(f"ours {k}", _run_ours, (shared, name, {**v, **dev, "profile": "paper"}))
                     for k, v in ABLATIONS.items()]
        runs += [(peer, _run_peer, (shared, name, peer)) for peer, ok in available.items() if ok]
        for method, target, targs in runs:
            status, mean, med, wall, rss, note, errors = run_child(target, targs, args.timeout)
            row = Row(bench.name, n, m, method, mean, med, wall, rss,
                      note if status == "ok" else f"error: {note}", errors)
            rows.append(row)
            print(format_table([row]).splitlines()[-1], flush=True)
        if name == "ellis":
            for method, mean, med in paper_rows(shared):
                rows.append(Row(bench.name, n, m, f"paper: {method}", mean, med, 0.0, 0.0,
                                "Table I, not run here"))
    table = format_table(rows)
    if available:
        table += "\n\n" + format_ratios(rows)
    print("\n" + table)
    if args.markdown:
        Path(args.markdown).write_text(table + "\n")
    if args.plots:
        for path in write_plots(rows, Path(args.plots)):
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
