"""The node's ``/diagnostics`` status: level, message and key/values from its counters.

Message-free: the builders in ``rotavg_ros.msg_adapters.outputs`` turn these into a
``diagnostic_msgs/DiagnosticStatus``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from rotavg_ros.app.accumulator import AccumulatorStats
from rotavg_ros.app.parameters import Settings
from rotavg_ros.app.session import SolveBookkeeping
from rotavg_ros.core.result import SolveResult, listed_ids
from rotavg_ros.core.types import FloatArray
from rotavg_ros.msg_adapters.outputs import Level

MAX_DETACHED_LISTED = 20


def diagnostic_name(node_name: str) -> str:
    return f"{node_name}: rotation averaging"


def inlier_residuals_deg(result: SolveResult) -> FloatArray:
    return np.asarray(result.residuals_deg)[np.asarray(result.edge_inlier, bool)]


def diagnostic_values(
    stats: AccumulatorStats, book: SolveBookkeeping, settings: Settings,
    incompatible_qos_events: int = 0,
) -> tuple[Level, str, dict[str, Any]]:
    """``(level, message, key/values)`` of the node's ``DiagnosticStatus``.

    ``incompatible_qos_events``: the node's count of incompatible-QoS events on its topics
    (the replay has no DDS endpoints: 0).
    """
    result = book.last_result
    values: dict[str, Any] = {
        "nodes": stats.num_nodes,
        "measurements": stats.num_measurements,
        "edges_received": stats.received,
        "edges_accepted": stats.accepted,
        "edges_rejected": stats.num_rejected,
    }
    values.update(stats.rejected)
    values.update(stats.notes)
    problems: list[str] = []
    level = Level.OK
    if result is not None:
        inlier = inlier_residuals_deg(result)
        median = float(np.median(inlier)) if inlier.size else math.nan
        num_components = len(result.anchors)
        detached = describe_detached(result)
        values.update({
            "solved_nodes": len(result.node_ids),
            "solved_edges": int(np.asarray(result.residuals_deg).size),
            "anchor": str(result.anchors[0]) if result.anchors else "",
            "components": num_components,
            "detached_components": detached or "none",
            "filtered_outliers": result.num_filtered,
            "rejected_by_filter": result.num_filtered,
            "rejected_by_verification": result.num_rejected_verify,
            "readmitted_by_verification": result.num_readmitted,
            "relocalized_by_verification": result.num_relocalized,
            "closure_runs_left_out": result.num_runs_left_out,
            "trusted_odometry_edges": result.num_trusted_odometry,
            "distrusted_odometry_edges": result.num_distrusted_odometry,
            "unchecked_odometry_edges": result.num_unchecked_odometry,
            "verification": result.verification or "off",
            "noise_sigma_deg": result.noise_sigma_deg,
            "odometry_weight": result.odometry_weight,
            "odometry_bias_deg_per_step": result.odometry_bias_deg_per_step,
            "untested_loop_closures": result.num_untested,
            "parallel_measurements_set_aside": result.num_parallel_set_aside,
            "parallel_pairs_undecided": result.num_parallel_undecided,
            "nodes_contested": result.num_contested_nodes,
            "nodes_contested_ids": describe_contested(result) or "none",
            "depth": result.depth,
            "residual_median_deg": median,
            "residual_mean_deg": float(np.mean(inlier)) if inlier.size else math.nan,
            "residual_max_deg": float(np.max(inlier)) if inlier.size else math.nan,
        })
        if num_components > 1:
            level = Level.WARN
            problems.append(f"{num_components - 1} component(s) not connected to the anchor")
        if result.num_distrusted_odometry:
            level = Level.WARN
            problems.append(f"{result.num_distrusted_odometry} odometry edge(s) disagreed "
                            "with the loop closures across them and were left out")
        if result.num_unchecked_odometry:
            level = Level.WARN
            problems.append(f"{result.num_unchecked_odometry} odometry edge(s) kept against "
                            "a run of loop closures that nothing else checks")
        if result.num_untested:
            level = Level.WARN
            problems.append(f"{result.num_untested} loop closure(s) could not be tested")
        if result.num_parallel_undecided:
            level = Level.WARN
            problems.append(f"{result.num_parallel_undecided} node pair(s) measured with "
                            "rotations that disagree, which the solution could not settle: "
                            "their merged edge stands")
        if result.num_contested_nodes:
            level = Level.WARN
            problems.append(f"{result.num_contested_nodes} node(s) rest on one measurement "
                            "that others contradict: their rotations could not be checked")
        closures, left_out = loop_closures_left_out(result)
        values["loop_closures_left_out"] = f"{left_out} / {closures}"
        if closures >= MIN_CLOSURES_TO_WARN and left_out > settings.left_out_warn_share * closures:
            level = Level.WARN
            problems.append(f"{left_out} of {closures} loop closures left out: the answer "
                            "rests on the few that agree")
        if math.isfinite(median) and median > settings.residual_warn_deg:
            level = Level.WARN
            problems.append(
                f"median residual {median:.2f} deg > {settings.residual_warn_deg:g} deg"
            )
    values.update({
        "last_solve_duration_s": book.last_duration_s,
        "graph_version": stats.version,
        "solved_version": book.last_solved_version,
        "solves_completed": book.solves_ok,
        "solves_failed": book.solves_failed,
        "timer_ticks_skipped_busy": book.skipped_busy,
        "last_error": book.last_error or "none",
        "incompatible_qos_events": incompatible_qos_events,
    })
    if book.anchor_warning:
        level = max(level, Level.WARN)
        problems.insert(0, book.anchor_warning)
    if book.last_error:
        level = Level.ERROR
        problems.insert(0, f"last solve failed ({book.last_error}); keeping last result")
    if problems:
        message = "; ".join(problems)
    elif result is None:
        message = "waiting for edges"
    else:
        message = f"{len(result.node_ids)} nodes solved"
    return level, message, values


MIN_CLOSURES_TO_WARN = 10
"""The share of loop closures left out warns only where there are at least this many: on a
few, one wrong match is a large share."""


def loop_closures_left_out(result: SolveResult) -> tuple[int, int]:
    """``(loop closures, those the solution leaves out)``: the loop closures are the edges
    not trusted as odometry (every edge of a view graph), the odometry edges the solver
    stopped trusting apart (reported on their own)."""
    odometry = result.num_trusted_odometry + result.num_distrusted_odometry
    closures = int(np.asarray(result.edge_inlier).size) - odometry
    left_out = int(np.count_nonzero(~np.asarray(result.edge_inlier)))
    return closures, left_out - result.num_distrusted_odometry


def describe_contested(result: SolveResult) -> str:
    """The contested nodes' ids, comma-separated (the first :data:`MAX_DETACHED_LISTED`)."""
    return listed_ids(result.contested_ids(), MAX_DETACHED_LISTED)


def describe_detached(result: SolveResult) -> str:
    """``"anchor_a (5 nodes), anchor_b (2 nodes)"`` for components other than 0."""
    component = np.asarray(result.component)
    sizes = np.bincount(component, minlength=len(result.anchors))
    parts = [
        f"{result.anchors[c]} ({int(sizes[c])} nodes)"
        for c in range(1, min(len(result.anchors), MAX_DETACHED_LISTED + 1))
    ]
    if len(result.anchors) - 1 > MAX_DETACHED_LISTED:
        parts.append(f"... {len(result.anchors) - 1 - MAX_DETACHED_LISTED} more")
    return ", ".join(parts)

