"""Command line: ``rotavg solve | evaluate | replay | bench`` (also ``python -m rotavg_ros``).

Exit status 2 with a one-line ``rotavg: error: ...`` for a :class:`~rotavg_ros.errors.RotavgError`
(bad input or options); any other exception is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from rotavg_ros.cli.bench import cmd_bench
from rotavg_ros.cli.evaluate import HELP as EVALUATE_HELP
from rotavg_ros.cli.evaluate import cmd_evaluate
from rotavg_ros.cli.replay import register as register_replay
from rotavg_ros.cli.solve import cmd_solve
from rotavg_ros.cli.solver_args import add_solver_arguments
from rotavg_ros.errors import RotavgError

EXIT_INPUT = 2


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
    e = sub.add_parser("evaluate", help="gauge-align an estimate and print its errors",
                       description="Gauge-align an estimate to a ground truth and print the\n"
                       "mean / median / max per-node error in degrees.", epilog=EVALUATE_HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    e.add_argument("estimate", help=".g2o written by 'rotavg solve'")
    e.add_argument("ground_truth", help="1DSfM .npz with R_gt, or a .npz with R_ref / R_gt: "
                   "world-to-node rotations (see below)")
    e.set_defaults(func=cmd_evaluate)
    b = sub.add_parser("bench", add_help=False,
                       help="benchmark on the shared data (source checkout: "
                       "python -m benchmarks.paper)")
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
    except RotavgError as exc:
        print(f"rotavg: error: {exc}", file=sys.stderr)
        return EXIT_INPUT


if __name__ == "__main__":
    sys.exit(main())
