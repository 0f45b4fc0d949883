"""``rotavg replay BAG``: the command line of the offline replay."""

from __future__ import annotations

import argparse
import math
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rotavg_ros.app.parameters import NODE_NAME, PARAMETER_SPECS, settings_from_parameters
from rotavg_ros.cli import REPLAY_HELP
from rotavg_ros.cli.output import say
from rotavg_ros.cli.solver_args import add_solver_arguments, options_from_args
from rotavg_ros.errors import InputError
from rotavg_ros.replay.config import DEFAULT_GT_TOPIC, EXIT_INPUT, ReplayConfig
from rotavg_ros.replay.engine import run_replay


def register(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``replay`` to the ``rotavg`` command line (:func:`rotavg_ros.cli.build_parser`)."""
    p = subparsers.add_parser(
        "replay", help=REPLAY_HELP,
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
    p.add_argument("--merge-mcap-files", action="store_true",
                   help="BAG is a directory without metadata.yaml holding several .mcap "
                   "files: read them as one bag, in log-time order (refused otherwise)")
    p.add_argument("--quiet", "-q", action="store_true",
                   help="no progress bar and no per-solve lines (the summary is printed)")
    p.add_argument("--verbose", "-v", action="store_true", help="print the solver's progress")
    node = p.add_argument_group("node parameters (as rotavg_node's)")
    node.add_argument("--node-name", default=NODE_NAME)
    _add_parameter_flags(node, NODE_FLAGS[:7])
    node.add_argument("--no-markers", action="store_true")
    node.add_argument("--no-warm-start", action="store_true",
                      help="solve every period from scratch (default: warm-start each solve "
                      "from the previous one, as the node does)")
    _add_parameter_flags(node, NODE_FLAGS[7:])
    add_solver_arguments(p)
    p.set_defaults(func=cmd_replay)
    return p


NODE_FLAGS = ("world_frame", "anchor_frame", "repeat_policy", "quaternion_tolerance",
              "reference_variance", "min_weight", "max_weight", "marker_spacing",
              "residual_warn_deg", "left_out_warn_share")
"""Node parameters with a flag of their own (``--world-frame`` ...), made from the parameter
table; ``--no-markers`` and ``--no-warm-start`` set ``publish_markers`` and ``warm_start``,
the solver flags the solver parameters."""

_UNSET_BY_DEFAULT = frozenset({"reference_variance"})
"""Flags whose default is None, meaning the table's default (kept out of the help)."""


def _add_parameter_flags(group: Any, names: Sequence[str]) -> None:
    """One flag per node parameter, with the table's type, default, choices and description."""
    for name in names:
        spec = PARAMETER_SPECS[name]
        text = spec.description.replace("%", "%%")
        if name in _UNSET_BY_DEFAULT:
            default, text = None, f"{text} (default: the node's)"
        else:
            default, text = spec.default, f"{text} (default %(default)r)"
        kwargs: dict[str, Any] = {"default": default, "help": text}
        if spec.choices:
            kwargs["choices"] = spec.choices
        elif spec.type is not str:
            kwargs["type"] = spec.type
        group.add_argument("--" + name.replace("_", "-"), **kwargs)


def config_from_args(args: argparse.Namespace) -> ReplayConfig:
    """Build the :class:`ReplayConfig` (raises InputError / InputError for bad values)."""
    if args.solve_period is not None and not (
        math.isfinite(args.solve_period) and args.solve_period > 0
    ):
        raise InputError(f"--solve-period must be > 0, got {args.solve_period}")
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", args.node_name):
        raise InputError(f"--node-name must be a ROS node name, got {args.node_name!r}")
    options = options_from_args(args).replace_flat(progress=say if args.verbose else None)
    params: dict[str, Any] = {name: getattr(args, name) for name in NODE_FLAGS
                              if getattr(args, name) is not None}
    params.update({
        "publish_markers": not args.no_markers,
        "profile": args.profile,
        "mode": args.mode,
        "odometry": args.odometry,
        "class_noise": not args.no_class_noise,
        "odometry_bias": not args.no_odometry_bias,
        "settle_parallel": not args.no_settle_parallel,
        "warm_start": not args.no_warm_start,
        "depths": list(options.dense.depths),
    })
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
        merge_mcap_files=args.merge_mcap_files,
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
