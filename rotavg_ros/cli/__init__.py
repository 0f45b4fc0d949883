"""Command line: ``rotavg solve | evaluate | replay | bench`` (also ``python -m rotavg_ros``).

Exit status 2 with a one-line ``rotavg: error: ...`` for a :class:`~rotavg_ros.errors.RotavgError`
(bad input or options); any other exception is a bug and keeps its traceback.

Start-up stays light: this module registers the arguments with argparse only, and each command's
module (with torch, the bag readers, ...) is imported by its handler when that command runs;
``replay``'s arguments, which need the node's parameter table, are registered only when
``replay`` is the command (the other commands keep its help line).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence

from rotavg_ros.cli.solver_args import add_solver_arguments
from rotavg_ros.errors import RotavgError

EXIT_INPUT = 2

EVALUATE_HELP = """\
Ground-truth convention: rotations R_i are world-to-node (x_node = R_i x_world), the
convention in which an edge measures R_ij = R_i R_j^T; the 1DSfM R_gt arrays are in it.
In a .npz, R_ref (or else R_gt) holds them, one row per node id. The estimate's g2o
vertices are node-to-world (g2o's convention, as 'rotavg solve' and 'rotavg replay
--output-g2o' write them) and are transposed on reading. Errors are per-node geodesic
angles after the best gauge alignment R_est_i ~ R_gt_i Q. If the ground truth fits far
better transposed (mean error under half, and 5 degrees or more lower), evaluate warns
that it looks node-to-world; transpose it before comparing.
"""
REPLAY_HELP = "replay a rosbag2 MCAP bag through the node's pipeline, offline"


def _solve(args: argparse.Namespace) -> int:
    from rotavg_ros.cli.solve import cmd_solve

    return cmd_solve(args)


def _evaluate(args: argparse.Namespace) -> int:
    from rotavg_ros.cli.evaluate import cmd_evaluate

    return cmd_evaluate(args)


def _bench(args: argparse.Namespace) -> int:
    from rotavg_ros.cli.bench import cmd_bench

    return cmd_bench(args)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``rotavg`` parser; given ``command`` (from :func:`main`), ``replay``'s arguments are
    registered only when it is that command (its help line is always listed)."""
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
    s.set_defaults(func=_solve)
    e = sub.add_parser("evaluate", help="gauge-align an estimate and print its errors",
                       description="Gauge-align an estimate to a ground truth and print the\n"
                       "mean / median / max per-node error in degrees.", epilog=EVALUATE_HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    e.add_argument("estimate", help=".g2o written by 'rotavg solve'")
    e.add_argument("ground_truth", help="1DSfM .npz with R_gt, or a .npz with R_ref / R_gt: "
                   "world-to-node rotations (see below)")
    e.set_defaults(func=_evaluate)
    b = sub.add_parser("bench", add_help=False,
                       help="benchmark on the shared data (source checkout: "
                       "python -m benchmarks.paper)")
    b.add_argument("bench_args", nargs=argparse.REMAINDER)
    b.set_defaults(func=_bench)
    if command is None or command == "replay":
        from rotavg_ros.cli.replay import register as register_replay

        register_replay(sub)
    else:  # its help line only: the node's parameter table and the bag readers stay unloaded
        sub.add_parser("replay", help=REPLAY_HELP)
    return p


def _command(argv: Sequence[str]) -> str:
    """The subcommand named in ``argv`` (``rotavg`` itself has no option taking a value)."""
    return next((a for a in argv if not a.startswith("-")), "")


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(_command(argv))
    args, extra = parser.parse_known_args(argv)
    if args.command == "bench":  # everything after 'bench' belongs to the benchmark
        args.bench_args = [*args.bench_args, *extra]
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    try:
        return int(args.func(args))
    except RotavgError as exc:
        print(f"rotavg: error: {exc}", file=sys.stderr)
        return EXIT_INPUT


def run() -> None:
    """The console entry (``rotavg``, ``python -m rotavg_ros``): :func:`main`, then a fast
    exit with its status.

    Every command has closed its files when :func:`main` returns; what is left is the
    interpreter's teardown of torch's modules and thread pools (about 0.4 s of a 4.5 s
    Ellis Island solve on 2 cores), which does nothing for the user. So once logging and
    the standard streams are flushed, the process ends with ``os._exit``. An exception or
    ``SystemExit`` (argparse's usage errors) leaves the normal way.
    """
    code = main()
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more can reach it
            pass
    os._exit(code)


if __name__ == "__main__":
    run()
