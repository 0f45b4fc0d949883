"""Whole-process speed, side by side (issue 16): ``python -m benchmarks.bench_speed``.

Times complete processes on the same input file: ours (``rotavg solve IN --output OUT.g2o``
on the CPU, default profile and ``--profile paper``) and a child process running pycolmap's
IRLS-L½ rotation averaging (:func:`benchmarks.peers.run_pycolmap_half_norm`; this module
with ``--pycolmap-child IN OUT``), which reads the file as ``rotavg`` does and writes its
rotations in the same g2o form. Wall time is the process's, start-up, reading and writing
included. Every output is scored against the ground truth (1DSfM for Ellis Island, the
generating rotations for generated graphs, the certified optimum for SE-Sync torus3D) with
:func:`rotavg_ros.core.metrics.evaluate`, so a speed-up can never come from accuracy silently.

Graphs: ``ellis`` (Ellis Island, GT cameras), ``ellis+15%`` (plus 15% random false edges),
``torus3D`` (the SE-Sync file as measured), ``synthetic2000`` (2,000 nodes, mean degree 20,
2 deg noise, 10% outliers) and ``tiny`` (60 nodes; generated, needs no shared data; not in
the default set). Generated inputs are written to a temporary folder. The median of
``--repeats`` runs is reported; the runs of one graph are interleaved across the methods.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
PROG = "bench_speed"
DEFAULT_GRAPHS = ("ellis", "ellis+15%", "torus3D", "synthetic2000")
ALL_GRAPHS = (*DEFAULT_GRAPHS, "tiny")
QUICK_GRAPHS = ("tiny", "ellis")
NEEDS_SHARED = frozenset({"ellis", "ellis+15%", "torus3D"})
PYCOLMAP = "pycolmap IRLS-L½"
METHODS: dict[str, list[str]] = {
    "rotavg (default)": ["-m", "rotavg_ros", "solve", "{input}", "--output", "{output}",
                         "--device", "cpu", "-q"],
    "rotavg --profile paper": ["-m", "rotavg_ros", "solve", "{input}", "--output", "{output}",
                               "--device", "cpu", "-q", "--profile", "paper"],
    PYCOLMAP: ["-m", "benchmarks.bench_speed", "--pycolmap-child", "{input}", "{output}"],
}


@dataclass
class Case:
    """One input file and the world-to-node rotations it is scored against."""

    name: str
    path: Path
    num_nodes: int
    num_edges: int
    truth: dict[int, Any]
    truth_kind: str


@dataclass
class Row:
    """One (graph, method): its wall times, and its errors or why it failed."""

    graph: str
    num_nodes: int
    num_edges: int
    method: str
    walls: list[float] = field(default_factory=list)
    mean_deg: float | None = None
    median_deg: float | None = None
    failure: str | None = None

    @property
    def median_wall(self) -> float | None:
        return statistics.median(self.walls) if self.walls and self.failure is None else None


# ----------------------------------------------------------------------------- inputs


def _write_case(name: str, folder: Path, i: Any, j: Any, R: Any, gt: Any,
                kind: str) -> Case:
    """Write edges ``R_ij ~= R_i R_j^T`` (node ids 0..N-1, identity vertices, unit weights)
    as g2o; the truth stays here."""
    import numpy as np

    from rotavg_ros.core.view_graph import EdgeArrays
    from rotavg_ros.io.g2o import write_g2o

    n = int(gt.shape[0])
    path = folder / f"{name.replace('%', 'pct').replace('+', '_plus')}.g2o"
    edges = EdgeArrays(np.asarray(i), np.asarray(j), np.asarray(R), np.ones(len(i)),
                       np.ones(len(i), np.int64))
    write_g2o(path, list(range(n)), np.broadcast_to(np.eye(3), (n, 3, 3)), edges)
    return Case(name, path, n, len(i), {k: gt[k] for k in range(n)}, kind)


def build_case(name: str, shared: Path | None, folder: Path) -> Case:
    """The input file of graph ``name`` (generated ones written into ``folder``)."""
    from benchmarks.regime_cases import dense_case, ellis_case

    if name in NEEDS_SHARED and shared is None:
        raise FileNotFoundError("shared data not found")
    if name == "torus3D":
        from benchmarks.datasets import load_se_sync

        assert shared is not None
        bench = load_se_sync(shared, "torus3D")
        e = bench.graph.edge_arrays()
        return Case(name, shared / "data/se_sync_3d/torus3D.g2o", bench.graph.num_nodes,
                    e.num_edges, {int(k): r for k, r in bench.reference.items()},  # type: ignore[call-overload]
                    bench.reference_kind)
    if name in ("ellis", "ellis+15%"):
        assert shared is not None
        c = ellis_case(name, shared, extra=0.15 if name == "ellis+15%" else 0.0)
        return _write_case(name, folder, c.i, c.j, c.R, c.gt, "1DSfM ground truth")
    if name == "synthetic2000":
        c = dense_case(name, 2000, 20.0, outliers=0.10, noise_deg=2.0)
    elif name == "tiny":
        c = dense_case(name, 60, 12.0, outliers=0.10, noise_deg=2.0)
    else:
        raise ValueError(f"unknown graph {name!r}; choose from {', '.join(ALL_GRAPHS)}")
    return _write_case(name, folder, c.i, c.j, c.R, c.gt, "generating rotations")


# ------------------------------------------------------------------------------ runs


def run_once(method: str, case: Case, output: Path, timeout: float) -> tuple[float, str | None]:
    """Wall seconds of one whole process, and None or why it failed."""
    argv = [sys.executable, *(a.format(input=case.path, output=output) for a in METHODS[method])]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        p for p in (str(REPO_ROOT), os.environ.get("PYTHONPATH", "")) if p)}
    output.unlink(missing_ok=True)
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(argv, cwd=REPO_ROOT, env=env, capture_output=True, text=True,
                              timeout=timeout, check=False)
    except subprocess.TimeoutExpired:
        return time.perf_counter() - t0, f"timed out after {timeout:g} s"
    wall = time.perf_counter() - t0
    if proc.returncode != 0 or not output.is_file():
        last = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return wall, f"exit {proc.returncode}: {last[:160]}"
    return wall, None


def score(output: Path, truth: dict[int, Any]) -> tuple[float, float]:
    """Mean and median error (deg) of a g2o result against ``truth`` after gauge alignment."""
    from rotavg_ros.core.metrics import evaluate
    from rotavg_ros.io.g2o import read_g2o_vertices

    ids, rots = read_g2o_vertices(output)
    stats = evaluate(dict(zip(ids, rots, strict=True)), truth)
    return stats.mean_deg, stats.median_deg


def bench_case(case: Case, methods: Sequence[str], repeats: int, folder: Path,
               timeout: float, say: Callable[[str], None]) -> list[Row]:
    """``repeats`` interleaved runs of every method on ``case``."""
    rows = {m: Row(case.name, case.num_nodes, case.num_edges, m) for m in methods}
    for rep in range(repeats):
        for method, row in rows.items():
            if row.failure is not None:
                continue
            out = folder / "out.g2o"
            wall, failure = run_once(method, case, out, timeout)
            row.walls.append(wall)
            row.failure = failure
            if failure is None and rep == 0:
                row.mean_deg, row.median_deg = score(out, case.truth)
            say(f"{case.name}: {method} run {rep + 1}/{repeats}: {wall:.2f} s"
                + (f" FAILED ({failure})" if failure else ""))
    return list(rows.values())


# ----------------------------------------------------------------------------- table


def ratio(row: Row, reference: Row | None) -> float | None:
    """``row``'s median wall over the reference's (same graph), None when either lacks one."""
    if reference is None or row.median_wall is None or not reference.median_wall:
        return None
    return row.median_wall / reference.median_wall


def format_table(rows: Sequence[Row], reference_method: str = PYCOLMAP) -> str:
    """Markdown table; the ratio is to ``reference_method`` on the same graph."""
    refs = {r.graph: r for r in rows if r.method == reference_method}
    lines = ["| graph | N | E | method | median wall s | runs | ratio to pycolmap "
             "| mean err deg | median err deg |",
             "|---|---:|---:|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        q = ratio(r, refs.get(r.graph))
        if r.failure is not None:
            wall, err_mean, err_med = f"failed: {r.failure}", "–", "–"
        else:
            wall = f"{r.median_wall:.2f}"
            err_mean = "–" if r.mean_deg is None else f"{r.mean_deg:.3f}"
            err_med = "–" if r.median_deg is None else f"{r.median_deg:.3f}"
        lines.append(f"| {r.graph} | {r.num_nodes:,} | {r.num_edges:,} | {r.method} | {wall} "
                     f"| {len(r.walls)} | {'–' if q is None else f'{q:.2f}'} | {err_mean} "
                     f"| {err_med} |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- child


def pycolmap_child(input_path: Path, output_path: Path) -> int:
    """Read ``input_path`` as ``rotavg solve`` does, run pycolmap IRLS-L½, write g2o."""
    import numpy as np

    from benchmarks.peers import run_pycolmap_half_norm
    from rotavg_ros.io.g2o import write_g2o
    from rotavg_ros.io.graph_files import read_graph_file

    graph, _ = read_graph_file(input_path)
    e = graph.edge_arrays()
    weight = None if np.all(e.weight == e.weight[0]) else e.weight
    rotations, _ = run_pycolmap_half_norm(graph.num_nodes, e.i, e.j, e.R, weight)
    write_g2o(output_path, graph.node_ids, rotations)
    return 0


# ------------------------------------------------------------------------------ main


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog=f"python -m benchmarks.{PROG}", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--graphs", nargs="+", choices=ALL_GRAPHS, metavar="GRAPH",
                   help=(f"subset of {', '.join(ALL_GRAPHS)} (default: "
                         f"{' '.join(DEFAULT_GRAPHS)}; --quick: {' '.join(QUICK_GRAPHS)})"
                         ).replace("%", "%%"))
    p.add_argument("--repeats", type=int, default=3, help="runs per (graph, method); the "
                   "median is reported (default %(default)s)")
    p.add_argument("--quick", action="store_true", help="one run each, on the small graphs")
    p.add_argument("--methods", nargs="+", choices=tuple(METHODS), metavar="METHOD",
                   default=list(METHODS), help="subset of: " + "; ".join(METHODS))
    p.add_argument("--timeout", type=float, default=900.0, help="seconds per process")
    p.add_argument("--markdown", type=Path, metavar="FILE",
                   help="also write the table here, rewritten after every graph")
    p.add_argument("--pycolmap-child", nargs=2, metavar=("INPUT", "OUTPUT"),
                   help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.repeats < 1:
        p.error("--repeats must be >= 1")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    if args.pycolmap_child:
        return pycolmap_child(Path(args.pycolmap_child[0]), Path(args.pycolmap_child[1]))

    def say(text: str) -> None:
        print(f"[{PROG}] {text}", file=sys.stderr, flush=True)

    import importlib.util

    from benchmarks.datasets import find_shared_dir

    if PYCOLMAP in args.methods and importlib.util.find_spec("pycolmap") is None:
        print(f"{PROG}: pycolmap is not installed (pip install --no-deps -r "
              "requirements-bench.txt); nothing to compare against", file=sys.stderr)
        return 0
    graphs = args.graphs or (QUICK_GRAPHS if args.quick else DEFAULT_GRAPHS)
    repeats = 1 if args.quick else args.repeats
    shared = find_shared_dir()
    if shared is None and any(g in NEEDS_SHARED for g in graphs):
        say("shared data not found (../shared or $ROTAVG_SHARED): skipping "
            + ", ".join(g for g in graphs if g in NEEDS_SHARED))
        graphs = [g for g in graphs if g not in NEEDS_SHARED]
    if not graphs:
        print(f"{PROG}: no graph left to run", file=sys.stderr)
        return 0
    rows: list[Row] = []
    with tempfile.TemporaryDirectory(prefix="rotavg_bench_speed_") as tmp:
        folder = Path(tmp)
        for name in graphs:
            case = build_case(name, shared, folder)
            say(f"{name}: N={case.num_nodes} E={case.num_edges} ({case.path.name}; scored "
                f"against the {case.truth_kind})")
            rows += bench_case(case, args.methods, repeats, folder, args.timeout, say)
            if args.markdown is not None:
                args.markdown.write_text(format_table(rows) + "\n", encoding="utf-8")
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
