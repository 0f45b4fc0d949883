"""``rotavg replay BAG``: the command line of the offline replay."""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rotavg_ros.app.parameters import NODE_NAME, settings_from_parameters
from rotavg_ros.cli.output import say
from rotavg_ros.cli.solver_args import add_solver_arguments, options_from_args
from rotavg_ros.errors import InputError
from rotavg_ros.replay.config import DEFAULT_GT_TOPIC, EXIT_INPUT, ReplayConfig
from rotavg_ros.replay.engine import run_replay


def register(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``replay`` to the ``rotavg`` command line (called by :mod:`rotavg_ros.cli.main`)."""
    p = subparsers.add_parser(
        "replay", help="replay a rosbag2 MCAP bag through the node's pipeline, offline",
        description="Replay a rosbag2 MCAP bag (directory or lone .mcap) through the same "
        "adapters, accumulator and solver as rotavg_node, without ROS. Exit status: 0 ok, "
        "1 nothing usable in the bag, 2 bad input, 3 the last solve failed.")
    p.add_argument("bag", help="rosbag2 directory (with metadata.yaml) or a .mcap file")
    p.add_argument("--output", "-o", help="write the node's outputs to this new bag directory")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --output bag")
    when = p.add_mutually_exclusive_group()
    when.add_argument("--solve-period", type=float, metavar="SECONDS",
                      help="solve like the node's timer, every SECONDS of bag time")
    when.add_argument("--solve-once", action="store_true",
                      help="one solve after the last message (the default)")
    p.add_argument("--output-g2o", metavar="FILE", help="write the final orientations as g2o")
    p.add_argument("--ground-truth-topic", default=DEFAULT_GT_TOPIC, metavar="TOPIC",
                   help="TransformStamped/TFMessage world->node ground truth "
                   "(default %(default)s; '' to ignore; a topic named /ground_truth is "
                   "never an edge topic unless named in --edge-topics)")
    p.add_argument("--edge-topics", nargs="+", metavar="TOPIC",
                   help="edge topics (default: every TransformStamped, Odometry and TFMessage "
                   "topic except the ground truth, /tf and /tf_static)")
    p.add_argument("--quiet", "-q", action="store_true",
                   help="no progress bar and no per-solve lines (the summary is printed)")
    p.add_argument("--verbose", "-v", action="store_true", help="print the solver's progress")
    node = p.add_argument_group("node parameters (as rotavg_node's)")
    node.add_argument("--node-name", default=NODE_NAME)
    node.add_argument("--world-frame", default="world")
    node.add_argument("--anchor-frame", default="")
    node.add_argument("--repeat-policy", default="merge", choices=("merge", "latest", "first"))
    node.add_argument("--quaternion-tolerance", type=float, default=1e-3)
    node.add_argument("--reference-variance", type=float, default=None,
                      help="rad^2 per axis that maps to weight 1 (default (1 deg)^2)")
    node.add_argument("--min-weight", type=float, default=1e-3)
    node.add_argument("--max-weight", type=float, default=1e3)
    node.add_argument("--no-markers", action="store_true")
    node.add_argument("--no-warm-start", action="store_true",
                      help="solve every period from scratch (default: warm-start each solve "
                      "from the previous one, as the node does)")
    node.add_argument("--marker-spacing", type=float, default=1.0)
    node.add_argument("--residual-warn-deg", type=float, default=5.0)
    add_solver_arguments(p)
    p.set_defaults(func=cmd_replay)
    return p


def config_from_args(args: argparse.Namespace) -> ReplayConfig:
    """Build the :class:`ReplayConfig` (raises InputError / InputError for bad values)."""
    if args.solve_period is not None and not (
        math.isfinite(args.solve_period) and args.solve_period > 0
    ):
        raise InputError(f"--solve-period must be > 0, got {args.solve_period}")
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", args.node_name):
        raise InputError(f"--node-name must be a ROS node name, got {args.node_name!r}")
    options = dataclasses.replace(
        options_from_args(args),
        progress=say if args.verbose else None)
    params: dict[str, Any] = {
        "world_frame": args.world_frame,
        "anchor_frame": args.anchor_frame,
        "repeat_policy": args.repeat_policy,
        "quaternion_tolerance": args.quaternion_tolerance,
        "min_weight": args.min_weight,
        "max_weight": args.max_weight,
        "publish_markers": not args.no_markers,
        "marker_spacing": args.marker_spacing,
        "residual_warn_deg": args.residual_warn_deg,
        "mode": args.mode,
        "warm_start": not args.no_warm_start,
        "depths": list(options.depths),
    }
    if args.reference_variance is not None:
        params["reference_variance"] = args.reference_variance
    try:
        settings = settings_from_parameters(params, solver=options)
    except ValueError as exc:
        raise InputError(str(exc)) from exc
    edge_topics = None
    if args.edge_topics is not None:
        edge_topics = [t.strip() for item in args.edge_topics for t in item.split(",")
                       if t.strip()]
    return ReplayConfig(
        bag=Path(args.bag),
        settings=settings,
        repeat_policy=args.repeat_policy,
        solve_period=args.solve_period,
        output=Path(args.output) if args.output else None,
        overwrite=args.overwrite,
        output_g2o=Path(args.output_g2o) if args.output_g2o else None,
        gt_topic=args.ground_truth_topic,
        edge_topics=edge_topics,
        node_name=args.node_name,
        quiet=args.quiet,
    )


def cmd_replay(args: argparse.Namespace) -> int:
    try:
        config = config_from_args(args)
        report = run_replay(config)
    except InputError as exc:
        print(f"rotavg replay: error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    return report.exit_code


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m rotavg_ros.cli.replay BAG ...`` (same as ``rotavg replay``)."""
    from rotavg_ros.cli import main as cli_main

    return cli_main(["replay", *(argv if argv is not None else sys.argv[1:])])


if __name__ == "__main__":
    sys.exit(main())
