"""What the rotation averager returns.

Conventions: rotations are world-to-node (``x_node = R_i x_world``); edges carry
``R_ij ~= R_i R_j^T``. The anchor node of each connected component gets identity.
"""

from __future__ import annotations

import math
from collections.abc import Hashable
from dataclasses import dataclass, field

import numpy as np

from rotavg_ros.core.types import BoolArray, FloatArray, IntArray

MAX_SIZES_LISTED = 8


@dataclass
class SolveResult:
    """Absolute rotations for every node of the graph that was solved."""

    node_ids: list[Hashable]
    rotations: FloatArray
    """(N, 3, 3) world-to-node rotations; each component's anchor is identity."""
    component: IntArray
    """(N,) component label; 0 is the anchor's component."""
    anchors: list[Hashable]
    """Anchor node id of each component, by label."""
    depth: int
    """Depth chosen for the largest component (0 when no DMF was fitted: no edges, or
    the verification kept its least-squares re-solve without one)."""
    residuals_deg: FloatArray
    """(E,) angular residual of every consolidated input edge against the solution."""
    edge_inlier: BoolArray
    """(E,) False for edges the final solution treats as outliers (removed by the filter
    and not re-admitted by the verification, or rejected by the verification)."""
    num_filtered: int
    """Edges the spanning-tree filter removed."""
    cost_by_depth: dict[int, float]
    duration_s: float
    iterations_by_depth: dict[int, int] = field(default_factory=dict)
    """Iterations each depth's fit ran (largest component; dense mode: at most
    ``iterations``, fewer when stopped early; sparse mode: the L-BFGS steps over all its
    rounds; empty when no DMF was fitted)."""
    num_rejected_verify: int = 0
    """Edges the filter kept and the verification rejected."""
    num_readmitted: int = 0
    """Edges the filter removed and the verification re-admitted."""
    noise_sigma_deg: float = math.nan
    """Per-axis noise of a unit-weight edge estimated from the data (largest component;
    NaN when the verification did not run). On a planar problem (every measurement about one
    axis, no odometry chain) the heading noise: about twice what the three-axis model read
    there before the one-axis model."""
    num_untested: int = 0
    """Loop closures (edges off a spanning tree) whose consistency no check could test: the
    ``paper`` profile tests only edges on triangles (or on a triangle-verified tree path);
    the verification tests every edge on a cycle."""
    num_relocalized: int = 0
    """Nodes the verification moved to where their own edges agree (relocalization)."""
    num_runs_left_out: int = 0
    """Runs of mutually consistent loop closures (between the same two stretches of the
    trajectory) that the verification left out as wholes: perceptual aliasing."""
    num_trusted_odometry: int = 0
    """Odometry edges the verification trusted as inliers (option ``odometry``)."""
    num_distrusted_odometry: int = 0
    """Odometry edges the verification stopped trusting and left out: the loop closures
    across them disagreed with them (a front end's wrong step, e.g. a track lost)."""
    num_unchecked_odometry: int = 0
    """Odometry edges kept on their own word: loop closures disagreed with them, the fit
    without them explained the data better, but nodes hang by each against one run of
    those closures alone (one piece of evidence against one step; perceptual aliasing as
    well as a lost track), so the step stands unchecked."""
    verification: str = ""
    """Which solution the verification kept (largest component): ``dmf`` (the filtered
    DMF), ``robust`` (its least-squares re-solve on every edge), ``dmf_refit`` (the re-solve
    won the choice and a DMF fitted on its inliers replaced it), ``failed`` (the
    verification raised; the DMF solution stands) or empty (``paper`` profile); with
    ``+ls``, ``+l1``, ``+huber`` or ``+cauchy`` where the cross-validation's fit of the
    inliers replaced the kept solution (``+l1-halfway``, ``+huber-halfway``: the folds tied,
    and the answer is halfway between that fit and least squares')."""
    pruned_depths: tuple[int, ...] = ()
    """Depth candidates the candidate race stopped early (largest component; option
    ``prune_ratio``): never chosen; their ``cost_by_depth`` is of the unfinished fit and
    their ``iterations_by_depth`` where they stopped."""
    odometry_weight: float = 1.0
    """Factor on the odometry edges' weights relative to the loop closures', estimated from
    the solution's inliers where the input weights did not tell the two apart and their
    noise differed beyond doubt (largest component; option ``class_noise``,
    :mod:`rotavg_ros.core.robust.class_noise`); 1 where not used."""
    odometry_bias_deg_per_step: float = 0.0
    """The odometry's systematic bias, degrees a step, estimated from the loop closures and
    removed from the odometry before the solve (largest component; option
    ``odometry_bias``, :mod:`rotavg_ros.core.robust.odometry_bias`); 0 where none was.
    ``residuals_deg`` are against the measurements as given, bias included."""
    num_parallel_set_aside: int = 0
    """Measurements of a node pair measured more than once that disagreed with the solution
    where the pair's other measurements agreed: set aside, the pair's edge merged again from
    the rest, and solved again (option ``settle_parallel``,
    :mod:`rotavg_ros.core.robust.parallel_measurements`). ``residuals_deg`` and
    ``edge_inlier`` are then those of the edges solved: one per pair, as before."""
    num_parallel_undecided: int = 0
    """Node pairs measured more than once with rotations that disagree with each other which
    the solution could not settle (none agrees with it, or only the pair's own edge joins
    its ends): their edge stays the merged one, a median between them."""
    node_contested: BoolArray = field(default_factory=lambda: np.zeros(0, bool))
    """(N,) per node (``node_ids`` order): its rotation rests on one kept edge that edges the
    solution left out contradict, so nothing checked it (a bridge of the inliers, not kept
    odometry, that outliers cross; or no inlier joins it to its anchor:
    :mod:`rotavg_ros.core.robust.contested_nodes`). Empty where not judged."""

    @property
    def num_contested_nodes(self) -> int:
        """Nodes of :attr:`node_contested`."""
        return int(np.count_nonzero(self.node_contested))

    def contested_ids(self) -> list[Hashable]:
        """The ids of the :attr:`node_contested` nodes, in ``node_ids`` order."""
        return [self.node_ids[k] for k in np.flatnonzero(self.node_contested)]


MAX_CONTESTED_LISTED = 10
"""Contested node ids :func:`contested_warning` names."""


def listed_ids(ids: list[Hashable], limit: int) -> str:
    """``"a, b, c"``: the first ``limit`` of ``ids``, then ``", ... N more"``."""
    listed = ", ".join(str(k) for k in ids[:limit])
    if len(ids) > limit:
        listed += f", ... {len(ids) - limit} more"
    return listed


def contested_warning(result: SolveResult) -> str | None:
    """One line when nodes rest on one measurement that others contradict
    (:attr:`SolveResult.node_contested`; else None), naming the first few."""
    count = result.num_contested_nodes
    if not count:
        return None
    return (f"{count} node(s) rest on one measurement that others contradict, so their "
            f"rotations could not be checked: "
            f"{listed_ids(result.contested_ids(), MAX_CONTESTED_LISTED)}")


def parallel_warning(result: SolveResult) -> str | None:
    """One line when node pairs measured with rotations that disagree could not be settled
    (:attr:`SolveResult.num_parallel_undecided`; else None)."""
    if not result.num_parallel_undecided:
        return None
    return (f"{result.num_parallel_undecided} node pair(s) measured with rotations that "
            "disagree could not be settled against the solution: their merged edge, a "
            "median between the measurements, stands")


def components_warning(result: SolveResult) -> str | None:
    """One line when the solution has several connected components (else None): how many,
    their sizes, and that each is only defined up to its own gauge."""
    count = len(result.anchors)
    if count <= 1:
        return None
    sizes = sorted(np.bincount(np.asarray(result.component), minlength=count).tolist(),
                   reverse=True)
    listed = ", ".join(str(n) for n in sizes[:MAX_SIZES_LISTED])
    if count > MAX_SIZES_LISTED:
        listed += f", ... {count - MAX_SIZES_LISTED} more"
    return (f"the graph has {count} connected components (sizes {listed} nodes); each "
            "component's rotations are defined only up to its own gauge (its anchor node gets "
            "identity), so rotations from different components cannot be compared")
