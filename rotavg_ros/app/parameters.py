r"""The node's parameters (one table: name, default, range, description, read-only) and the
:class:`Settings` built from their values.

Shared by ``rotavg_node`` and ``rotavg replay``: both turn the same parameter values into the
same :class:`Settings`. :data:`PARAMETER_TABLE` is the one place a parameter is defined; the
node's ``ParameterDescriptor``\ s (:mod:`rotavg_ros.ros.node`), the replay's node-parameter
flags (:mod:`rotavg_ros.cli.replay`) and ``config/rotavg.yaml`` (:func:`parameters_yaml`;
regenerate with ``python -m rotavg_ros.app.parameters --write config/rotavg.yaml``) are made
from it. The solver parameters take their defaults from
:class:`~rotavg_ros.core.options.SolverOptions`. ROS-free: plain dataclasses.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rotavg_ros.core.options import PROFILES, SolverOptions
from rotavg_ros.core.view_graph import RepeatPolicy
from rotavg_ros.errors import InputError
from rotavg_ros.msg_adapters.inputs import DEFAULT_REFERENCE_VARIANCE, AdapterConfig

NODE_NAME = "rotavg_node"


@dataclass(frozen=True)
class FloatRange:
    """Inclusive range of a floating-point parameter (a ROS ``FloatingPointRange``)."""

    low: float
    high: float


@dataclass(frozen=True)
class IntRange:
    """Inclusive range of an integer parameter (a ROS ``IntegerRange``)."""

    low: int
    high: int


@dataclass(frozen=True)
class ParameterSpec:
    """One node parameter: its type is its default's (``bool``, ``int``, ``float``, ``str``
    or a list of ``int``)."""

    name: str
    default: Any
    description: str
    range: FloatRange | IntRange | None = None
    choices: tuple[str, ...] = ()
    """The accepted values of a string parameter (checked by :func:`validate_parameter`)."""
    constraints: str = ""
    """Constraint text for tools (a descriptor's ``additional_constraints``); with
    ``choices`` and no text, "one of: ..."."""
    read_only: bool = False
    """Set at start only (a ROS read-only parameter)."""

    @property
    def type(self) -> type:
        return type(self.default)

    @property
    def constraint_text(self) -> str:
        if self.constraints or not self.choices:
            return self.constraints
        return "one of: " + ", ".join(self.choices)


_SOLVER = SolverOptions()
EDGE_RELIABILITIES = ("reliable", "best_effort")

PARAMETER_TABLE: tuple[ParameterSpec, ...] = (
    ParameterSpec(
        "world_frame", "world",
        "Frame id of the published orientations' header (the parent frame in TF).",
        constraints="non-empty frame id without '/' prefix"),
    ParameterSpec(
        "anchor_frame", "",
        "Frame that gets the identity rotation; empty = the first frame accepted."),
    ParameterSpec(
        "solve_period", 1.0,
        "Seconds between timer checks; a solve starts only if the graph changed.",
        range=FloatRange(0.01, 3600.0), read_only=True),
    ParameterSpec(
        "repeat_policy", RepeatPolicy.MERGE.value,
        "How repeated measurements of one frame pair combine: merge (robust average, weights "
        "add), latest (newest wins) or first (oldest wins).",
        choices=tuple(p.value for p in RepeatPolicy), read_only=True),
    ParameterSpec(
        "quaternion_tolerance", 1e-3,
        "Accepted | |q| - 1 |; within it the quaternion is normalised, beyond it the edge is "
        "rejected as non_unit_quaternion.", range=FloatRange(0.0, 0.5)),
    ParameterSpec(
        "reference_variance", DEFAULT_REFERENCE_VARIANCE,
        "Per-axis rotation variance (rad^2) of an Odometry edge that gets weight 1; "
        "weight = 3 * reference_variance / trace(rotation covariance). Default (1 deg)^2.",
        range=FloatRange(1e-12, 10.0)),
    ParameterSpec(
        "min_weight", 1e-3,
        "Lower clamp of covariance-derived edge weights.", range=FloatRange(1e-9, 1e9)),
    ParameterSpec(
        "max_weight", 1e3,
        "Upper clamp of covariance-derived edge weights.", range=FloatRange(1e-9, 1e9)),
    ParameterSpec(
        "profile", "default",
        "Solver profile: default (filtered DMF, then a verification that re-solves every edge "
        "robustly with the noise estimated from the data and keeps the better-explaining "
        "solution) or paper (Algorithm 1 and the DMF only, as published).",
        choices=tuple(PROFILES)),
    ParameterSpec(
        "odometry", _SOLVER.verify.odometry,
        "Which edges the default profile's verification trusts as odometry (known inliers, "
        "never outvoted by loop closures): consecutive (frames adjacent in their names' "
        "natural order, kf_9 before kf_10, where that chains more frames than the order "
        "they were first seen, else that order; for ids with no order, the graph's own "
        "paths of frames with two edges; e.g. consecutive keyframes), none, or auto "
        "(consecutive when they chain at least 90% of the frames of a graph that joins at "
        "most half its frame pairs; a near-complete SfM view graph: none).",
        choices=("auto", "consecutive", "none")),
    ParameterSpec(
        "class_noise", _SOLVER.verify.class_noise,
        "Where the weights do not tell odometry from loop closures (the same median weight "
        "in both: no covariances sent) and the graph has odometry: the default profile "
        "estimates one noise scale for the "
        "odometry and one for the loop closures and, where they differ beyond doubt, solves "
        "again with the odometry weighted by their ratio (diagnostic odometry_weight). "
        "false: the weights stay as given."),
    ParameterSpec(
        "odometry_bias", _SOLVER.verify.odometry_bias,
        "On an odometry chain with sparse loop closures (redundancy below 0.15) and at least "
        "8 closures on one unbroken piece of it: the default profile estimates a systematic "
        "bias of the odometry (one rotation a step, a gyro's bias) from the loops the "
        "closures close over it and, where the loops show it beyond the odometry's own "
        "drift in both halves of the trajectory, removes it from the odometry before the "
        "solve (diagnostic odometry_bias_deg_per_step). false: the odometry stays as "
        "measured."),
    ParameterSpec(
        "settle_parallel", _SOLVER.verify.settle_parallel,
        "Where a frame pair is measured more than once with rotations that disagree (two "
        "hypotheses; repeat_policy merge averages them into one edge between them): after "
        "the solve, the measurements the solution disagrees with are set aside where others "
        "of the pair agree, and the graph is solved again (diagnostics "
        "parallel_measurements_set_aside, parallel_pairs_undecided). false: the merged edge "
        "stands."),
    ParameterSpec(
        "mode", _SOLVER.mode,
        "Solver variant: dense (the paper's DMF), sparse (chordal warm start + Huber + "
        "L-BFGS, for chain-like SLAM graphs) or auto (by mean degree).",
        choices=("auto", "dense", "sparse")),
    ParameterSpec(
        "depths", list(_SOLVER.dense.depths),
        "Candidate DMF depths (positive, even); the one with the lowest cost wins. Dense "
        "mode: the default profile fits the shallowest and the deepest of them, the paper "
        "profile every one.",
        constraints="non-empty list of positive even integers"),
    ParameterSpec(
        "iterations", _SOLVER.dense.iterations,
        "Gradient iterations of the DMF optimisation per depth.",
        range=IntRange(1, 10_000_000)),
    ParameterSpec(
        "sigma", _SOLVER.filter.sigma,
        "Spanning-tree filter threshold on the chordal distance d_chord(R_ij, R_ij^tree).",
        range=FloatRange(0.0, 2.83)),
    ParameterSpec(
        "seed", _SOLVER.runtime.seed, "Random seed of the solver.",
        range=IntRange(0, 2**31 - 1)),
    ParameterSpec(
        "warm_start", True,
        "Warm-start each re-solve from the previous solution (known nodes keep their "
        "rotation, new ones start from the spanning tree; dense mode then runs a short "
        "fit at the previous depth)."),
    ParameterSpec(
        "solve_in_subprocess", True,
        "Run the solver in a child process (default) so a long solve cannot starve the "
        "subscriptions of the interpreter lock; false runs it in the worker thread.",
        read_only=True),
    ParameterSpec(
        "solver_niceness", 10,
        "Added to the solver child process's nice value (POSIX), so solves use the CPU the "
        "node and its neighbours (a SLAM front end) leave idle; 0 = same priority as the "
        "node.", range=IntRange(0, 19), read_only=True),
    ParameterSpec(
        "graph_file", "",
        "g2o file of the live graph (rotavg_ros.io.graph_store format): loaded at start when "
        "it exists, written by ~/save_graph and on a clean shutdown; empty = no persistence.",
        read_only=True),
    ParameterSpec(
        "device", _SOLVER.runtime.device,
        "Torch device of the solver: cpu, cuda, cuda:N or auto (CUDA when available).",
        constraints="cpu, cuda, cuda:N or auto"),
    ParameterSpec(
        "threads", _SOLVER.runtime.threads or 0,  # SolverOptions' None is the node's 0
        "CPU threads for the solver: torch's, split among the depth candidates, and the "
        "verification's re-solves from different starts side by side; 0 = one thread per "
        "candidate, candidates (and re-solves) in parallel up to the CPU count.",
        range=IntRange(0, 1024)),
    ParameterSpec(
        "publish_markers", True,
        "Publish ~/markers (RViz MarkerArray) after solves, when something subscribes."),
    ParameterSpec(
        "marker_spacing", 1.0,
        "Grid spacing (m) of the marker layout (there are no translations to show).",
        range=FloatRange(0.01, 100.0)),
    ParameterSpec(
        "residual_warn_deg", 5.0,
        "Diagnostics turn WARN when the median inlier residual exceeds this (deg).",
        range=FloatRange(0.0, 180.0)),
    ParameterSpec(
        "left_out_warn_share", 0.6,
        "Diagnostics turn WARN when the solution leaves out more than this share of the "
        "loop closures (edges not trusted as odometry; at least 10 of them): the answer then "
        "rests on the few that agree.",
        range=FloatRange(0.0, 1.0)),
    ParameterSpec(
        "qos_depth", 10000,
        "KEEP_LAST depth of the edge subscriptions.",
        range=IntRange(1, 1_000_000), read_only=True),
    ParameterSpec(
        "edge_reliability", "reliable",
        "Reliability of the edge subscriptions: reliable (no edge lost, but a best-effort "
        "publisher does not match at all: incompatible QoS, logged and counted) or "
        "best_effort (matches reliable and best-effort publishers; edges can be dropped).",
        choices=EDGE_RELIABILITIES, read_only=True),
    ParameterSpec(
        "orientations_qos_depth", 10000,
        "KEEP_LAST depth of ~/orientations; a solve publishes one message per node, so keep "
        "it at least the number of nodes.", range=IntRange(1, 10_000_000), read_only=True),
)
"""Every ``rotavg_node`` parameter, in declaration order."""

PARAMETER_SPECS: dict[str, ParameterSpec] = {spec.name: spec for spec in PARAMETER_TABLE}

PARAMETER_DEFAULTS: dict[str, Any] = {spec.name: spec.default for spec in PARAMETER_TABLE}
"""Every ``rotavg_node`` parameter and its default."""


def validate_parameter(name: str, value: Any) -> str | None:
    """Reason why ``value`` is not acceptable for parameter ``name``, or None.

    The solver parameters (``mode``, ``depths``, ``iterations``, ``sigma``, ``device``, ...)
    are checked together by :meth:`SolverOptions.validate` in :func:`settings_from_parameters`.
    """
    if name == "repeat_policy":
        try:
            RepeatPolicy(value)
        except ValueError:
            return f"repeat_policy must be one of merge, latest, first; got {value!r}"
    elif name == "edge_reliability":
        if value not in EDGE_RELIABILITIES:
            return f"edge_reliability must be reliable or best_effort; got {value!r}"
    elif name == "world_frame":
        if not value or value.startswith("/") or not value.isprintable() or " " in value:
            return f"world_frame must be a non-empty tf2 frame id; got {value!r}"
    elif name in ("min_weight", "max_weight", "reference_variance", "marker_spacing"):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            return f"{name} must be a finite number > 0; got {value!r}"
    return None


@dataclass(frozen=True)
class Settings:
    """Parameter values as used by the node and the replay."""

    world_frame: str
    anchor_frame: str
    publish_markers: bool
    marker_spacing: float
    residual_warn_deg: float
    left_out_warn_share: float
    adapter: AdapterConfig
    solver: SolverOptions
    warm_start: bool = True


def solver_options_from_parameters(p: Mapping[str, Any]) -> SolverOptions:
    """The node's :class:`SolverOptions` (fields without a parameter keep their default)."""
    threads = int(p["threads"])
    return SolverOptions.for_profile(
        str(p["profile"]),
        mode=str(p["mode"]),
        odometry=str(p["odometry"]),
        class_noise=bool(p["class_noise"]),
        odometry_bias=bool(p["odometry_bias"]),
        settle_parallel=bool(p["settle_parallel"]),
        depths=tuple(int(d) for d in p["depths"]),
        iterations=int(p["iterations"]),
        sigma=float(p["sigma"]),
        seed=int(p["seed"]),
        device=str(p["device"]),
        threads=threads if threads > 0 else None,
    )


def settings_from_parameters(
    values: Mapping[str, Any], solver: SolverOptions | None = None
) -> Settings:
    """:class:`Settings` from parameter values (missing names take their default).

    ``solver`` replaces the options built from the solver parameters (the replay passes the
    ones from its command line). Raises ``ValueError`` for an invalid value or
    ``min_weight > max_weight``.
    """
    unknown = set(values) - set(PARAMETER_DEFAULTS)
    if unknown:
        raise InputError(f"unknown parameter(s): {', '.join(sorted(unknown))}")
    p = {**PARAMETER_DEFAULTS, **values}
    for name, value in p.items():
        reason = validate_parameter(name, value)
        if reason is not None:
            raise InputError(reason)
    if float(p["min_weight"]) > float(p["max_weight"]):
        raise InputError("min_weight > max_weight")
    options = solver if solver is not None else solver_options_from_parameters(p)
    options.validate()
    return Settings(
        world_frame=str(p["world_frame"]),
        anchor_frame=str(p["anchor_frame"]),
        publish_markers=bool(p["publish_markers"]),
        marker_spacing=float(p["marker_spacing"]),
        residual_warn_deg=float(p["residual_warn_deg"]),
        left_out_warn_share=float(p["left_out_warn_share"]),
        adapter=AdapterConfig(
            quaternion_tolerance=float(p["quaternion_tolerance"]),
            reference_variance=float(p["reference_variance"]),
            min_weight=float(p["min_weight"]),
            max_weight=float(p["max_weight"]),
            reserved_frames=frozenset({str(p["world_frame"])}),
        ),
        solver=options,
        warm_start=bool(p["warm_start"]),
    )



# --------------------------------------------------------------------------- params file

_YAML_HEADER = """\
# Parameters of rotavg_node (rotavg_ros/ros/node.py); every value here is the default.
# Generated from rotavg_ros/app/parameters.py: python -m rotavg_ros.app.parameters --write FILE
# Load with:  rotavg_node --ros-args --params-file config/rotavg.yaml
# The key below matches a node named rotavg_node in any namespace; use "/**" for every node.
/**/rotavg_node:
  ros__parameters:
"""

_PLAIN_STRING = re.compile(r"[A-Za-z_][A-Za-z0-9_:./-]*")
_YAML_WORDS = {"true", "false", "yes", "no", "on", "off", "null", "y", "n", "~"}


def yaml_value(value: Any) -> str:
    """``value`` as a YAML scalar or flow list that ROS reads back with the same type."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        text = repr(value)
        mantissa, e, exponent = text.partition("e")
        if "." not in mantissa and mantissa not in ("inf", "-inf", "nan"):
            text = f"{mantissa}.0{e}{exponent}"  # a double, never an integer or a string
        return text
    if isinstance(value, str):
        plain = _PLAIN_STRING.fullmatch(value) and value.lower() not in _YAML_WORDS
        return value if plain else json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(yaml_value(v) for v in value) + "]"
    raise TypeError(f"no YAML form for {value!r}")


def _range_text(spec: ParameterSpec) -> str:
    parts = []
    if spec.range is not None:
        if isinstance(spec.range, IntRange):
            parts.append(f"range {spec.range.low} to {spec.range.high}")
        else:
            parts.append(f"range {spec.range.low:g} to {spec.range.high:g}")
    if spec.constraint_text:
        parts.append(spec.constraint_text)
    if spec.read_only:
        parts.append("read-only: set at start")
    return "; ".join(parts)


def _type_name(spec: ParameterSpec) -> str:
    if isinstance(spec.default, list):
        return "integer array"
    return {bool: "bool", int: "integer", float: "double", str: "string"}[spec.type]


def parameters_help(prog: str = NODE_NAME) -> str:
    """``rotavg_node --help``: usage and every parameter with its type, default, range or
    choices, whether it is read-only, and its description."""
    lines = [
        f"usage: {prog} [-h] [--ros-args [-p NAME:=VALUE ...] [--params-file FILE] ...]",
        "",
        "Live rotation averaging: relative rotations in on ~/edges (TransformStamped) and",
        "~/edges_with_covariance (Odometry), absolute orientations out on ~/orientations.",
        "An integer is accepted for a double parameter. Read-only parameters are set at start",
        "only; the others can also be changed at run time.",
        "",
        "parameters:",
    ]
    for spec in PARAMETER_TABLE:
        head = f"  {spec.name} ({_type_name(spec)}, default {yaml_value(spec.default)})"
        extra = _range_text(spec)
        lines.append(head + (f" [{extra}]" if extra else ""))
        lines += textwrap.wrap(spec.description, width=92, initial_indent="      ",
                               subsequent_indent="      ", break_on_hyphens=False)
    lines += ["", "Example: rotavg_node --ros-args --params-file config/rotavg.yaml "
              "-p solve_period:=0.5"]
    return "\n".join(lines) + "\n"


def parameters_yaml() -> str:
    """The text of ``config/rotavg.yaml``: every parameter at its default, each under a
    comment with its description, range and whether it is read-only."""
    lines = [_YAML_HEADER.rstrip("\n")]
    for k, spec in enumerate(PARAMETER_TABLE):
        if k:
            lines.append("")
        lines += textwrap.wrap(spec.description, width=92, initial_indent="    # ",
                               subsequent_indent="    # ", break_on_hyphens=False)
        extra = _range_text(spec)
        if extra:
            lines.append(f"    # [{extra}]")
        lines.append(f"    {spec.name}: {yaml_value(spec.default)}")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m rotavg_ros.app.parameters --yaml`` prints the params file; ``--write FILE``
    writes it."""
    p = argparse.ArgumentParser(prog="python -m rotavg_ros.app.parameters",
                                description="Generate rotavg_node's params file from the "
                                "parameter table.")
    out = p.add_mutually_exclusive_group(required=True)
    out.add_argument("--yaml", action="store_true", help="print it")
    out.add_argument("--write", metavar="FILE", help="write it to FILE (config/rotavg.yaml)")
    args = p.parse_args(argv)
    text = parameters_yaml()
    if args.write:
        Path(args.write).write_text(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
