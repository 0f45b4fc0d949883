"""The solver's command-line flags, shared by every command that solves."""

from __future__ import annotations

import argparse

from rotavg_ros.cli.output import say
from rotavg_ros.core.options import PROFILES, SolverOptions
from rotavg_ros.errors import InputError


def add_solver_arguments(parser: argparse.ArgumentParser) -> None:
    """Solver knobs shared by every command that solves."""
    d = SolverOptions()
    g = parser.add_argument_group("solver")
    g.add_argument("--profile", default="default", choices=tuple(PROFILES),
                   help="default: the filtered DMF, then a verification that re-solves every "
                   "edge robustly with the noise estimated from the data and keeps the "
                   "better-explaining solution; paper: Algorithm 1 and the DMF only, as "
                   "published (use it for the ablations) (default %(default)s)")
    g.add_argument("--odometry", default=d.verify.odometry,
                   choices=("auto", "consecutive", "none"),
                   help="which edges the default profile's verification trusts as odometry: "
                   "consecutive (nodes adjacent in their ids' natural order, kf_9 before "
                   "kf_10, where that chains more nodes than the order first named, else "
                   "that order; for ids with no order, the graph's own paths of nodes with "
                   "two edges), none, or auto (consecutive when they chain >= 90%% of the "
                   "nodes of a graph that joins at most half its node pairs) "
                   "(default %(default)s)")
    g.add_argument("--no-class-noise", action="store_true",
                   help="keep the weights as given: by default, where they do not tell the "
                   "odometry from the loop closures (the same median weight in both, e.g. "
                   "no covariances), the default profile estimates one "
                   "noise scale for the odometry and one for the loop closures and, where "
                   "they differ beyond doubt, solves again with the odometry weighted by "
                   "their ratio")
    g.add_argument("--no-settle-parallel", action="store_true",
                   help="keep a node pair's disagreeing measurements merged: by default, "
                   "where a pair is measured more than once with rotations that disagree, "
                   "those the solution disagrees with are set aside where others of the "
                   "pair agree, and the graph is solved again")
    g.add_argument("--no-odometry-bias", action="store_true",
                   help="keep the odometry as measured: by default, on an odometry chain "
                   "with sparse loop closures and at least 8 on one piece of it, the default "
                   "profile estimates a systematic bias of the odometry (one rotation a "
                   "step) from the loops the closures close over it and removes it where "
                   "the loops show it beyond the odometry's own drift")
    g.add_argument("--mode", default=d.mode, choices=("auto", "dense", "sparse"),
                   help="dense: the paper's DMF; sparse: chordal start + Huber + L-BFGS for "
                   "chain-like SLAM graphs; auto: by mean degree (default %(default)s)")
    g.add_argument("--seed", type=int, default=d.runtime.seed,
                   help="random seed; a seed gives bitwise-equal results on the CPU "
                   "(default %(default)s)")
    g.add_argument("--depths", default=",".join(map(str, d.dense.depths)),
                   help="candidate depths, comma separated; in dense mode the default "
                   "profile fits the shallowest and the deepest (default %(default)s)")
    g.add_argument("--iterations", type=int, default=d.dense.iterations,
                   help="dense mode: Adam iterations at most (default %(default)s)")
    g.add_argument("--tolerance", type=float, default=d.dense.tolerance,
                   help="dense mode early stopping: relative change of H per 25 iterations "
                   "(0 = off; default %(default)s)")
    g.add_argument("--dtype", default=d.dense.dtype, choices=("float32", "float64"),
                   help="dense mode: precision of the Adam fit (default %(default)s)")
    g.add_argument("--lr", type=float, default=d.dense.lr,
                   help="dense mode: initial Adam step size, cosine decay (default %(default)s)")
    g.add_argument("--sigma", type=float, default=d.filter.sigma,
                   help="filter threshold on d_chord(R_ij, R_ij^tree) (default %(default)s)")
    g.add_argument("--device", default=d.runtime.device, help="cpu, cuda or auto")
    g.add_argument("--threads", type=int, default=None,
                   help="CPU threads: torch's, split among the depth candidates, and the "
                   "verification's re-solves side by side (default or 0: one per candidate, "
                   "candidates and re-solves in parallel up to the CPU count)")
    g.add_argument("--hidden-width", type=int, default=None,
                   help="width of H's hidden factors (>= 3; default: min(3N, 64), with "
                   "--profile paper 3N up to 300 nodes)")
    g.add_argument("--no-filter", action="store_true", help="ablation (a)")
    g.add_argument("--no-support-count", action="store_true", help="ablation (b)")
    g.add_argument("--no-explicit-constraint", action="store_true", help="ablation (c)")
    g.add_argument("--no-reweighting", action="store_true", help="ablation (d)")


def options_from_args(args: argparse.Namespace) -> SolverOptions:
    try:
        depths = tuple(int(x) for x in str(args.depths).split(",") if x.strip())
    except ValueError as exc:
        raise InputError(f"--depths: expected comma-separated integers: {args.depths!r}") from exc
    progress = None if getattr(args, "quiet", False) else say
    return SolverOptions.for_profile(
        getattr(args, "profile", "default"),
        mode=args.mode, odometry=getattr(args, "odometry", "auto"),
        class_noise=not getattr(args, "no_class_noise", False),
        odometry_bias=not getattr(args, "no_odometry_bias", False), depths=depths,
        settle_parallel=not getattr(args, "no_settle_parallel", False),
        iterations=args.iterations, tolerance=args.tolerance,
        dtype=args.dtype, lr=args.lr, sigma=args.sigma,
        seed=args.seed, device=args.device,
        threads=None if args.threads == 0 else args.threads,  # 0 = default, as the node's
        hidden_width=args.hidden_width, use_filter=not args.no_filter,
        use_support_count=not args.no_support_count,
        explicit_constraint=not args.no_explicit_constraint,
        reweighting=not args.no_reweighting, progress=progress,
    )
