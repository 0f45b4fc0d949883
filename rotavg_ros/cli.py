"""Command line: ``rotavg solve | evaluate | replay | bench`` (also ``python -m rotavg_ros``).

Output g2o files hold one ``VERTEX_SE3:QUAT id 0 0 0 qx qy qz qw`` per node with the
**node-to-world** quaternion (g2o's vertex convention), i.e. the transpose of our
world-to-node ``R_i``. For 1DSfM input, ids are the dataset's camera indices.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Hashable, Sequence
from pathlib import Path

import numpy as np

from rotavg_ros.io_1dsfm import open_npz, read_1dsfm_egs, read_1dsfm_npz, read_rotations_npz
from rotavg_ros.io_g2o import EDGE_TAG, VERTEX_TAG, read_g2o, read_g2o_vertices, write_g2o
from rotavg_ros.metrics import evaluate
from rotavg_ros.replay import register as register_replay
from rotavg_ros.solver import RotationAverager
from rotavg_ros.solver_types import SolverOptions
from rotavg_ros.view_graph import ViewGraph


class InputError(Exception):
    """Unusable input; the message names the file (and line where known)."""


def load_graph(
    path: Path, gt_only: bool = False, warn: Callable[[str], None] | None = None,
) -> tuple[ViewGraph, dict[Hashable, np.ndarray]]:
    """Read ``.g2o``, a 1DSfM ``.npz`` or ``EGs.txt``; returns the graph and any GT.

    ``warn`` gets a line about g2o lines skipped for their tag (e.g. ``EDGE_SE2``).
    """
    if not path.exists():
        raise InputError(f"{path}: no such file")
    if path.is_dir():
        raise InputError(f"{path}: is a directory, not a graph file")
    name = path.name.lower()
    try:
        if name.endswith(".g2o"):
            g2o = read_g2o(path)
            skipped = ", ".join(f"{tag} x{n}" for tag, n in sorted(g2o.skipped_tags.items()))
            if g2o.num_edges == 0:
                raise InputError(f"{path}: no {EDGE_TAG} edges"
                                 + (f" (skipped lines: {skipped})" if skipped else ""))
            if skipped and warn is not None:
                warn(f"{path}: skipped lines with tags not used for rotation averaging: "
                     f"{skipped}")
            return g2o.graph, {}
        if name.endswith(".npz"):
            ds = read_1dsfm_npz(path, gt_only=gt_only)
            return ds.graph, {k: r for k, r in ds.gt.items()}
        if name.endswith(".txt"):
            ds = read_1dsfm_egs(path)
            return ds.graph, {k: r for k, r in ds.gt.items()}
    except (ValueError, KeyError, OSError) as exc:
        raise InputError(str(exc) if str(path) in str(exc) else f"{path}: {exc}") from exc
    raise InputError(f"{path}: unknown input format (expected .g2o, .npz or EGs .txt)")


def add_solver_arguments(parser: argparse.ArgumentParser) -> None:
    """Solver knobs shared by every command that solves."""
    d = SolverOptions()
    g = parser.add_argument_group("solver")
    g.add_argument("--mode", default=d.mode, choices=("auto", "dense", "sparse"),
                   help="dense: the paper's DMF; sparse: chordal start + Huber + L-BFGS for "
                   "chain-like SLAM graphs; auto: by mean degree (default %(default)s)")
    g.add_argument("--seed", type=int, default=d.seed,
                   help="random seed; a seed gives bitwise-equal results on the CPU "
                   "(default %(default)s)")
    g.add_argument("--depths", default=",".join(map(str, d.depths)),
                   help="candidate depths, comma separated (default %(default)s)")
    g.add_argument("--iterations", type=int, default=d.iterations,
                   help="dense mode: Adam iterations at most (default %(default)s)")
    g.add_argument("--tolerance", type=float, default=d.tolerance,
                   help="dense mode early stopping: relative change of H per 25 iterations "
                   "(0 = off; default %(default)s)")
    g.add_argument("--dtype", default=d.dtype, choices=("float32", "float64"),
                   help="dense mode: precision of the Adam fit (default %(default)s)")
    g.add_argument("--lr", type=float, default=d.lr,
                   help="dense mode: initial Adam step size, cosine decay (default %(default)s)")
    g.add_argument("--sigma", type=float, default=d.sigma,
                   help="filter threshold on d_chord(R_ij, R_ij^tree) (default %(default)s)")
    g.add_argument("--device", default=d.device, help="cpu, cuda or auto")
    g.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads, split among the depth candidates (default or 0: "
                   "one per candidate, candidates in parallel up to the CPU count)")
    g.add_argument("--hidden-width", type=int, default=None,
                   help="width of H's hidden factors (>= 3; default: 3N up to 300 nodes, "
                   "64 above)")
    g.add_argument("--no-filter", action="store_true", help="ablation (a)")
    g.add_argument("--no-support-count", action="store_true", help="ablation (b)")
    g.add_argument("--no-explicit-constraint", action="store_true", help="ablation (c)")
    g.add_argument("--no-reweighting", action="store_true", help="ablation (d)")


def options_from_args(args: argparse.Namespace) -> SolverOptions:
    try:
        depths = tuple(int(x) for x in str(args.depths).split(",") if x.strip())
    except ValueError as exc:
        raise InputError(f"--depths: expected comma-separated integers: {args.depths!r}") from exc
    progress = None if getattr(args, "quiet", False) else _stderr
    return SolverOptions(
        mode=args.mode, depths=depths, iterations=args.iterations, tolerance=args.tolerance,
        dtype=args.dtype, lr=args.lr, sigma=args.sigma,
        seed=args.seed, device=args.device,
        threads=None if args.threads == 0 else args.threads,  # 0 = default, as the node's
        hidden_width=args.hidden_width, use_filter=not args.no_filter,
        use_support_count=not args.no_support_count,
        explicit_constraint=not args.no_explicit_constraint,
        reweighting=not args.no_reweighting, progress=progress,
    )


def _stderr(text: str) -> None:
    print(f"[rotavg] {text}", file=sys.stderr, flush=True)


def _warn(text: str) -> None:
    print(f"rotavg: warning: {text}", file=sys.stderr, flush=True)


def cmd_solve(args: argparse.Namespace) -> int:
    options = options_from_args(args)
    options.validate()  # before reading a large input
    out_dir = Path(args.output).resolve().parent
    if Path(args.output).is_dir():
        raise InputError(f"{args.output}: is a directory; --output names the .g2o file")
    if not out_dir.is_dir():
        raise InputError(f"{args.output}: output directory {out_dir} does not exist")
    graph, _ = load_graph(Path(args.input), gt_only=args.gt_only, warn=_warn)
    if graph.num_nodes == 0:
        raise InputError(f"{args.input}: no edges")
    t0 = time.perf_counter()
    result = RotationAverager(options).solve(graph)
    wall = time.perf_counter() - t0
    write_g2o(args.output, result.node_ids, result.rotations)
    ncomp = int(result.component.max()) + 1 if result.component.size else 0
    if not args.quiet:
        inl = result.residuals_deg[result.edge_inlier]
        print(f"solved {graph.num_nodes} nodes, {graph.edge_arrays().num_edges} edges in "
              f"{wall:.2f} s: depth {result.depth}, {result.num_filtered} edges filtered, "
              f"{ncomp} component(s), inlier residual median "
              f"{f'{np.median(inl):.3f} deg' if inl.size else 'n/a'} -> {args.output}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    ids, rots = read_g2o_vertices(args.estimate)
    est = {k: r for k, r in zip(ids, rots, strict=True)}
    gt_path = Path(args.ground_truth)
    if not gt_path.is_file():
        raise InputError(f"{gt_path}: no such file")
    if gt_path.suffix == ".npz":
        with open_npz(gt_path) as data:
            is_dataset = "edges" in data.files
        gt = (dict(read_1dsfm_npz(gt_path, gt_only=True).gt) if is_dataset
              else dict(read_rotations_npz(gt_path)))
    else:
        raise InputError(f"{gt_path}: ground truth must be a 1DSfM .npz or a reference .npz")
    if not est:
        raise InputError(f"{args.estimate}: no {VERTEX_TAG} lines")
    stats = evaluate(est, gt)
    missing = len(set(gt) - set(est))
    extra = len(set(est) - set(gt))
    if missing or extra:
        _warn(f"scored the {stats.num_nodes} common node(s) only: {missing} ground-truth "
              f"node(s) have no estimate, {extra} estimated node(s) have no ground truth")
    print(f"nodes {stats.num_nodes}  mean {stats.mean_deg:.3f} deg  "
          f"median {stats.median_deg:.3f} deg  max {stats.max_deg:.3f} deg")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from rotavg_ros.benchmark import main as bench_main

    return bench_main(list(args.bench_args))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rotavg", description="Filtered-DMF rotation averaging")
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("solve", help="solve a .g2o / 1DSfM .npz / EGs.txt graph")
    s.add_argument("input")
    s.add_argument("--output", "-o", required=True, help="output .g2o (node-to-world quats)")
    s.add_argument("--gt-only", action="store_true",
                   help="1DSfM .npz: keep only cameras with ground truth (paper protocol)")
    s.add_argument("--quiet", "-q", action="store_true",
                   help="no progress lines and no result line (warnings and errors still)")
    add_solver_arguments(s)
    s.set_defaults(func=cmd_solve)
    e = sub.add_parser("evaluate", help="gauge-align an estimate and print its errors")
    e.add_argument("estimate", help=".g2o written by 'rotavg solve'")
    e.add_argument("ground_truth", help="1DSfM .npz with R_gt, or a .npz with R_ref / R_gt")
    e.set_defaults(func=cmd_evaluate)
    b = sub.add_parser("bench", add_help=False,
                       help="benchmark on the shared data (python -m rotavg_ros.benchmark)")
    b.add_argument("bench_args", nargs=argparse.REMAINDER)
    b.set_defaults(func=cmd_bench)
    register_replay(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if args.command == "bench":  # everything after 'bench' belongs to the benchmark
        args.bench_args = [*args.bench_args, *extra]
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    try:
        return int(args.func(args))
    except InputError as exc:
        print(f"rotavg: error: {exc}", file=sys.stderr)
        return 2
    except (ValueError, OSError) as exc:
        print(f"rotavg: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
