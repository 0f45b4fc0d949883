"""The node's parameters (names, defaults, checks) and the :class:`Settings` built from them.

Shared by ``rotavg_node`` and ``rotavg replay``: both turn the same parameter values into the
same :class:`Settings`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.view_graph import RepeatPolicy
from rotavg_ros.errors import InputError
from rotavg_ros.msg_adapters.inputs import DEFAULT_REFERENCE_VARIANCE, AdapterConfig

NODE_NAME = "rotavg_node"

_SOLVER_DEFAULTS = SolverOptions()

PARAMETER_DEFAULTS: dict[str, Any] = {
    "world_frame": "world",
    "anchor_frame": "",
    "solve_period": 1.0,
    "repeat_policy": "merge",
    "quaternion_tolerance": 1e-3,
    "reference_variance": DEFAULT_REFERENCE_VARIANCE,
    "min_weight": 1e-3,
    "max_weight": 1e3,
    "mode": _SOLVER_DEFAULTS.mode,
    "depths": list(_SOLVER_DEFAULTS.depths),
    "iterations": _SOLVER_DEFAULTS.iterations,
    "sigma": _SOLVER_DEFAULTS.sigma,
    "seed": 0,
    "warm_start": True,
    "solve_in_subprocess": True,
    "solver_niceness": 10,
    "graph_file": "",
    "device": "cpu",
    "threads": 0,
    "publish_markers": True,
    "marker_spacing": 1.0,
    "residual_warn_deg": 5.0,
    "qos_depth": 10000,
    "orientations_qos_depth": 10000,
}
"""Every ``rotavg_node`` parameter and its default (the node adds descriptors and ranges)."""



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
    adapter: AdapterConfig
    solver: SolverOptions
    warm_start: bool = True


def solver_options_from_parameters(p: Mapping[str, Any]) -> SolverOptions:
    """The node's :class:`SolverOptions` (fields without a parameter keep their default)."""
    threads = int(p["threads"])
    return SolverOptions(
        mode=str(p["mode"]),
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

