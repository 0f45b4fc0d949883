"""Filtered-DMF rotation averager: edge filter, DMF per candidate depth, projection.

One estimator, one options struct (:class:`~rotavg_ros.core.options.SolverOptions`).
Input is a :class:`~rotavg_ros.core.view_graph.ViewGraph` (or plain arrays through
:func:`average_rotations`). Conventions: ``R_i`` world-to-node, edges ``R_ij ~= R_i R_j^T``;
the output gives every connected component its own gauge, with its anchor at identity.
"""

from __future__ import annotations

import math
import time
from collections.abc import Hashable, Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from rotavg_ros.core.chordal_init import chordal_rotations, reused_relaxations
from rotavg_ros.core.depth_choice import choose_depth
from rotavg_ros.core.dmf.sparse import shows_outliers
from rotavg_ros.core.filter.edge_filter import filter_edges
from rotavg_ros.core.node_sequence import node_sequence
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.result import SolveResult
from rotavg_ros.core.robust.class_noise import class_noise
from rotavg_ros.core.robust.contested_nodes import contested_nodes
from rotavg_ros.core.robust.gauss_newton import (
    refine_least_squares,
    remembered_cg_failures,
    shared_elimination_order,
)
from rotavg_ros.core.robust.l1_choice import (
    CAUCHY,
    LEAST_SQUARES,
    EstimatorVerdict,
    choose_by_cross_validation,
    fold_plan,
)
from rotavg_ros.core.robust.noise import NOISE_AXES, noise_axes, redundancy
from rotavg_ros.core.robust.odometry_bias import estimate_odometry_bias, remove_odometry_bias
from rotavg_ros.core.robust.parallel_measurements import ParallelVerdict, settle_parallel
from rotavg_ros.core.robust.verify import (
    GNC_SIGMAS,
    RobustSolve,
    VerifyOutcome,
    chain_tree,
    choose,
    connects_all,
    odometry_edges,
    robust_resolve,
    truncated_l1,
    truncated_squares,
    verify,
)
from rotavg_ros.core.so3 import chordal_distance, geodesic_distance, project_to_so3
from rotavg_ros.core.threads import verify_workers
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray
from rotavg_ros.core.view_graph import EdgeArrays, RepeatPolicy, ViewGraph, consolidate


@dataclass
class ComponentSolution:
    """Rotations of one connected component in local indexing (local node 0 = identity;
    :func:`average_rotations` then turns the component to its anchor)."""

    rotations: FloatArray
    kept: BoolArray
    """Edges the final solution keeps as inliers (after the filter and the verification)."""
    depth: int
    cost_by_depth: dict[int, float]
    iterations_by_depth: dict[int, int]
    filter_kept: BoolArray
    """Edges the spanning-tree filter kept (all True without the filter)."""
    noise_sigma_deg: float = math.nan
    """Per-axis noise of a unit-weight edge estimated by the verification (NaN: not run)."""
    verification: str = ""
    """Which solution the verification kept: ``dmf``, ``robust``, ``dmf_refit``, ``failed``
    or empty (not run); see :attr:`SolveResult.verification`."""
    untested: int = 0
    """Loop closures (edges off a spanning tree) that no check could test."""
    relocalized: int = 0
    """Node moves of the verification's relocalization (kept solution)."""
    trusted: int = 0
    """Odometry edges the verification trusted as inliers."""
    pruned_depths: tuple[int, ...] = ()
    """Depth candidates the candidate race stopped early (never chosen)."""
    runs_left_out: int = 0
    """Runs of loop closures the verification's re-solve left out as wholes."""
    distrusted: int = 0
    """Odometry edges the verification stopped trusting and left out: the loop closures
    across them disagreed (:mod:`.robust.odometry_breaks`)."""
    odometry_weight: float = 1.0
    """Weight of the odometry edges relative to the loop closures that the solution was
    fitted with, estimated from the data (option ``class_noise``); 1 where not used."""
    odometry_bias_deg: float = 0.0
    """The odometry's bias (degrees a step) removed before the solve (option
    ``odometry_bias``); 0 where none was."""
    inlier_threshold: float = math.inf
    """The verification's inlier threshold on standardized residuals (radians of a
    unit-weight edge; inf: not run)."""
    unchecked: int = 0
    """Odometry edges kept against one run of loop closures that nothing else checks
    (:attr:`.robust.verify.VerifyOutcome.unchecked`)."""
    contested: BoolArray | None = None
    """Per node: its rotation rests on one kept edge that edges left out contradict
    (:func:`.robust.contested_nodes.contested_nodes`); None: not judged."""


@dataclass
class _FirstFit:
    """The first fit of one component (:meth:`RotationAverager._first_fit`), which the
    verification judges. Local indices; node 0 = identity where a DMF was fitted (the
    re-solve's rotations, where it is the answer, are anchored after the verification)."""

    rotations: FloatArray
    depth: int
    costs: dict[int, float]
    iterations: dict[int, int]
    pruned: tuple[int, ...]
    filter_kept: BoolArray
    """Edges the spanning-tree filter kept (all True without the filter)."""
    dmf_kept: BoolArray
    """Edges the kept solution was fitted on: the filter's, or the re-solve's inliers the
    DMF fit's own filter kept (the re-solve's inliers where no DMF was fitted)."""
    untested: int
    """Loop closures that no check of the filter could test."""
    starts: dict[str, FloatArray]
    """The verification's starts besides the odometry chain (the filter's tree)."""
    sparse: bool
    robust: RobustSolve | None = None
    """The robust re-solve run before the DMF fit (sparse mode), or None."""
    resolve_why: str = ""
    """Why the re-solve is the answer and no DMF was fitted ("" where one was)."""

    @property
    def resolve_only(self) -> bool:
        """The re-solve is the answer: no DMF fit."""
        return bool(self.resolve_why)


READMITTED_SHARE = 0.05
"""Sparse mode: a kept DMF solution is fitted again on its inliers where the edges re-admitted
by the verification are more than this share of the edges it was fitted on (option
``refit_readmitted``). Fewer move a least-squares-like fit by little against the refit's cost
(parking-garage + 20% false closures re-admits 1%, 56 edges; at 5 deg per edge the filter
removes and the verification re-admits 17-21%, at 20 deg over 200%)."""

DENSE_UNFITTED_SHARE = 0.25
"""Dense mode: a kept DMF solution is fitted again on its inliers where more than this share
of them were not in its fit (the filter removed them, the verification re-admitted them;
option ``refit_readmitted``). A fit on fewer than three quarters of its inliers has at least
4/3 the variance of one on all of them. Measured shares with the default reweighting (seeds
0-2): Ellis Island 4%, its variants with 15% and 30% random edges 8% and 19-26% (seeds 3-5
of the latter under 25%); a refit there at 18.8% raised the median by 3% (the re-admitted
real edges are worse than the kept ones), at 25.5% lowered it by 0.5%. The other dense-mode
cases of the regime suite and the stress variants 0-15%, one 65%; dense graphs without
false edges at 5 deg folded noise 32-44% (one 100-node draw under 25%), where the refit
lowered the median by 18-32%. Was 1/2, then 1/3; the margin is narrow on both sides (see
docs/method.md, step 7)."""

REFIT_TOLERANCE = 0.02
"""A sparse-mode DMF solution fitted again without the outliers its own residuals show is
kept unless its choice cost is more than this (relative) above the first fit's: a sign the
refit failed, not a difference between two fits of the same inliers."""


class RotationAverager:
    """The paper's pipeline: filter -> DMF at each candidate depth -> pick -> project."""

    def __init__(self, options: SolverOptions | None = None) -> None:
        self.options = options or SolverOptions()
        self.options.validate()

    @property
    def _trusts_odometry(self) -> bool:
        """Whether the solve may trust odometry, which the node sequence tells."""
        verify = self.options.verify
        return verify.enabled and verify.odometry != "none"

    # ------------------------------------------------------------------ public
    def solve(
        self,
        graph: ViewGraph,
        anchor: Hashable | None = None,
        initial: Mapping[Any, FloatArray] | None = None,
        initial_depth: int | None = None,
    ) -> SolveResult:
        """Solve every connected component of ``graph``.

        ``anchor`` (a node id; default: the first node added) gets identity; each other
        component is anchored at its first-added node. Component label 0 is the anchor's.
        The odometry (``verify.odometry``) joins nodes consecutive in the graph's sequence
        (:func:`~.node_sequence.node_sequence`: the ids' natural order or the order the
        nodes were added, whichever chains more nodes, else the graph's own paths).

        ``initial`` (node id -> world-to-node rotation, any gauge), e.g. the previous
        solution of a growing graph, warm-starts the solve: known nodes start there, new
        ones from the spanning tree, and dense mode runs ``warm_iterations`` at
        ``warm_lr`` for the single depth ``initial_depth`` (the previous choice).
        """
        edges = graph.edge_arrays()
        ids = graph.node_ids
        anchor_idx = graph.index_of(anchor) if anchor is not None and graph.has_node(
            anchor) else 0
        init = None
        if initial:
            init = np.full((graph.num_nodes, 3, 3), np.nan)
            for k, node_id in enumerate(ids):
                if node_id in initial:
                    init[k] = initial[node_id]
        result = self._solve_edges(graph, edges, anchor_idx, init, initial_depth)
        if not (self.options.verify.enabled and self.options.verify.settle_parallel
                and graph.repeat_policy is RepeatPolicy.MERGE
                and graph.num_measurements > edges.num_edges):
            return result
        return self._settle_parallel(graph, edges, result, anchor_idx, init, initial_depth)

    def _settle_parallel(
        self, graph: ViewGraph, edges: EdgeArrays, result: SolveResult, anchor_idx: int,
        init: FloatArray | None, initial_depth: int | None,
    ) -> SolveResult:
        """:meth:`solve`'s answer ``result`` (of the merged ``edges``) with the graph's pairs
        measured more than once whose measurements disagree settled against it, and solved
        again where that changes the edges (:mod:`.robust.parallel_measurements`)."""
        mi, mj, mR, mw = graph.measurement_arrays()

        def judged(keep: BoolArray, edges: EdgeArrays, result: SolveResult,
                   ) -> ParallelVerdict | None:
            return settle_parallel(graph.num_nodes, mi[keep], mj[keep], mR[keep], mw[keep],
                                   edges.i, edges.j, edges.R, edges.weight,
                                   result.edge_inlier, result.rotations,
                                   math.radians(result.noise_sigma_deg))

        def solved(keep: BoolArray) -> tuple[EdgeArrays, SolveResult]:
            edges = consolidate(mi[keep], mj[keep], mR[keep], mw[keep], RepeatPolicy.MERGE)
            return edges, self._solve_edges(graph, edges, anchor_idx, init, initial_depth)

        first = judged(np.ones(mi.size, bool), edges, result)
        if first is None:
            return result
        keep, undecided = first.keep, first.undecided
        if first.withhold.any():
            # Undecided pairs: their merged edge may have bent the solution, or pushed the
            # closures across it out. Solved without them, then judged again.
            held = first.withhold
            edges, result = solved(keep & ~held)
            again = judged(held, edges, result)
            if again is not None:
                keep = keep.copy()
                keep[held] = again.keep
                undecided += again.undecided - int(np.unique(
                    mi[held] * graph.num_nodes + mj[held]).size)
        if not keep.all() or first.withhold.any():
            self._say(f"parallel measurements: {int((~keep).sum())} set aside (their pair's "
                      "other measurements agree with the solution); solving again")
            edges, result = solved(keep)
        return replace(result, num_parallel_set_aside=int((~keep).sum()),
                       num_parallel_undecided=undecided)

    def _solve_edges(
        self, graph: ViewGraph, edges: EdgeArrays, anchor_idx: int,
        init: FloatArray | None, initial_depth: int | None,
    ) -> SolveResult:
        """:meth:`solve` on ``edges``, the graph's edges (one per pair, as
        :meth:`~.view_graph.ViewGraph.edge_arrays` orders them)."""
        ids = graph.node_ids
        out = average_rotations(
            graph.num_nodes, edges.i, edges.j, edges.R, edges.weight, self.options,
            anchor=anchor_idx, initial=init, initial_depth=initial_depth,
            sequence=node_sequence(ids, edges.i, edges.j) if self._trusts_odometry else None,
        )
        residuals = _residuals_deg(out.rotations, edges.i, edges.j, edges.R)
        return SolveResult(
            node_ids=ids,
            rotations=out.rotations,
            component=out.component,
            anchors=[ids[a] for a in out.component_anchor],
            depth=out.depth,
            residuals_deg=residuals,
            edge_inlier=out.kept,
            num_filtered=int((~out.filter_kept).sum()),
            num_rejected_verify=int((out.filter_kept & ~out.kept).sum()),
            num_readmitted=int((~out.filter_kept & out.kept).sum()),
            noise_sigma_deg=out.noise_sigma_deg,
            verification=out.verification,
            num_untested=out.untested,
            num_relocalized=out.relocalized,
            num_runs_left_out=out.runs_left_out,
            num_trusted_odometry=out.trusted,
            num_distrusted_odometry=out.distrusted,
            num_unchecked_odometry=out.unchecked,
            cost_by_depth=out.cost_by_depth,
            duration_s=out.duration_s,
            iterations_by_depth=out.iterations_by_depth,
            pruned_depths=out.pruned_depths,
            odometry_weight=out.odometry_weight,
            odometry_bias_deg_per_step=out.odometry_bias_deg,
            node_contested=(np.zeros(graph.num_nodes, bool) if out.contested is None
                            else out.contested),
        )

    def solve_component(
        self, n: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
        initial: FloatArray | None = None, initial_depth: int | None = None,
    ) -> ComponentSolution:
        """Solve one connected graph in local indices; node 0 gets identity.

        ``initial`` (n, 3, 3) world-to-node rotations with NaN rows for unknown nodes.
        Where the weights do not tell the odometry from the loop closures (the same median
        weight in both: every edge at weight 1, or pairs measured twice merged at weight 2),
        the graph has odometry and the solution's inliers show the two classes' noise
        differ beyond doubt (option ``class_noise``), it is solved again with the odometry's
        weights multiplied by their ratio. The verification's noise model has one axis where
        every measurement turns about one common axis (a planar problem,
        :func:`~.robust.noise.noise_axes`) and the graph is no odometry chain with sparse
        loop closures (the redundancy of all its edges, false closures included, at least
        ``least_squares_below_redundancy``), else three.
        On such a chain the three-axis model's tighter reading of heading noise keeps fewer
        false closures, and a true closure lost costs little there: on a planar chain of
        1,000 keyframes with 40% false closures 10-180 deg off (16 draws) the one-axis model
        kept more false closures on 11 and had the higher mean error on 12, the lower on
        none (docs/benchmarks.md, "Planar robots: a one-axis noise model").
        """
        planar = (noise_axes(R) == 1 and redundancy(n, np.ones(i.size, bool))
                  >= self.options.verify.least_squares_below_redundancy)
        token = NOISE_AXES.set(1 if planar else 3)
        try:
            # (the same edges relaxed twice: solved once; CG's failure on one of the
            # graph's Laplacians remembered for the whole solve; one fill-reducing order
            # of its nodes for every sparse factorization of the solve)
            with (reused_relaxations(), remembered_cg_failures(n),
                  shared_elimination_order(n, i, j)):
                sol = self._solve_component(n, i, j, R, w, initial, initial_depth)
        finally:
            NOISE_AXES.reset(token)
        # (kept odometry is trusted: no contest where it alone joins a block)
        trusted = odometry_edges(n, i, j, self.options.verify.odometry) & sol.kept
        return replace(sol, contested=contested_nodes(n, i, j, sol.kept, trusted))

    def _solve_component(
        self, n: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
        initial: FloatArray | None, initial_depth: int | None,
    ) -> ComponentSolution:
        """:meth:`solve_component` within its noise model's axes."""
        opt = self.options
        odometry = odometry_edges(n, i, j, opt.verify.odometry)
        bias = None
        # Only on an odometry chain with sparse loop closures (the redundancy of all its
        # edges below ``least_squares_below_redundancy``): there the odometry carries the
        # solution between closures far apart, and a bias breaks the loop tests. A pose
        # graph dense with closures absorbs a bias in its many short loops (at the oracle's
        # median up to 1 deg a step), and its loops confound the estimate (sphere2500 at
        # 0.5 and 1 deg a step: 1.9-3.3 deg a step estimated, passed, and 14-25 deg error).
        if (opt.verify.enabled and opt.verify.odometry_bias and odometry.any()
                and redundancy(n, np.ones(i.size, bool))
                < opt.verify.least_squares_below_redundancy):
            bias = estimate_odometry_bias(n, i, j, R, w, odometry)
        sol = self._solve_once(n, i, j, R, w, odometry, initial, initial_depth)
        removed = 0.0
        if bias is not None and bias.applied:
            unbiased = remove_odometry_bias(i, j, R, odometry, bias.beta)
            with_bias = self._solve_once(n, i, j, unbiased, w, odometry, initial, initial_depth)
            if self._explains_more(with_bias, unbiased, sol, R, i, j, w):
                self._say(f"odometry bias {bias.degrees_per_step:.3f} deg a step removed "
                          f"(the loops read {math.degrees(bias.scale_before):.2f} deg per "
                          f"axis with it, {math.degrees(bias.scale_after):.2f} without)")
                sol, R, removed = with_bias, unbiased, bias.degrees_per_step
            else:
                self._say(f"odometry bias {bias.degrees_per_step:.3f} deg a step estimated "
                          "but not removed: the solve without it explains the data better "
                          "(a wrong odometry step, not a bias)")
        sol = replace(sol, odometry_bias_deg=removed)
        if not (opt.verify.enabled and opt.verify.class_noise and sol.verification
                and sol.verification != "failed" and i.size):
            return sol
        if not (odometry.any() and (~odometry).any()
                and np.median(w[odometry]) == np.median(w[~odometry])):
            return sol  # no odometry, or weights that tell the two apart: trusted as given
        if redundancy(n, sol.kept) < opt.verify.least_squares_below_redundancy:
            return sol  # chain-like: a few units of redundancy, closures that may be false
        scales = class_noise(sol.rotations, i, j, R, w / np.mean(w), sol.kept, odometry,
                             cut=sol.inlier_threshold, seed=opt.runtime.seed)
        if scales is None or not scales.significant:
            return sol
        self._say(f"noise per edge class: odometry {1.0 / math.sqrt(scales.factor):.2f} x the "
                  f"loop closures' (at equal weights {scales.z:.1f} standard errors apart); "
                  f"solving again with the odometry weighted {scales.factor:.3g} x")
        again = self._solve_once(n, i, j, R, w * np.where(odometry, scales.factor, 1.0),
                                 odometry, initial, initial_depth)
        return replace(again, odometry_weight=scales.factor, odometry_bias_deg=removed)

    def _explains_more(self, unbiased: ComponentSolution, unbiased_R: FloatArray,
                       raw: ComponentSolution, raw_R: FloatArray, i: IntArray, j: IntArray,
                       w: FloatArray) -> bool:
        """Whether the solve with the odometry's bias removed (``unbiased``, of the
        measurements ``unbiased_R``) explains its data at least as well as the solve
        without (``raw``, of ``raw_R``) explains the raw data: truncated squares at ``GNC_SIGMAS``
        times the lower of the two noise scales (at most the initial threshold), every
        edge capped. A wrong odometry step can pass for a bias where the closures' loops
        are all about as long (a route driven twice: a 0.45 deg a step bias estimated on an
        unbiased route with one wrong step, 46.4 deg median error with it removed against
        4.2 deg without, the oracle's); the bias's correction then bends the odometry that
        the raw solve fits once it has left the wrong step out. Noise scales not finite:
        the bias stands, as the estimate's own test said."""
        sigmas = [s for s in (unbiased.noise_sigma_deg, raw.noise_sigma_deg) if math.isfinite(s)]
        if not sigmas:
            return True
        c = min(GNC_SIGMAS * math.radians(min(sigmas)),
                math.radians(self.options.verify.initial_threshold_deg))
        weights = w / np.mean(w)
        return (truncated_squares(unbiased.rotations, i, j, unbiased_R, weights, c)
                <= truncated_squares(raw.rotations, i, j, raw_R, weights, c))

    def _solve_once(
        self, n: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
        odometry: BoolArray, initial: FloatArray | None = None,
        initial_depth: int | None = None,
    ) -> ComponentSolution:
        """:meth:`solve_component` at the weights ``w`` as given; ``odometry`` marks the
        edges trusted as odometry (:func:`~.robust.verify.odometry_edges`).

        The stages, in order: the first fit (:meth:`_first_fit`: the filter, then in sparse
        mode the robust re-solve where the chordal solution shows outliers, and the DMF);
        the verification (:meth:`_verify`); a DMF refit where the verification's inliers
        call for one (:meth:`_refit_after_verify`), or, in sparse mode, least squares'
        optimum of them where the cross-validation keeps a spanning tree in its folds (its
        fit replaces any refit; ``refit_where_folds_replace`` off);
        the estimator on the inliers by cross-validation
        (:meth:`_estimator_by_cross_validation`); the anchor back at identity."""
        opt = self.options
        w = w / np.mean(w)
        first = self._first_fit(n, i, j, R, w, odometry, initial, initial_depth)
        if not opt.verify.enabled or i.size < 3:
            return ComponentSolution(first.rotations, first.filter_kept, first.depth, first.costs,
                                     first.iterations, first.filter_kept, untested=first.untested,
                                     pruned_depths=first.pruned)
        out = self._verify(n, i, j, R, w, odometry, first)
        if out is None:
            return ComponentSolution(first.rotations, first.filter_kept, first.depth, first.costs,
                                     first.iterations, first.filter_kept, verification="failed",
                                     untested=first.untested, pruned_depths=first.pruned)
        # The edges the kept solution explains: the re-solve's inliers, or those the noise
        # model fitted to the DMF solution's own residuals calls inliers.
        inlier = out.classified
        tree = (self._cross_validation_tree(n, i, j, w, inlier) if first.sparse else None)
        # The cross-validation that keeps a spanning tree in its folds puts least squares'
        # optimum or Huber's fit of the inliers in place of the kept solution either way:
        # no DMF refit for it to replace, least squares in its place.
        replaced_by_fold_fit = (tree is not None and not opt.verify.refit_where_folds_replace
                                and _folds_keep_tree(n, i[inlier], j[inlier],
                                                     opt.runtime.seed, tree))
        if replaced_by_fold_fit:
            final = refine_least_squares(out.rotations, i[inlier], j[inlier], R[inlier],
                                         w[inlier], iterations=20)
        else:
            final = self._refit_after_verify(n, i, j, R, w, first, out, initial is None)
        refitted = final is not out.rotations and not replaced_by_fold_fit
        estimator = ""
        if tree is not None:
            final, estimator = self._estimator_by_cross_validation(
                final, i, j, R, w, inlier, tree, odometry)
        if (out.chosen == "robust" or refitted or estimator or out.relocalized
                or replaced_by_fold_fit):
            # (the anchor may have moved)
            final = project_to_so3(np.einsum("nab,cb->nac", final, final[0]))  # node 0 = I
            final[0] = np.eye(3)
        trusted = int(out.known.sum())
        self._say(f"verification: kept the {out.chosen} solution"
                  f"{' (DMF refit)' if refitted else ''}"
                  f"{f' (no DMF fit: {first.resolve_why})' if first.resolve_only else ''}"
                  f"{' (least squares restarted from the relaxation)' if out.restarted else ''}"
                  ", noise "
                  f"{out.noise.sigma_deg:.2f} deg per axis, {int((~inlier).sum())} "
                  f"edges outside, {trusted} odometry edges trusted, {out.relocalized} nodes "
                  f"relocalized, {out.runs_left_out} runs of loop closures left out"
                  f"{f', {out.distrusted} odometry edges left out' if out.distrusted else ''}")
        kept_solution = "dmf_refit" if out.chosen == "robust" and refitted else out.chosen
        if estimator:
            kept_solution += f"+{estimator}"
        return ComponentSolution(final, inlier, first.depth, first.costs, first.iterations,
                                 first.filter_kept, out.noise.sigma_deg, kept_solution,
                                 out.untested, out.relocalized, trusted, first.pruned,
                                 runs_left_out=out.runs_left_out,
                                 distrusted=out.distrusted,
                                 inlier_threshold=out.noise.threshold,
                                 unchecked=out.unchecked)

    def _first_fit(
        self, n: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
        odometry: BoolArray, initial: FloatArray | None, initial_depth: int | None,
    ) -> _FirstFit:
        """The solution the verification judges: the edge filter, then in sparse mode
        (cold, verification on) the robust re-solve of every edge where the chordal
        solution of the filter's edges shows outliers (:meth:`_robust_first`), and the DMF
        on its inliers, or no DMF where least squares answers (:meth:`_least_squares_answers`)
        or the cross-validation's fit will replace it; otherwise the order of the paper, the
        DMF on the filter's edges (warm-started from ``initial`` where enough nodes are
        known)."""
        opt = self.options
        tree_rot: FloatArray | None = None
        untested = max(i.size - (n - 1), 0)  # without a filter nothing is tested
        triangles = 0
        if opt.filter.use_filter:
            filt = filter_edges(i, j, R, w, n, opt.filter.sigma, opt.filter.use_support_count,
                                opt.filter.sigma_untested)
            kept = filt.kept
            tree_rot = filt.tree_rotations
            untested = int(np.sum(~(filt.tested | filt.path_tested | filt.in_tree)))
            triangles = filt.num_triangles
            self._say(f"filter: {filt.num_triangles} triangles, removed "
                      f"{filt.num_removed}/{i.size} edges")
        else:
            kept = np.ones(i.size, bool)
        fi, fj, fR, fw = i[kept], j[kept], R[kept], w[kept]
        sparse = self.is_sparse(n, fi.size)
        self._say(f"{'sparse' if sparse else 'dense'} mode: {n} nodes, {fi.size} edges")
        starts = {} if tree_rot is None else {"tree": tree_rot}  # the filter's tree
        chordal: FloatArray | None = None  # sparse mode's start, when computed here
        if (sparse and initial is None and opt.verify.enabled and opt.verify.robust_first
                and opt.dense.explicit_constraint and i.size >= 3):
            chordal = chordal_rotations(n, fi, fj, fR, fw)
            # Where the filter found no triangle its tree tested nothing: one more arbitrary
            # spanning tree, which drifts as the chain does. The chordal solution starts the
            # re-solve in its place (see _robust_first).
            robust = self._robust_first(n, (i, j, R, w), kept, chordal,
                                        starts if triangles else {"chordal": chordal},
                                        odometry)
            if robust is not None and connects_all(n, i, j, robust.inlier):
                resolve_why = self._least_squares_answers(n, robust)
                if (not resolve_why and not opt.verify.dmf_where_folds_replace
                        and self._folds_replace(n, i, j, w, robust.inlier)):
                    resolve_why = "the cross-validation's fit replaces it"
                if resolve_why:  # the re-solve is the answer, no DMF fit
                    return _FirstFit(robust.rotations, 0, {}, {}, (), kept, robust.inlier,
                                     untested, starts, sparse, robust, resolve_why)
                from_resolve = self._refit_from_resolve(robust.gaussian)
                fit = self._fit_inliers(n, i, j, R, w, robust.inlier,
                                        robust.rotations if from_resolve else None,
                                        unfiltered=from_resolve)
                if fit is not None:
                    dmf_kept = robust.inlier.copy()
                    dmf_kept[robust.inlier] = fit.filter_kept
                    return _FirstFit(fit.rotations, fit.depth, fit.cost_by_depth,
                                     fit.iterations_by_depth, fit.pruned_depths, kept,
                                     dmf_kept, untested, starts, sparse, robust)
        # The order of the paper: fit, then verify (also where the inliers split).
        H0 = None
        if initial is not None and opt.dense.explicit_constraint:
            known = np.all(np.isfinite(initial.reshape(n, 9)), axis=1)
            if known.mean() >= opt.warm.min_known:
                if tree_rot is None:
                    tree_rot = chordal_rotations(n, fi, fj, fR, fw)
                H0 = warm_start_rotations(initial, known, tree_rot, fi, fj, fR,
                                          opt.filter.sigma)
                self._say(f"warm start: {int(known.sum())}/{n} nodes known")
        choice = choose_depth(opt, n, fi, fj, fR, fw, sparse, H0, initial_depth, chordal)
        return _FirstFit(choice.rotations, choice.depth, choice.costs, choice.iterations,
                         choice.pruned, kept, kept, untested, starts, sparse)

    def _verify(
        self, n: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
        odometry: BoolArray, first: _FirstFit,
    ) -> VerifyOutcome | None:
        """The verification of the first fit: after a robust re-solve, the choice between it
        and the DMF fit on its inliers, if one was fitted (:func:`~.robust.verify.choose`);
        else the whole verification of the DMF solution (:func:`~.robust.verify.verify`).
        None (and said) where it failed numerically: the first fit then stands, marked
        ``failed``."""
        opt = self.options
        max_threshold = math.radians(opt.verify.max_threshold_deg)
        try:
            chain_like = self._least_squares_below()
            if first.robust is not None:
                return choose(n, i, j, R, w, first.robust,
                              None if first.resolve_only else first.rotations,
                              first.dmf_kept, max_threshold, least_squares_below=chain_like)
            return verify(n, i, j, R, w, first.rotations, first.filter_kept, first.starts,
                          known_inlier=odometry,
                          initial_threshold=math.radians(opt.verify.initial_threshold_deg),
                          max_threshold=max_threshold, rounds=opt.verify.rounds,
                          least_squares_below=chain_like,
                          workers=verify_workers(i.size, opt.runtime.threads),
                          chain_below=opt.verify.least_squares_below_redundancy)
        except (np.linalg.LinAlgError, FloatingPointError, RuntimeError) as exc:
            self._say(f"verification failed ({type(exc).__name__}: {exc}); keeping the DMF "
                      "solution")
            return None

    def _refit_after_verify(
        self, n: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
        first: _FirstFit, out: VerifyOutcome, no_initial: bool,
    ) -> FloatArray:
        """The verified solution, or the DMF fitted again on its inliers where they call
        for it (:meth:`_refit_dmf`, which keeps ``out.rotations``, the same object, where the
        refit loses). ``no_initial``: the solve was given no initial rotations."""
        opt = self.options
        inlier = out.classified
        if out.chosen == "robust":
            if (first.robust is None and not self._least_squares_stands(out, first.filter_kept)
                    and redundancy(n, out.inlier) >= self._least_squares_below()):
                # (else the DMF on these inliers has just lost, or the re-solve's residuals
                # or its inliers' redundancy said least squares)
                # In either mode from the re-solve, unfiltered, unless its residuals look
                # Gaussian (the filter would drop the true edges of a high-noise graph again).
                from_resolve = self._refit_from_resolve(out.resolve_gaussian)
                # A cold, filtered refit on every edge repeats the first fit exactly.
                repeat = no_initial and not from_resolve and bool(np.all(out.inlier))
                return self._refit_dmf(n, i, j, R, w, out.inlier, out.rotations, out.cap,
                                       warm=from_resolve, unfiltered=from_resolve,
                                       fitted=first.rotations if repeat else None)
            return out.rotations
        # Edges judged by the kept DMF solution that were not in its fit (the filter removed
        # them, the verification re-admitted them).
        unfitted = int(np.count_nonzero(inlier & ~first.dmf_kept))
        if first.sparse:
            readmitted = bool(opt.verify.refit_readmitted and unfitted
                              > READMITTED_SHARE * np.count_nonzero(first.dmf_kept))
            if np.any(out.inlier & ~inlier) or readmitted:
                # Sparse mode's Huber fit gives gross outliers an L1 say; where its own
                # residuals show some, fit it again without them, and keep that unless it
                # failed (its cost clearly higher: on the same edges the costs of the two
                # fits differ by about 0.01%). The dense fit's reweighting already gives
                # them almost no say: there a refit changed little (Ellis Island: 2.209 /
                # 0.393 -> 2.249 / 0.386 deg) and cost a whole fit. Likewise where its
                # residuals call many edges inliers that were not in its fit (more than
                # READMITTED_SHARE of those it was fitted on): the kept solution is then a
                # fit of a part of its inliers only, and the refit, a fit of all of them,
                # replaces it whatever the cost (two fits of different edges: clean
                # parking-garage at 5 deg, 1,027 re-admitted, the refit's cost 2.4% higher
                # for 6.90 deg median against 9.10).
                return self._refit_dmf(n, i, j, R, w, inlier, out.rotations, out.cap,
                                       tolerance=math.inf if readmitted else REFIT_TOLERANCE,
                                       warm=True, unfiltered=opt.verify.refit_from_resolve)
        elif (opt.verify.refit_readmitted
              and unfitted > DENSE_UNFITTED_SHARE * np.count_nonzero(inlier)):
            # Many of the edges the kept DMF solution is judged by were not in its fit: fit
            # it again on them, briefly, from where it stands.
            return self._refit_dmf(n, i, j, R, w, inlier, out.rotations, out.cap,
                                   warm=True, unfiltered=True)
        return out.rotations

    def _estimator_by_cross_validation(
        self, rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
        inlier: BoolArray, tree: BoolArray, odometry: BoolArray,
    ) -> tuple[FloatArray, str]:
        """Least squares, L1, Huber or Cauchy on the ``inlier`` edges, chosen by cross-validation
        (:func:`~.robust.l1_choice.choose_by_cross_validation`, ``tree`` kept in every
        fold where the folds would split the graph): ``(rotations, the estimator whose fit
        replaced rot, "ls", "l1", "huber" or "cauchy", with "-halfway" where the answer is the
        midpoint of that fit and least squares' on a tie; "" where rot stands)``."""
        opt = self.options
        verdict = choose_by_cross_validation(
            rot, i[inlier], j[inlier], R[inlier], w[inlier], seed=opt.runtime.seed,
            tree=tree, l1_from_fold=NOISE_AXES.get() == 1,
            workers=verify_workers(i.size, opt.runtime.threads),
            robust_l1_stands=not (opt.verify.l1_over_robust_with_odometry
                                  and bool(odometry.any())),
            huber_for_l1=opt.verify.huber_where_weights_differ and _weights_differ(w[inlier]),
            heavy_tails=opt.verify.cauchy_where_decided,
            halfway_where_tied=opt.verify.halfway_where_tied)
        swapped = verdict.replaced and verdict.fitted != verdict.estimator
        robust_fate = ("; the kept robust fit stands"
                       if verdict.robust_given and not verdict.replaced
                       else "; Huber's fit replaces the robust fit"
                       if swapped and verdict.robust_given
                       else "; Huber's fit in the L1 fit's place (the weights differ)"
                       if swapped else "")
        self._say("cross-validation: no verdict (the inliers do not join every node)"
                  if np.isnan(verdict.held_out_change)
                  else f"cross-validation: {verdict.estimator}"
                  f" (held-out change {verdict.held_out_change:+.3f}, "
                  f"{verdict.folds_run} folds"
                  f"{', a spanning tree in every fold' if verdict.tree_kept else ''}"
                  f"{robust_fate}"
                  f"{_halfway_said(verdict)}"
                  f"{_heavier_tails_said(verdict)})")
        if not verdict.replaced:  # the kept solution stands as it is
            return rot, ""
        # The alternative's fit (or halfway to it on a tie), or least squares' optimum in
        # a robust fit's place.
        if verdict.fitted == LEAST_SQUARES:
            return verdict.rotations, "ls"
        return verdict.rotations, (f"{verdict.fitted}-halfway" if verdict.halfway
                                   else verdict.fitted)

    def _robust_first(
        self, n: int, edges: tuple[IntArray, IntArray, FloatArray, FloatArray],
        kept: BoolArray, chordal: FloatArray, starts: dict[str, FloatArray],
        odometry: BoolArray,
    ) -> RobustSolve | None:
        """Sparse mode: the verification's robust re-solve of every edge
        (:func:`~.robust.verify.robust_resolve`), when ``chordal``, the chordal solution of
        the filter's ``kept`` edges, shows outliers; else None. A failed re-solve is said
        and gives None too (the solve then goes on as without). ``starts`` are the
        re-solve's starts besides the odometry chain: the filter's tree, or, where the
        filter found no triangle, ``chordal`` in its place. There an untested tree drifts
        like the chain, and where heavy noise, not false edges, made the chordal solution
        show outliers, GNC from those two can end in another least-squares basin (a planar
        sphere2500 at 20 deg of heading noise, no triangle: 45.7 deg mean from them, 15.9
        from the chordal solution; the least-squares optimum 12.5). Where the filter tested
        triangles its tree stays: a chordal start there as well (measured) cost one more
        GNC run, moved the regime suite's errors by under 1%, and at held-out seed 5 led
        parking-garage at 20 deg per edge from 26.5 to 30.6 deg median."""
        i, j, R, w = edges
        opt = self.options
        if not shows_outliers(chordal, i[kept], j[kept], R[kept], w[kept],
                              opt.sparse.outlier_factor):
            return None
        try:
            robust = robust_resolve(
                n, i, j, R, w, starts, odometry,
                initial_threshold=math.radians(opt.verify.initial_threshold_deg),
                max_threshold=math.radians(opt.verify.max_threshold_deg),
                rounds=opt.verify.rounds, workers=verify_workers(i.size, opt.runtime.threads),
                chain_below=opt.verify.least_squares_below_redundancy)
        except (np.linalg.LinAlgError, FloatingPointError, RuntimeError) as exc:
            self._say(f"robust re-solve failed ({type(exc).__name__}: {exc}); fitting every "
                      "edge the filter kept")
            return None
        self._say(f"robust first: the chordal solution shows outliers; the re-solve leaves "
                  f"{int((~robust.inlier).sum())} edges outside")
        return robust

    def _least_squares_answers(self, n: int, robust: RobustSolve) -> str:
        """Robust first: why the re-solve (least squares on its inliers) is the answer and no
        DMF is fitted on them (``VerifyOptions.least_squares_where_gaussian``), or "" where
        the DMF fit runs. Least squares is the better estimator where the re-solve's
        standardized inlier residuals look Gaussian (:attr:`RobustSolve.gaussian`), and where the
        inliers' redundancy (:func:`redundancy`) is below
        ``VerifyOptions.least_squares_below_redundancy``: an L1 fit gains on noise peaked at
        zero only where most edges are redundant, and on a chain it puts each loop's
        misclosure on a few edges instead of spreading it along the loop."""
        if not self.options.verify.least_squares_where_gaussian:
            return ""
        if robust.gaussian:
            return "its residuals look Gaussian"
        spare = redundancy(n, robust.inlier)
        return f"redundancy {spare:.2f}" if spare < self._least_squares_below() else ""

    def _cross_validation_tree(self, n: int, i: IntArray, j: IntArray, w: FloatArray,
                               inlier: BoolArray) -> BoolArray | None:
        """Sparse mode: the spanning tree of the ``inlier`` edges that the cross-validation
        (``VerifyOptions.l1_by_cross_validation``) keeps where its folds would split them,
        or None where it does not run."""
        opt = self.options.verify
        if not (opt.l1_by_cross_validation and n <= opt.l1_max_nodes
                and redundancy(n, inlier) >= self._least_squares_below()):
            return None
        return chain_tree(n, i[inlier], j[inlier], w[inlier])

    def _folds_replace(self, n: int, i: IntArray, j: IntArray, w: FloatArray,
                       inlier: BoolArray) -> bool:
        """Whether the cross-validation of the ``inlier`` edges keeps a spanning tree in
        its folds and reaches a verdict: its fit then replaces any robust fit."""
        tree = self._cross_validation_tree(n, i, j, w, inlier)
        return tree is not None and _folds_keep_tree(n, i[inlier], j[inlier],
                                                     self.options.runtime.seed, tree)

    def _least_squares_stands(self, out: VerifyOutcome, filtered: BoolArray) -> bool:
        """Fit first, then verify: whether the kept re-solve stands without the DMF refit on
        its inliers (``VerifyOptions.least_squares_where_gaussian``). Where its residuals look
        Gaussian (``out.resolve_gaussian``) the refit is cold and filtered; where the filter
        had removed edges the re-solve keeps (``filtered``: the edges the filter kept), that
        refit fits only part of the data least squares fitted whole, and its L1 fit would
        still win the L1 cost it is judged by: least squares, the better estimator on
        Gaussian residuals, stands (parking-garage at 5 deg of Gaussian noise three times
        larger about one axis, 1,215 edges filtered: the refit replaced the re-solve's
        6.20 / 5.06 deg mean / median with 12.66 / 11.84). Where the filter removed none of
        them, the refit fits them all (real/smallGrid3D: 0.048 deg median against least
        squares' 0.070; its reference weighs chordal distances, as the DMF's loss does)."""
        return (self.options.verify.least_squares_where_gaussian and out.resolve_gaussian
                and bool(np.any(out.inlier & ~filtered)))

    def _least_squares_below(self) -> float:
        """The redundancy below which least squares is the answer (0: never, by it)."""
        opt = self.options.verify
        return opt.least_squares_below_redundancy if opt.least_squares_where_gaussian else 0.0

    def _refit_from_resolve(self, resolve_gaussian: bool) -> bool:
        """Whether the DMF fits on the re-solve's inliers skip the filter and start from it
        (``VerifyOptions.refit_from_resolve``). Not where the re-solve's standardized
        inlier residuals look Gaussian (``resolve_gaussian``, :attr:`RobustSolve.gaussian`):
        there least squares is the better estimator, and an L1 fit started from it always
        lowers the choice's L1 cost, so it would replace it."""
        return self.options.verify.refit_from_resolve and not resolve_gaussian

    def _fit_inliers(self, n: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
                     keep: BoolArray, initial: FloatArray | None = None,
                     unfiltered: bool = False) -> ComponentSolution | None:
        """The DMF (no verification) on the edges ``keep``, from its own start or warm-started
        from ``initial``; None if those edges do not connect every node. ``unfiltered``: no
        edge filter first (the verification has judged these edges already)."""
        if not connects_all(n, i, j, keep):
            return None
        plain = RotationAverager(self.options.replace_flat(
            verify=False, use_filter=self.options.filter.use_filter and not unfiltered))
        return plain.solve_component(n, i[keep], j[keep], R[keep], w[keep], initial=initial)

    def _refit_dmf(self, n: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
                   keep: BoolArray, current: FloatArray, cap: float, tolerance: float = 0.0,
                   warm: bool = False, unfiltered: bool = False,
                   fitted: FloatArray | None = None) -> FloatArray:
        """The DMF again, on the edges ``keep`` (see :meth:`_fit_inliers`); ``current`` itself
        (the same object) if those do not connect every node or the refit's cost (the
        choice's, every edge capped at ``cap``) is more than ``tolerance`` (relative) above
        ``current``'s.

        After a robust re-solve: the least-squares re-solve found the inliers; the DMF's
        entry-wise L1 fit with reweighting is the more accurate estimator on them where it
        converges, and the cost test keeps the re-solve where it does not. ``warm``: the
        refit continues from ``current`` (the re-solve, or a kept DMF solution fitted again
        without the outliers it shows) instead of a new start. ``fitted``: the refit's
        result, already known (a cold, filtered refit on every edge repeats the first fit).
        """
        if fitted is not None:
            refit = fitted
        else:
            fit = self._fit_inliers(n, i, j, R, w, keep, current if warm else None, unfiltered)
            if fit is None:  # the inliers do not connect every node
                return current
            refit = fit.rotations
        # Judged by the same cap, every edge capped: on the same inliers, the question is
        # only which estimator fits the data better, not which edges to trust.
        if (truncated_l1(refit, i, j, R, w, cap)
                <= (1.0 + tolerance) * truncated_l1(current, i, j, R, w, cap)):
            self._say(f"verification: the DMF refit on {int(keep.sum())} inliers replaces "
                      "the solution")
            return refit
        return current

    def is_sparse(self, num_nodes: int, num_edges: int) -> bool:
        """Whether the sparse-graph variant is used for this component."""
        mode = self.options.mode
        if mode not in ("auto", "dense", "sparse"):
            raise ValueError(f"mode must be auto, dense or sparse, got {mode!r}")
        if mode == "auto":
            return 2.0 * num_edges / max(num_nodes, 1) < self.options.sparse.mean_degree
        return mode == "sparse"

    def _say(self, text: str) -> None:
        if self.options.runtime.progress is not None:
            self.options.runtime.progress(text)


def _halfway_said(verdict: EstimatorVerdict) -> str:
    """The tie's words for the progress line ("" where the folds did not tie)."""
    if not verdict.halfway:
        return ""
    return (f"; a tie (t {verdict.held_out_t:+.2f}): halfway between its fit and least "
            "squares")


def _heavier_tails_said(verdict: EstimatorVerdict) -> str:
    """The second cross-validation's figures for the progress line ("" where it did not
    run)."""
    if not verdict.heavier_folds:
        return ""
    decided = ("Cauchy's fit replaces it" if verdict.estimator == CAUCHY
               else "Cauchy's not decided lower")
    return (f"; against Cauchy {verdict.heavier_change:+.3f} over "
            f"{verdict.heavier_folds} folds: {decided}")


def warm_start_rotations(
    initial: FloatArray, known: BoolArray, tree: FloatArray,
    i: IntArray, j: IntArray, R: FloatArray, sigma: float,
) -> FloatArray:
    """Known nodes keep ``initial`` unless their edges side with the tree; the others get
    ``tree`` moved into the initial's gauge.

    Both are world-to-node, so the gauge acts on the right: ``initial_i ~= tree_i Q`` with
    ``Q = proj(sum_known tree_i^T initial_i)``. A previous solution can hold a node that was
    wrong when it had few edges (a short warm fit cannot turn it round); so a known node
    takes ``tree_i Q`` instead when more of its edges ``(i, j, R_ij)`` agree with it
    (``d_chord(R_ij, R_i R_j^T) <= sigma``, the other end at its start value) than with
    ``initial_i``; the gauge Q is then fitted again without the replaced nodes.
    """
    Q = project_to_so3(np.einsum("kba,kbc->ac", tree[known], initial[known]))
    alt = tree @ Q
    out = alt.copy()
    out[known] = initial[known]
    if i.size == 0:
        return out
    n = out.shape[0]

    def agreeing(Ri: FloatArray, Rj: FloatArray) -> FloatArray:
        return (chordal_distance(R, np.einsum("eab,ecb->eac", Ri, Rj)) <= sigma).astype(float)

    current = agreeing(out[i], out[j])
    support_now = np.bincount(i, current, n) + np.bincount(j, current, n)
    support_alt = (np.bincount(i, agreeing(alt[i], out[j]), n)
                   + np.bincount(j, agreeing(out[i], alt[j]), n))
    keep = known & ~(support_alt > support_now)
    if keep.any() and not keep.all():  # the gauge again, without the replaced nodes
        Q = project_to_so3(np.einsum("kba,kbc->ac", tree[keep], initial[keep]))
        out[~keep] = (tree @ Q)[~keep]
    return out


@dataclass
class ArraySolution:
    """What :func:`average_rotations` returns, in the graph's node indexing."""

    rotations: FloatArray
    """(N, 3, 3) world-to-node rotations; each component's anchor gets identity."""
    component: IntArray
    """(N,) component label of each node (0 = the anchor's, then by decreasing size)."""
    component_anchor: list[int]
    """Anchor node of each component, by label."""
    depth: int
    """Depth chosen for the largest component (0 if no DMF was fitted, see
    :attr:`SolveResult.depth`)."""
    kept: BoolArray
    """(E,) whether each edge is an inlier of the final solution."""
    cost_by_depth: dict[int, float]
    """Eq. 3 cost of each depth candidate (largest component)."""
    duration_s: float
    iterations_by_depth: dict[int, int]
    """Iterations each depth's fit ran (largest component)."""
    filter_kept: BoolArray
    """(E,) whether each edge passed the spanning-tree filter."""
    noise_sigma_deg: float = math.nan
    """Noise per axis estimated by the verification (largest component; NaN: not run)."""
    verification: str = ""
    """Solution the verification kept for the largest component (see
    :attr:`SolveResult.verification`)."""
    untested: int = 0
    """Loop closures no check could test, over all components."""
    relocalized: int = 0
    """Nodes the verification relocalized, over all components."""
    trusted: int = 0
    """Odometry edges the verification trusted, over all components."""
    pruned_depths: tuple[int, ...] = ()
    """Depth candidates the candidate race stopped early (largest component)."""
    runs_left_out: int = 0
    """Runs of loop closures the verification left out as wholes, over all components."""
    distrusted: int = 0
    """Odometry edges the verification stopped trusting and left out, over all components."""
    odometry_weight: float = 1.0
    """Weight of the odometry relative to the loop closures estimated from the data (largest
    component; option ``class_noise``); 1 where not used."""
    odometry_bias_deg: float = 0.0
    """The odometry's bias removed before the solve, degrees a step (largest component;
    option ``odometry_bias``); 0 where none was."""
    unchecked: int = 0
    """Odometry edges kept against one run of loop closures that nothing else checks, over
    all components."""
    contested: BoolArray | None = None
    """(N,) whether each node's rotation rests on one kept edge that edges left out
    contradict (:attr:`ComponentSolution.contested`, every component)."""


def average_rotations(
    num_nodes: int,
    i: IntArray,
    j: IntArray,
    R: FloatArray,
    weight: FloatArray,
    options: SolverOptions | None = None,
    anchor: int = 0,
    initial: FloatArray | None = None,
    initial_depth: int | None = None,
    sequence: IntArray | None = None,
) -> ArraySolution:
    """Array interface: solve each component; see :meth:`RotationAverager.solve`.

    ``sequence`` (N,): each node's position along the trajectory
    (:func:`~.node_sequence.node_sequence`; default: index order). Each component is solved
    with its nodes in that order, so that the odometry joins consecutive local indices, and
    its edges sorted by their local ends (else in the order given); then turned so that its
    anchor (``anchor``, or its first node by index) is identity."""
    t0 = time.perf_counter()
    averager = RotationAverager(options)
    i = np.asarray(i, np.int64)
    j = np.asarray(j, np.int64)
    if i.size and (np.any(i == j) or min(i.min(), j.min()) < 0
                   or max(i.max(), j.max()) >= num_nodes):
        raise ValueError("edge indices must be distinct and in [0, num_nodes)")
    labels = _component_labels(num_nodes, i, j, anchor)
    rotations = np.tile(np.eye(3), (num_nodes, 1, 1))
    kept = np.ones(i.size, bool)
    filter_kept = np.ones(i.size, bool)
    comp_anchor: list[int] = []
    depth, costs, iterations, best_size = 0, {}, {}, 0
    pruned: tuple[int, ...] = ()
    noise, verification, untested, relocalized, trusted = math.nan, "", 0, 0, 0
    runs_left_out, distrusted, odometry_weight, odometry_bias = 0, 0, 1.0, 0.0
    unchecked = 0
    contested = np.zeros(num_nodes, bool)
    for label in range(int(labels.max()) + 1 if num_nodes else 0):
        nodes = np.flatnonzero(labels == label)
        comp_anchor.append(anchor if label == 0 and anchor in nodes else int(nodes[0]))
        if nodes.size < 2:
            continue
        if sequence is not None:
            nodes = nodes[np.argsort(sequence[nodes], kind="stable")]
        local = np.full(num_nodes, -1, np.int64)
        local[nodes] = np.arange(nodes.size)
        sel = np.flatnonzero(labels[i] == label)
        li, lj = local[i[sel]], local[j[sel]]
        if sequence is not None:  # edges in local (i, j) order: the solve then depends on
            # the graph and its sequence, not on the order the input named the nodes in
            # (but for pairs measured twice, which keep the order given)
            by_pair = np.lexsort((np.maximum(li, lj), np.minimum(li, lj)))
            sel, li, lj = sel[by_pair], li[by_pair], lj[by_pair]
        lR = R[sel]
        swap = li > lj
        li, lj = np.where(swap, lj, li), np.where(swap, li, lj)
        lR = np.where(swap[:, None, None], lR.transpose(0, 2, 1), lR)
        sol = averager.solve_component(
            nodes.size, li, lj, lR, weight[sel],
            None if initial is None else initial[nodes], initial_depth)
        rotations[nodes] = _anchored(sol.rotations, int(np.flatnonzero(
            nodes == comp_anchor[-1])[0]))
        kept[sel] = sol.kept
        filter_kept[sel] = sol.filter_kept
        untested += sol.untested
        relocalized += sol.relocalized
        runs_left_out += sol.runs_left_out
        distrusted += sol.distrusted
        unchecked += sol.unchecked
        trusted += sol.trusted
        if sol.contested is not None:
            contested[nodes] = sol.contested
        if nodes.size > best_size:
            depth, costs, best_size = sol.depth, sol.cost_by_depth, nodes.size
            iterations, pruned = sol.iterations_by_depth, sol.pruned_depths
            noise, verification = sol.noise_sigma_deg, sol.verification
            odometry_weight = sol.odometry_weight
            odometry_bias = sol.odometry_bias_deg
    return ArraySolution(rotations, labels, comp_anchor, depth, kept, costs,
                         time.perf_counter() - t0, iterations, filter_kept, noise,
                         verification, untested, relocalized, trusted, pruned, runs_left_out,
                         distrusted, odometry_weight, odometry_bias, unchecked, contested)


def _folds_keep_tree(n: int, i: IntArray, j: IntArray, seed: int, tree: BoolArray) -> bool:
    """Whether the cross-validation of these inlier edges keeps the spanning ``tree`` in
    every fold and reaches a verdict (:func:`~.robust.l1_choice.fold_plan`)."""
    plan = fold_plan(n, i, j, seed=seed, tree=tree)
    return plan.tree_kept and not plan.split


def _weights_differ(w: FloatArray) -> bool:
    """Whether the edges' weights are not all equal (beyond rounding): the input's
    information weights tell each edge's noise scale."""
    return bool(w.size) and float(np.max(w)) > (1.0 + 1e-9) * float(np.min(w))


def _anchored(rotations: FloatArray, anchor: int) -> FloatArray:
    """World-to-node ``rotations`` in the gauge where node ``anchor`` is identity
    (``R_i R_a^T``; the edges' ``R_i R_j^T`` are the same in every gauge)."""
    if anchor == 0:  # (solve_component's own gauge)
        return rotations
    turned = project_to_so3(np.einsum("nab,cb->nac", rotations, rotations[anchor]))
    turned[anchor] = np.eye(3)
    return turned


def _component_labels(num_nodes: int, i: IntArray, j: IntArray, anchor: int) -> IntArray:
    """Labels with the anchor's component 0, then by decreasing size."""
    if num_nodes == 0:
        return np.zeros(0, np.int64)
    adj = coo_matrix((np.ones(i.size), (i, j)), shape=(num_nodes, num_nodes))
    _, raw = connected_components(adj, directed=False)
    sizes = np.bincount(raw)
    order = sorted(range(sizes.size), key=lambda c: (c != raw[anchor], -sizes[c], c))
    relabel = np.empty(sizes.size, np.int64)
    relabel[order] = np.arange(sizes.size)
    return relabel[raw]


def _residuals_deg(rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray) -> FloatArray:
    if i.size == 0:
        return np.zeros(0)
    pred = np.einsum("eab,ecb->eac", rot[i], rot[j])
    return np.degrees(geodesic_distance(R, pred))
