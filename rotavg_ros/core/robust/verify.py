"""Verification after the solve: a robust re-solve on every input edge, and the choice
between it and the filtered-DMF solution by a consensus cost over every input edge.

Why: the paper's filter judges edges against one spanning tree with a fixed threshold. On
high-noise graphs it removes the loop closures, when the tree takes an outlier it condemns
the subtree's correcting edges, and on chains (no triangles) it tests nothing. This stage
takes the solution, not the tree, as the reference, and lets the data set the threshold:

1. **Robust re-solves.** GNC-TLS (:mod:`.gnc`) over every edge, at ``initial_threshold``,
   from each start point: the DMF solution, the odometry chain's rotations (a spanning tree
   that takes consecutive node indices first; only where there is odometry or no other
   start; where the odometry is in pieces, also its pieces joined by the closures that
   agree, :mod:`.odometry_start`) and any the caller adds (the solver adds the filter's
   spanning tree), then least squares on its inliers. The re-solve whose residuals
   are most likely under an inlier/outlier mixture fitted to them is kept.
2. **Noise.** Every residual is standardized by its own predicted spread (leverage for edges
   in the fit, prediction variance for the others; :func:`standardized_residuals`); the
   mixture fitted to the standardized residuals (:mod:`.noise`) gives the noise scale and,
   per edge, whether it is more likely an inlier or an outlier.
3. **Re-admit and drop.** Up to ``rounds`` times: re-classify every edge so, and re-solve by
   geodesic least squares on the inliers.
4. **GNC at the data's threshold.** Where there is odometry and step 3 found outliers,
   and always on an odometry chain with sparse loop closures (redundancy below
   ``chain_below``, where false closures can bend step 3's fit until it shows none):
   GNC-TLS again at ``GNC_SIGMAS`` noise scales (at most the initial threshold)
   from step 3's solution and from the odometry chain, the odometry edges
   (``known_inlier``) trusted from here on (known inliers, uncapped in the choice cost);
   where those disagree, always on such a chain and where the loop closures are few
   (``PAIRWISE_ALWAYS_UP_TO``), also from the best of the starts on
   pairwise-consistent closure sets (:func:`consistent_starts`,
   :mod:`.closure_consistency`); step 3 on the result of the lowest truncated squares
   (:func:`truncated_squares`, the GNC's objective). Where such a start fits its own edges
   at a noise scale below ``RESCALE_BELOW`` of step 3's, or, on an odometry chain whose
   odometry does not turn about one axis, the closures' loops over the odometry show one
   below every such start's (an upper bound of their scale,
   :func:`~.closure_consistency.loop_noise_scale`: no fit enters it), false closures bent
   step 3's fit and inflated its scale: the pass runs again at the lower scale, every
   candidate costed there. At the loops' scale the GNC's inliers then stand as they are
   (step 3's re-admission would excuse closures a few degrees wrong by the prediction
   variance of the long odometry between them). Then runs of loop closures that pull
   the fit all one way (:mod:`.closure_runs`) are left out where that lowers the choice
   cost (:func:`_leave_runs_out`). Where odometry steps are suspect of a break (the
   closures across them rejected and the step a jump, or a fit leaves the step far off:
   :mod:`.odometry_breaks`), the pass runs again with the suspects as ordinary edges,
   from the odometry's pieces joined where the most closures agree, and that fit stands
   where its truncated squares, with ``BREAK_PENALTY`` caps for each suspect it leaves out
   that is only a misfit (no jump pointed at or rare), are the lower
   (:func:`_breaks_explain_more`); a cut that no closure tells from a kept jump's moves onto
   the jump first (:func:`~.odometry_breaks.cuts_onto_jumps`). Where jumps are common (a
   car's turns), a trusted jump whose cut unbends the fit by more than that penalty is cut
   (:mod:`.bent_routes`; up to ``BENT_CUTS``): least squares bends a long route around a
   wrong step until nothing points at it.
5. **Relocalize.** Nodes the re-solve left far off move to where their own edges agree
   (:mod:`.relocalize`); if that lowers the choice cost, step 3 runs again from there. A
   block of nodes that one wrong edge or one run of closures alone holds turns where its
   rejected edges to the rest agree, where that lowers the truncated squares, each run of
   closures one piece of evidence (:func:`turn_blocks`, :mod:`.relocalize_blocks`). The
   DMF solution's far-off nodes move the same way. Last, on a sparse graph, least squares
   on the re-solve's inliers from their chordal relaxation replaces the re-solve where it
   fits them better (:func:`least_squares_from_relaxation`: a least-squares local
   minimum).
6. **Choice.** The truncated L1 cost over all input edges decides between the re-solve and
   the DMF solution, which is kept unless the re-solve is clearly (``margin``) better: a
   filter that condemned a subtree, or false closures the DMF bent to fit, lose; a DMF
   solution that explains the data keeps its accuracy. (The solver then fits the DMF again
   on the re-solve's inliers: ``RotationAverager._refit_dmf``.)

:func:`verify` runs all six steps after the DMF fit. In sparse mode, when the chordal
solution already shows outliers, the solver runs steps 1-5 first (:func:`robust_resolve`,
without the DMF start), fits the DMF on the re-solve's inliers only, and step 6
(:func:`choose`) judges that fit.

Conventions: world-to-node ``R_i``, ``R_ij ~= R_i R_j^T``, node 0 fixed (anchor).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Concatenate, ParamSpec, TypeVar

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree

from rotavg_ros.core.chordal_init import chordal_rotations
from rotavg_ros.core.filter.edge_filter import tree_rotations
from rotavg_ros.core.robust.bent_routes import cut_bent_jump
from rotavg_ros.core.robust.closure_consistency import (
    closure_loops,
    consistent_closures,
    loop_noise_scale_and_bound,
    neighbour_supported,
)
from rotavg_ros.core.robust.closure_runs import (
    closure_runs,
    independent_pieces,
    remembered_run_leverages,
    suspect_runs,
)
from rotavg_ros.core.robust.gauss_newton import (
    ITERATIVE_MIN_DEGREE,
    WELL_CONNECTED,
    edge_residuals,
    prediction_variance,
    refine_least_squares,
    remembered_cg_failures,
    residual_angles,
    shared_elimination_order,
    shared_probe_draws,
)
from rotavg_ros.core.robust.gnc import gnc_tls
from rotavg_ros.core.robust.noise import (
    NoiseModel,
    fit_noise,
    is_inlier,
    log_likelihood,
    looks_gaussian,
    noise_axes,
    redundancy,
)
from rotavg_ros.core.robust.odometry_breaks import (
    OdometrySuspects,
    common_jumps,
    cuts_onto_jumps,
    hanging_steps,
    left_out_jumps,
    outsized_steps,
    rare_jumps,
    steps_spanned,
    suspect_odometry,
)
from rotavg_ros.core.robust.odometry_start import odometry_start
from rotavg_ros.core.robust.relocalize import relocalize_nodes
from rotavg_ros.core.robust.relocalize_blocks import MAX_TURNS, BlockTurn, block_turns
from rotavg_ros.core.threads import map_in_threads
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray

CHOICE_SIGMAS = 3.0
"""Cap of an edge's say in the choice, in fitted noise scales (the 97th percentile of an
inlier's residual angle is 3.0 sigma; on a planar problem, one noise axis, the 99.7th)."""

GNC_SIGMAS = 4.0
"""Threshold of the second GNC-TLS pass, in fitted noise scales (an inlier's residual angle
exceeds 4.0 sigma with probability about 0.1%; on a planar problem 0.006%)."""

TIGHT_START_MU = 1.0 / GNC_SIGMAS ** 2
"""The surrogate at which the second pass's GNC from the first pass's solution starts (at
least): the TLS weights there are 1 up to about one noise scale and fall as ``1 / r``
beyond, a Huber-like loss. From its own robust solution a GNC needs no flatter start: from
the default start (``mu`` down to 1e-6 at a threshold of a few noise scales) its first ten
or so stages only walked the solution through near-L1 fits back to where it began. On the
regime benchmark's 30 sparse cases with false edges of seeds 0 and 3: the same errors to
the third decimal, 7-31% fewer Gauss-Newton steps in the re-solve. The pass from the
odometry chain keeps the flat start: the chain's drift is what it must escape."""

MIN_SUPPORTED_SHARE = 0.5
"""The share of the loop closures their neighbours must support for the supported start
(:func:`supported_closures_start`) to be tried: where closures come in runs (a route
revisited keyframe after keyframe: the Manhattan world at 5 deg + 20% false, 75%), the
start is the graph without its random false closures; where most have no neighbour
(revisits far apart: the grid walks, 22-32%), it drops most true closures too and is one
more start drifting along the odometry, whose GNC ended in another basin as often for
the worse. A run may hold at most this share of the supported closures."""

BREAK_PENALTY = 3.0
"""Odometry suspects of a break (:mod:`.odometry_breaks`) become ordinary edges only where
the fit without trusting them has truncated squares lower, by this many caps for each
suspect it leaves out that is only a misfit, no jump pointed at or rare (besides that
edge's own cap), than the fit that trusted them: cutting such a step must free several
closures (see :func:`_breaks_explain_more`)."""

BREAK_TEST_ROUNDS = 3
"""Rounds of the break test (step 4): after a break, the test runs again from the fit that
cut it, while it finds more (parking-garage with three wrong steps: the first round cut
two, the closures across the third, 129 of them, pointed at it only then)."""

HANGING_RETRIES = 2
"""Times a break's untrusting pass runs again with the steps that nodes hang by trusted
(:func:`_hanging_cuts`) before the break is given up."""

LATER_ROUND_MARGIN = 1.0
"""Caps a later round of the break test must gain beyond the test's own terms: one edge
explained more, not cuts moved between jumps that no closure tells apart at the same
truncated squares (stress draw 97's parking-garage: two true turns cut for one, 1.49 deg
mean -> 9.06)."""

BENT_CUT_PENALTY = 1.0
"""Caps a jump's cut must lower the truncated squares by, beyond the jump's own, before
:func:`~.bent_routes.cut_bent_jump` makes it. Where no break is, a cut frees three
parameters, and the squares fall by ``sigma^2 chi2_3``: above 16.3 ``sigma^2`` with
probability 0.1%, one cap at ``GNC_SIGMAS`` (a planar problem's ``chi2_1``, 10.8
``sigma^2``, makes it stricter there). ``BREAK_PENALTY``'s three caps, used here before,
let the bend stand where the cut explained the data by one to three caps (the lost-track
car route of ``regime_stress``, 234 draws: means above 1.5x the oracle's 63 -> 48; those
routes without the wrong step, 186 draws: no cut made)."""

BENT_CUTS = 2
"""Jumps cut, one after the other, where a route bent around them
(:func:`~.bent_routes.cut_bent_jump`): a lost track rarely breaks more than twice."""

MORE_TURN_ROUNDS = 6
"""Rounds of further block turns once one stood (:func:`turn_blocks` ``together``): each
round turns, together, the blocks that the round's proposals turn apart from one
another."""

MORE_TURNS = 200
"""Block turns proposed in each of those rounds. A front end that lost its track often
leaves many blocks (gtsam's City10000 with the second of its 200 ambiguous odometry
measurements: 200 wrong steps, 114 nodes far off after the first turn)."""

MIN_NOISE_RESIDUALS = 5
"""Fewest informative standardized residuals (:func:`standardized_residuals`) a noise
model is fitted to. In the break test (:func:`_breaks_explain_more`) a fit's scale counts
only where this many of its inliers are informative: a fit that trusts a wrong odometry step
and rejects the true closures across it keeps a near-tree, whose few remaining loops give a
scale from two or three residuals (a 50-keyframe chain: 0.34 deg against the 0.99 deg of
the fit without the step, whose cap then counted every closure of the right fit a misfit)."""

PAIRWISE_ALWAYS_UP_TO = 200
"""The tight pass runs its pairwise closure test whatever its starts say on a graph with at
most this many loop closures (edges not odometry): the test's cost grows with their
square, and on so few it is a small part of the solve. A chain with many closures for its
length reads as no chain (a 50-keyframe chain, 8 true closures and 3 of a false group left:
redundancy 0.18, above ``chain_below``), and there the GNC's starts can all end in the same
bent fit. On graphs with thousands of closures (parking-garage, 4,600) the test ran only
where the starts disagree: always running it cost 0.5-1.1 s on clean SLAM graphs for the
same accuracy."""

LOCAL_FIT_ROUNDS = 10
"""Least-squares fits of :func:`_local_fit` at most (on 72 short chains with wrong steps the
edges within the threshold settled after one fit on 56, two on 14, three on 2)."""

RESCALE_BELOW = 0.75
"""The tight pass runs again at the noise scale of a pairwise-consistent start's own fit,
or on a chain at the one the closures' loops over the odometry show, when that is below
this fraction of step 3's (see :func:`robust_resolve`)."""

CONSISTENCY_SCALES = (1.0, 0.5, 0.25)
"""The pairwise closure test of the tight pass runs at the fitted noise scale times each of
these, and at the closures' loops' own scale where that is lower still (see
:func:`consistent_starts`)."""

RUN_ROUNDS = 3
"""The tight pass judges runs of closures (:mod:`.closure_runs`) up to this many times: each
time every suspect run, the most suspect first, is left out where that lowers the choice
cost, and the runs are judged again on the new fit if any was."""

ODOMETRY_COVERAGE = 0.9
"""``odometry="auto"``: consecutive edges are odometry when they join at least this fraction
of the consecutive node pairs."""
ODOMETRY_MAX_DENSITY = 0.5
"""``odometry="auto"``: ... and the graph joins at most this share of all node pairs. A
graph that joins a share ``p`` of its pairs at random joins about ``p`` of the consecutive
ones: a near-complete view graph chains its ids by accident (Ellis Island with 30% more
random edges joins every pair), where a trajectory, however often revisited, joins a few
percent (the Manhattan world's 10,000 poses at mean degree 12.9: 0.13%; a drone survey's
720 images at mean degree 21: 3%)."""

P = ParamSpec("P")
T = TypeVar("T")

RESTART_MARGIN = 1e-6
""":func:`least_squares_from_relaxation` replaces a least-squares solution only when it fits
its edges better by more than this (relative): two fits of the same minimum differ by far
less, and keep the solution as it was."""
EXACT_LEVERAGE_EDGES = 100
"""At most this many high-leverage edges off the chain tree (loop closures) get their
prediction variance solved exactly (one Laplacian solve each)."""


@dataclass(frozen=True)
class VerifyOutcome:
    """Result of :func:`verify`: rotations and the edges the chosen solution keeps."""

    rotations: FloatArray
    inlier: BoolArray
    """Edges the kept solution rests on: the filter's for ``dmf``, the re-solve's inliers
    for ``robust``."""
    noise: NoiseModel
    chosen: str
    """``"dmf"`` (the filtered-DMF solution stands) or ``"robust"`` (the re-solve)."""
    costs: dict[str, float]
    start: str
    untested: int
    """Loop closures (edges off the chain tree) whose residual nothing could check: their
    leverage under the kept solution's fit is 1 (no other path constrains them)."""
    cap: float
    """Cap of an edge's say in the choice's truncated L1 cost (``costs``), radians."""
    relocalized: int
    """Node moves of :func:`~.relocalize.relocalize_nodes` in the kept re-solve, plus the
    nodes on the smaller side of a block turn (:func:`turn_blocks`)."""
    known: BoolArray
    """The trusted (odometry) edges: known inliers of the re-solve, uncapped in ``costs``."""
    classified: BoolArray
    """Edges the noise model fitted to the kept solution's own residuals classifies as
    inliers (with the trusted ones): for ``dmf``, the filter's edges minus those the DMF
    solution itself shows to be outliers."""
    restarted: bool = False
    """The kept re-solve came from :func:`least_squares_from_relaxation` (False for ``dmf``)."""
    runs_left_out: int = 0
    """Runs of loop closures the re-solve left out as wholes (:mod:`.closure_runs`), whichever
    solution is kept."""
    resolve_gaussian: bool = False
    """The re-solve's residuals look Gaussian (:attr:`RobustSolve.gaussian`)."""
    distrusted: int = 0
    """Odometry edges the re-solve stopped trusting (:attr:`RobustSolve.distrusted`) that
    the kept solution leaves out."""
    unchecked: int = 0
    """Odometry edges kept against one run of loop closures that nothing else checks
    (:attr:`RobustSolve.unchecked`) that the kept solution keeps."""


def few_closures(trusted: BoolArray) -> bool:
    """Whether the loop closures (the edges not ``trusted`` as odometry) are at most
    ``PAIRWISE_ALWAYS_UP_TO``: the tight pass and its pairwise test then always run."""
    return int(np.count_nonzero(~trusted)) <= PAIRWISE_ALWAYS_UP_TO


def chain_tree(num_nodes: int, i: IntArray, j: IntArray, weight: FloatArray) -> BoolArray:
    """A spanning tree that takes consecutive-index edges (an odometry chain) first, then
    the heaviest others. Returns the tree mask over the edges."""
    consecutive = np.abs(i - j) == 1
    # Minimum spanning tree of a cost: consecutive edges 1, others 2 + 1/(1 + weight).
    cost = np.where(consecutive, 1.0, 2.0 + 1.0 / (1.0 + weight))
    mst = minimum_spanning_tree(coo_matrix((cost, (i, j)), shape=(num_nodes,) * 2).tocsr())
    t = mst.tocoo()
    keys = np.minimum(t.row, t.col).astype(np.int64) * num_nodes + np.maximum(t.row, t.col)
    edge_keys = np.minimum(i, j).astype(np.int64) * num_nodes + np.maximum(i, j)
    return np.isin(edge_keys, keys)


def odometry_edges(num_nodes: int, i: IntArray, j: IntArray, rule: str) -> BoolArray:
    """The edges trusted as odometry, by ``rule``: ``consecutive`` (nodes adjacent in the
    node indices, which the solver lays out in the graph's sequence,
    :func:`~rotavg_ros.core.node_sequence.node_sequence`), ``none``, or ``auto``:
    consecutive edges when they chain at least ``ODOMETRY_COVERAGE`` of the nodes and the
    graph joins at most ``ODOMETRY_MAX_DENSITY`` of its node pairs (a trajectory, however
    many loop closures it has; not a near-complete view graph, whose consecutive ids are
    joined by accident). Until 2026-12-07 ``auto`` also asked for a mean degree below
    sparse mode's: the Manhattan world's pose graph (mean degree 12.9) then trusted no
    odometry, and 20 runs of grouped false closures turned blocks of it 55 deg (median;
    1.0 deg, the oracle's, with its odometry trusted)."""
    if rule not in ("auto", "consecutive", "none"):
        raise ValueError(f"odometry must be auto, consecutive or none, got {rule!r}")
    consecutive = np.abs(i - j) == 1
    if rule == "none":
        return np.zeros(i.size, bool)
    if rule == "auto":
        n = max(num_nodes, 2)
        steps = np.unique(np.minimum(i, j)[consecutive]).size
        chained = steps >= ODOMETRY_COVERAGE * (n - 1)
        off = i != j
        joined = np.unique(np.minimum(i, j)[off].astype(np.int64) * n
                           + np.maximum(i, j)[off]).size
        if not chained or joined > ODOMETRY_MAX_DENSITY * n * (n - 1) / 2:
            return np.zeros(i.size, bool)
    return consecutive


def truncated_l1(rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
                 c: float, trusted: BoolArray | None = None) -> float:
    """``sum_e min(sqrt(w_e) r_e, c)``: every edge counts (its residual in units of its own
    noise), none by more than ``c`` (radians of a unit-weight edge), except ``trusted``
    edges (odometry), which count in full."""
    return _capped_sum(residual_angles(rot, i, j, R) * np.sqrt(w), c, trusted)


def truncated_squares(rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray,
                      w: FloatArray, c: float, trusted: BoolArray | None = None) -> float:
    """``sum_e min(w_e r_e^2, c^2)``, ``trusted`` edges uncapped: the truncated
    least-squares objective that GNC-TLS minimizes (at threshold ``c`` for a unit-weight
    edge). The re-solve compares its least-squares fits of different inlier sets by it. Its
    truncated L1 counterpart (:func:`truncated_l1`) favours cutting long loops: a kept
    closure adds about 3 sigma^2 to a fit's squared residuals, however long the loop it
    closes, but adds the loop's whole misclosure, which grows with the loop's length, to the
    sum of the residual angles. A chain left in pieces fits its odometry exactly."""
    return _capped_sum(residual_angles(rot, i, j, R) ** 2 * w, c * c, trusted)


def squares_by_pieces(rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray,
                      w: FloatArray, c: float, trusted: BoolArray, runs: list[IntArray],
                      mean_square: float) -> float:
    """:func:`truncated_squares` with each run of closures (``runs``,
    :func:`~.closure_runs.closure_runs`) one piece of evidence: a run costs its capped
    squares, at most one cap ``c^2`` plus ``mean_square`` (an inlier's expected square) for
    each of its other edges. A run of false closures between the same two stretches is one
    wrong match repeated keyframe after keyframe, so leaving it out costs what leaving out
    one edge costs; a run of true ones, explained, costs its squares as before."""
    squares = np.minimum(residual_angles(rot, i, j, R) ** 2 * w, np.where(trusted, np.inf,
                                                                            c * c))
    in_run = np.zeros(i.size, bool)
    total = 0.0
    for run in runs:
        in_run[run] = True
        total += min(float(squares[run].sum()), c * c + (run.size - 1) * mean_square)
    return total + float(squares[~in_run].sum())


def _capped_sum(values: FloatArray, cap: float, trusted: BoolArray | None) -> float:
    """``sum min(values, cap)``, the ``trusted`` entries uncapped."""
    capped = np.minimum(values, cap)
    return float(np.sum(capped if trusted is None else np.where(trusted, values, capped)))


def standardized_residuals(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray, fit: BoolArray,
    tree: BoolArray | None = None, seed: int = 0,
) -> tuple[FloatArray, FloatArray]:
    """``(t, spread)``: residual angles in units of their own expected spread, and the
    spread of each edge's prediction from the other edges.

    ``rot`` is (close to) the weighted least-squares solution on the edges in ``fit``. An edge
    in the fit has a residual shrunk by its leverage ``h = w q`` (``q`` from
    :func:`~.gauss_newton.prediction_variance`), one outside it is predicted with variance
    ``1 / w + q``; ``t`` is the residual over that standard deviation (unit-weight noise =
    1). Edges of a chain or a tree have leverage near 1: their residual says
    nothing about the noise, and their ``t`` is set to NaN; ``tree`` marks such edges known
    in advance (a spanning tree's), which are not worth an exact leverage.
    """
    r = residual_angles(rot, i, j, R)
    exact = np.zeros(i.size, bool)

    def high_leverage(q_probed: FloatArray) -> BoolArray:
        # The probe estimate of h has a spread of about 0.14 h: where h > 0.5 it is too
        # rough for 1 - h. Solve exactly for up to EXACT_LEVERAGE_EDGES such edges off the
        # tree (loop closures, highest first); the others (tree edges) say nothing about
        # the noise.
        h = w * q_probed
        high = np.flatnonzero(fit & (h > 0.5) & (True if tree is None else ~tree))
        exact[high[np.argsort(-h[high])][:EXACT_LEVERAGE_EDGES]] = True
        return exact

    q = prediction_variance(rot, i, j, w * fit, seed=seed, exact=high_leverage)
    h = w * q
    var = np.where(fit, (1.0 - h) / w, 1.0 / w + q)
    scale = np.sqrt(np.maximum(var, 1e-12))
    # Spread of the edge's prediction from all the other edges: an outlier's error u (a
    # uniform-rotation angle) shows as t = u / spread, in the fit (r = u (1 - h)) or not.
    spread = np.where(fit, 1.0 / np.sqrt(np.maximum(w * (1.0 - h), 1e-12)),
                      np.sqrt(1.0 / w + q))
    undetermined = fit & np.where(exact, h > 1.0 - 1e-3, h > 0.5)
    # An edge outside the fit that joins two pieces of the fit graph (or a node no fitted
    # edge reaches) has no prediction at all: the probes never see that null space.
    pieces = connected_components(coo_matrix(
        (np.ones(int(fit.sum())), (i[fit], j[fit])), shape=(rot.shape[0],) * 2),
        directed=False)[1]
    undetermined |= ~fit & (pieces[i] != pieces[j])
    t = np.where(undetermined, np.nan, r / scale)
    return t, spread


def _fit_and_classify(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray, fit: BoolArray,
    max_threshold: float, tree: BoolArray | None = None,
) -> tuple[NoiseModel, BoolArray, FloatArray]:
    """Noise model of the standardized residuals, the edges within its threshold, and t."""
    t, spread = standardized_residuals(rot, i, j, R, w, fit, tree)
    informative = np.isfinite(t)
    if informative.sum() < MIN_NOISE_RESIDUALS:  # too little to fit a model: nothing changes
        return NoiseModel(math.nan, 1.0, max_threshold), fit.copy(), t
    noise = fit_noise(t[informative], max_threshold=max_threshold, scale=spread[informative])
    # Each edge by its own posterior (the outlier density depends on its scale); edges
    # whose residual says nothing (t NaN) keep their status.
    inlier = fit.copy()
    inlier[informative] = is_inlier(t[informative], noise, spread[informative], max_threshold)
    return noise, inlier, t


def _settle(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    inlier: BoolArray, known: BoolArray, tree: BoolArray, rounds: int, max_threshold: float,
    initial_threshold: float,
) -> tuple[FloatArray, BoolArray, NoiseModel, FloatArray]:
    """Up to ``rounds`` times: re-classify every edge by the noise model fitted to the
    standardized residuals, and re-solve by least squares on the inliers. Returns the
    rotations, inliers, noise model and standardized residuals of the final fit."""
    noise = NoiseModel(initial_threshold / 3.0, 1.0, initial_threshold)
    for _ in range(rounds):
        noise, new_inlier, t = _fit_and_classify(rot, i, j, R, w, inlier, max_threshold,
                                                 tree)
        new_inlier |= known
        if np.array_equal(new_inlier, inlier):
            return rot, inlier, noise, t
        inlier = new_inlier
        rot = refine_least_squares(rot, i, j, R, w * inlier)
    noise, _, t = _fit_and_classify(rot, i, j, R, w, inlier, max_threshold, tree)
    return rot, inlier, noise, t  # the final fit's noise and t; its inliers stay


def _noise_of(rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
              fit: BoolArray, max_threshold: float, tree: BoolArray,
              resting: bool = False) -> float:
    """The noise scale of the least-squares fit ``rot`` of the edges ``fit`` (inf where too
    few of its residuals are informative to fit one; ``resting``: also where fewer than
    ``MIN_NOISE_RESIDUALS`` of the informative ones are in ``fit``, the break test's rule)."""
    noise, _, t = _fit_and_classify(rot, i, j, R, w, fit, max_threshold, tree)
    if resting and np.count_nonzero(np.isfinite(t) & fit) < MIN_NOISE_RESIDUALS:
        return math.inf
    return noise.sigma if math.isfinite(noise.sigma) else math.inf


def _cap(noise: NoiseModel, initial_threshold: float) -> float:
    """Cap of an edge's say in the choice: CHOICE_SIGMAS fitted noise scales."""
    return CHOICE_SIGMAS * noise.sigma if math.isfinite(noise.sigma) else initial_threshold


def log_likelihood_of(rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray,
                      w: FloatArray, max_threshold: float) -> tuple[float, NoiseModel]:
    """Log-likelihood of every edge's residual under the mixture fitted to them."""
    r = residual_angles(rot, i, j, R) * np.sqrt(w)
    model = fit_noise(r, max_threshold=max_threshold)
    return log_likelihood(r, model), model


def robust_from(
    start: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    threshold: float | FloatArray, known: BoolArray | None = None, mu_min: float = 0.0,
) -> tuple[FloatArray, BoolArray]:
    """``(rotations, inliers)``: GNC-TLS at ``threshold`` (radians; one, or one per edge)
    from ``start`` with the ``known`` edges trusted, then least squares on its inliers;
    ``mu_min``: the surrogate the GNC starts at, at least (:func:`~.gnc.gnc_tls`)."""
    g = gnc_tls(start, i, j, R, w, threshold, known, mu_min=mu_min)
    inlier = g.weights > 0 if known is None else (g.weights > 0) | known
    return refine_least_squares(g.rotations, i, j, R, w * inlier), inlier


def robust_solutions(
    i: IntArray, j: IntArray, R: FloatArray, w: FloatArray, starts: dict[str, FloatArray],
    threshold: float, workers: int = 1,
) -> dict[str, tuple[FloatArray, BoolArray]]:
    """``name -> (rotations, inliers)``: :func:`robust_from` each distinct start (a start
    equal to an earlier one is skipped), on up to ``workers`` threads."""
    distinct: dict[str, FloatArray] = {}
    for name, rotations in starts.items():
        if any(np.allclose(rotations, other, atol=1e-9) for other in distinct.values()):
            continue  # the same start twice (a chain's spanning tree is the chain)
        distinct[name] = rotations
    solved = map_in_threads(lambda start: robust_from(start, i, j, R, w, threshold),
                            distinct.values(), workers)
    return dict(zip(distinct, solved, strict=True))


def most_likely(solutions: dict[str, tuple[FloatArray, BoolArray]], i: IntArray,
                j: IntArray, R: FloatArray, w: FloatArray, max_threshold: float) -> str:
    """The name of the solution whose residuals are most likely under the inlier/outlier
    mixture fitted to them."""
    scored = {k: log_likelihood_of(v[0], i, j, R, w, max_threshold)[0]
              for k, v in solutions.items()}
    return max(scored, key=lambda k: scored[k])


def _linear_solves_set_for_the_graph(
    solve: Callable[Concatenate[int, IntArray, IntArray, P], T],
) -> Callable[Concatenate[int, IntArray, IntArray, P], T]:
    """Run ``solve(num_nodes, i, j, ...)`` with the Laplacian solves set up for the input
    graph: :data:`~.gauss_newton.WELL_CONNECTED` set when it has at least
    ``ITERATIVE_MIN_DEGREE`` edges per node (an SfM view graph: every large normal matrix
    is then solved by conjugate gradients first, until CG fails more often than not:
    :func:`~.gauss_newton.remembered_cg_failures`), one shared fill-reducing order of its
    nodes for the sparse factorizations (:func:`~.gauss_newton.shared_elimination_order`),
    the closure runs' leverages kept from fit to fit
    (:func:`~.closure_runs.remembered_run_leverages`), and one normal draw for every fit's
    probes (:func:`~.gauss_newton.shared_probe_draws`)."""

    @functools.wraps(solve)
    def run(num_nodes: int, i: IntArray, j: IntArray, *args: P.args,
            **kwargs: P.kwargs) -> T:
        token = WELL_CONNECTED.set(2.0 * i.size / max(num_nodes, 1) >= ITERATIVE_MIN_DEGREE)
        try:
            with (shared_elimination_order(num_nodes, i, j), remembered_run_leverages(),
                  remembered_cg_failures(num_nodes), shared_probe_draws()):
                return solve(num_nodes, i, j, *args, **kwargs)
        finally:
            WELL_CONNECTED.reset(token)

    return run


@dataclass(frozen=True)
class RobustSolve:
    """Steps 1-5 of the verification: the robust re-solve of every edge."""

    rotations: FloatArray
    inlier: BoolArray
    """The edges the re-solve's final least-squares fit rests on."""
    noise: NoiseModel
    t: FloatArray
    """Standardized residuals of the final fit (NaN: undetermined)."""
    cap: float
    """Cap of an edge's say in the choice cost, radians."""
    known: BoolArray
    """The trusted (odometry) edges (none unless the tight pass ran)."""
    tree: BoolArray
    """The chain tree (:func:`chain_tree`) over the edges."""
    start: str
    """The start whose GNC-TLS re-solve was kept (``dmf``, ``chain``, ``odometry``,
    ``supported`` (:func:`supported_closures_start`), or a caller's)."""
    relocalized: int
    """Node moves of :func:`~.relocalize.relocalize_nodes` in the re-solve, plus the nodes
    on the smaller side of a block turn (:func:`turn_blocks`)."""
    restarted: bool = False
    """Its least squares was restarted from the chordal relaxation of its inliers, which fit
    them better (:func:`least_squares_from_relaxation`)."""
    runs_left_out: int = 0
    """Runs of loop closures the tight pass left out as wholes (:mod:`.closure_runs`)."""
    gaussian: bool = False
    """The final fit's standardized inlier residuals look Gaussian on the axes they span
    (:func:`~.noise.looks_gaussian` with their rotation vectors): least squares is then the
    better estimator."""
    distrusted: BoolArray | None = None
    """Odometry edges no longer trusted: the loop closures across them disagreed with them
    (:mod:`.odometry_breaks`); None: every odometry edge trusted. Those a kept solution
    leaves out are counted as distrusted (:attr:`VerifyOutcome.distrusted`)."""
    unchecked: BoolArray | None = None
    """Odometry edges still trusted that the break test would have cut but that nodes hang
    by against one run of loop closures alone (:func:`_hanging_cuts`), where the fit still
    rejects a closure of that run: kept on the odometry's word, which nothing else checks.
    None: none."""


def verify(
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    dmf_rotations: FloatArray, dmf_kept: BoolArray, starts: dict[str, FloatArray],
    known_inlier: BoolArray | None = None,
    initial_threshold: float = math.radians(30.0),
    max_threshold: float = math.radians(90.0),
    rounds: int = 2,
    margin: float = 0.02,
    least_squares_below: float = 0.0,
    workers: int = 1,
    chain_below: float = 0.0,
) -> VerifyOutcome:
    """Robust re-solve of every edge (:func:`robust_resolve`, the DMF solution one of its
    starts, with ``chain_below``) and the choice against the DMF solution (:func:`choose`,
    with ``margin`` and ``least_squares_below``); see the module docstring.

    ``starts`` are extra start points (name -> rotations) besides the DMF solution and the
    chain tree's rotations. ``workers``: threads for the re-solves from different starts.
    """
    robust = robust_resolve(num_nodes, i, j, R, w, starts, known_inlier, initial_threshold,
                            max_threshold, rounds, dmf_rotations, workers, chain_below)
    return choose(num_nodes, i, j, R, w, robust, dmf_rotations, dmf_kept, max_threshold,
                  margin, least_squares_below)


@_linear_solves_set_for_the_graph
def robust_resolve(
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    starts: dict[str, FloatArray], known_inlier: BoolArray | None = None,
    initial_threshold: float = math.radians(30.0),
    max_threshold: float = math.radians(90.0),
    rounds: int = 2,
    dmf_rotations: FloatArray | None = None,
    workers: int = 1,
    chain_below: float = 0.0,
) -> RobustSolve:
    """Steps 1-5 of the module docstring: the robust re-solve of every edge from the DMF
    solution (if given), the chain tree's rotations (where there is odometry or no other
    start) and ``starts`` (name -> rotations), and the noise scale it shows. The GNC runs
    from different starts take up to ``workers`` threads (the same result). A graph with
    odometry whose step-3 inliers have a redundancy below ``chain_below`` (an odometry chain
    with sparse loop closures) always gets step 4 with the pairwise closure test."""
    odometry = np.zeros(i.size, bool) if known_inlier is None else known_inlier
    known = np.zeros(i.size, bool)  # trusted edges: none until the noise scale is known
    runs_left_out = 0
    distrusted: BoolArray | None = None  # odometry no longer trusted (suspects of a break)
    jumps = np.zeros(i.size, bool)  # of those, the jumps (a lost track's steps)
    # Steps a break would have cut that nodes hang by against one run of closures alone,
    # with those closures: trusted on the odometry's word (:func:`_hanging_cuts`).
    hanging: list[tuple[BoolArray, BoolArray]] = []

    def cost(rotations: FloatArray) -> float:
        return truncated_l1(rotations, i, j, R, w, cap, known)

    tree = chain_tree(num_nodes, i, j, w)
    # The chain start is the odometry's rotations; without odometry it is one more
    # arbitrary spanning tree, and the caller's tree (the filter's) is start enough. (On the
    # 9 SfM regime cases the chain start never won; skipping it saves a third of the
    # GNC time there.) Where the odometry is in pieces, the chain tree joins them by
    # whichever closure it meets first, and the pieces joined by the closures that agree
    # (:func:`~.odometry_start.odometry_start`) are one more start.
    chain_rot = tree_rotations(i, j, R, np.flatnonzero(tree), num_nodes)
    has_odometry = bool(odometry.any())
    chain = {"chain": chain_rot} if has_odometry or not starts else {}
    if has_odometry:
        joined = odometry_start(num_nodes, i, j, R, w, odometry, initial_threshold)
        if not np.allclose(joined, chain_rot, atol=1e-9):
            chain["odometry"] = joined
    dmf = {} if dmf_rotations is None else {"dmf": dmf_rotations}
    # One more start where the odometry lets neighbouring closures vouch for each other:
    # the fit of the odometry and the closures a neighbour supports, which neither random
    # false closures nor a winding of the headings bends (:func:`supported_closures_start`).
    supported = supported_closures_start(num_nodes, i, j, R, w, odometry) if has_odometry \
        else None
    more = {} if supported is None else {"supported": supported}
    solutions = robust_solutions(i, j, R, w, {**dmf, **chain, **starts, **more},
                                 initial_threshold, workers)
    start = most_likely(solutions, i, j, R, w, max_threshold)
    rot, inlier = solutions[start]
    rot, inlier, noise, t = _settle(rot, i, j, R, w, inlier, known, tree, rounds,
                                    max_threshold, initial_threshold)
    cap = _cap(noise, initial_threshold)
    # GNC again at the threshold the data's noise sets (at most the initial one), with the
    # odometry trusted from here on: at the fixed initial threshold a group of mutually
    # consistent false closures can bend a weakly connected graph with every residual
    # under it; at a few noise scales it cannot, and cutting the odometry to fit them
    # costs the cut edges' full residuals. It runs where step 3 found outliers, whatever
    # the noise scale: a scale fitted to a fit that false closures bent is inflated, and
    # above the initial threshold's it had left the closures unjudged (a 50-keyframe chain
    # with 8 true closures and a group of 7 false ones: 8.2 deg per axis, four of the group
    # kept, 18.4 deg median error against the oracle's 1.8). Where step 3 found no outlier
    # every edge is consistent at the fitted noise and there is nothing to judge again,
    # except on an odometry chain with sparse loop closures (``chain_below``), where the
    # pass always runs, pairwise test included: there each closure carries much of the
    # fit, and a few false ones can bend it until every residual is inside (a 100-keyframe
    # chain with 8 true and 2 false closures: no outlier, 7.1 deg per axis against the
    # odometry's 1.4), and wherever the loop closures are few (``PAIRWISE_ALWAYS_UP_TO``),
    # where a group of false ones can lift the redundancy above the chain bound and still
    # bend step 3's fit until it shows no outlier (a 50-keyframe chain with 8 true closures
    # and a group of 7 false ones: redundancy 0.23, 11.1 deg mean error against the
    # oracle's 1.8). Without odometry there is nothing to judge the closures by.
    chain_like = has_odometry and redundancy(num_nodes, inlier) < chain_below
    if math.isfinite(noise.sigma) and has_odometry and (chain_like or few_closures(odometry)
                                                        or not inlier.all()):
        step3_residuals = residual_angles(rot, i, j, R) * np.sqrt(w)
        tight = functools.partial(_tight_pass, num_nodes, i, j, R, w, step3=(
            rot, inlier, noise, t), tree=tree, rounds=rounds, max_threshold=max_threshold,
            initial_threshold=initial_threshold, workers=workers, chain_like=chain_like)
        tight_fit = tight(odometry, chain)
        known = odometry
        # Odometry that the loop closures across it disagree with (a front end that lost
        # its track and reported a wrong step): trusted, it turns everything after it, and
        # the pass rejects the true closures across it instead. The pass runs again with
        # the suspects as ordinary edges, from the odometry's pieces joined where the most
        # closures agree, and stands where it explains the data clearly better.

        def break_that_stands(tried: OdometrySuspects, untrusting: TightFit,
                              trusted: BoolArray, margin: float = 0.0,
                              ) -> tuple[OdometrySuspects, TightFit, BoolArray] | None:
            """The break test (:func:`_breaks_explain_more`) on the untrusting pass of
            ``tried``; where a step it cuts has nodes hang by it against one run of
            closures alone (:func:`_hanging_cuts`), that step is trusted again and the
            pass runs without it, and without the other suspects that closures span
            and that nothing but their size made suspect (a turn spread over several
            steps: else the cut moves to the next one), up to ``HANGING_RETRIES``
            times. ``(suspects, pass, trusted)`` of the break that stands, or None."""
            for retry in range(HANGING_RETRIES + 1):
                if not _breaks_explain_more(tight_fit, untrusting, i, j, R, w, trusted,
                                            tried, initial_threshold, margin):
                    return None
                steps, closures = _hanging_cuts(tight_fit, untrusting, i, j, R, trusted,
                                                tried)
                if not steps.any():
                    return tried, untrusting, trusted
                hanging.append((steps, closures))
                spanned = steps_spanned(i, j, closures, odometry)
                tried = tried.trusting(steps | (_suspect_by_closures_only(R, odometry, tried)
                                                & spanned))
                if retry == HANGING_RETRIES or not tried.edges.any():
                    return None
                untrusting, trusted = untrusted(tried)
            return None

        misfit = ((step3_residuals > initial_threshold)
                  | (residual_angles(tight_fit.rotations, i, j, R) * np.sqrt(w)
                     > GNC_SIGMAS * tight_fit.noise.sigma))
        suspects = suspect_odometry(num_nodes, i, j, R, odometry, tight_fit.inlier, misfit)
        untrusted = functools.partial(_untrusting_pass, tight, num_nodes, i, j, R, w,
                                      odometry, max_threshold, initial_threshold, tree)
        tries: list[OdometrySuspects] = []
        if not odometry.all():  # (no closure: nothing to judge by)
            # Jumps a first-pass fit left out (it judged the odometry as any other edge)
            # are suspects too, tried first: that pass stands where it cuts one of them and
            # explains the data clearly better; else the pass without them is tried.
            judged = suspects.with_left_out(left_out_jumps(
                i, j, R, odometry, (first_inlier for _, first_inlier in solutions.values())))
            if judged.left_out is not None and judged.left_out.any():
                tries.append(judged)
            if suspects.edges.any():
                tries.append(suspects)
        for tried in tries:
            untrusting, trusted = untrusted(tried)
            if tried.left_out is not None and not (tried.left_out & ~untrusting.inlier).any():
                continue  # no left-out jump cut: no break of theirs found
            stood = break_that_stands(tried, untrusting, trusted)
            if stood is not None:
                tried, tight_fit, known = stood
                distrusted, jumps = tried.edges, tried.jumps
                break
        # Several wrong steps: a fit bent by all of them points at some only, and the
        # closures across the others are rejected by the fit that cut the first ones and
        # trusts the rest. The test runs again from the fit it chose, by a margin.
        for _ in range(BREAK_TEST_ROUNDS - 1):
            if distrusted is None:  # (no break)
                break
            again = _more_suspects(num_nodes, i, j, R, w, odometry, known, tight_fit,
                                   distrusted, jumps)
            if again is None:
                break
            untrusting, trusted = untrusted(again)
            stood = break_that_stands(again, untrusting, trusted, LATER_ROUND_MARGIN)
            if stood is None:
                break
            again, tight_fit, known = stood
            distrusted, jumps = again.edges, again.jumps
        rot, inlier, noise, t = (tight_fit.rotations, tight_fit.inlier, tight_fit.noise,
                                 tight_fit.t)
        runs_left_out = tight_fit.runs_left_out
        cap = _cap(noise, initial_threshold)
    # A route bent around a wrong step where jumps are common (a car's turns): the break
    # test had nothing to point at; the trusted jump whose cut unbends the fit is cut. Only
    # on an odometry chain with sparse loop closures: on a pose graph dense with loops, a
    # biased odometry strains every step, and a cut that relieves the strain turned a block
    # of parking-garage (0.5-1 deg a step: means 2.1-2.9 deg -> 5.0-8.3 deg).
    if chain_like and math.isfinite(noise.sigma):
        common = common_jumps(R, odometry)
        for _ in range(BENT_CUTS):
            c = min(GNC_SIGMAS * noise.sigma, initial_threshold)
            bent = cut_bent_jump(rot, i, j, R, w, inlier | known, known, common & ~jumps, c,
                                 BENT_CUT_PENALTY, functools.partial(
                                     truncated_squares, i=i, j=j, R=R, w=w, c=c))
            if bent is None:
                break
            known = known.copy()
            known[bent.edge] = False
            cut = np.zeros(i.size, bool)
            cut[bent.edge] = True
            distrusted = cut if distrusted is None else distrusted | cut
            jumps = jumps | cut
            rot, inlier, noise, t = _settle(bent.rotations, i, j, R, w, bent.inlier, known,
                                            tree, rounds, max_threshold, initial_threshold)
            cap = _cap(noise, initial_threshold)
            if not math.isfinite(noise.sigma):
                break
    relocalized = 0
    # Nodes the re-solve left far off (all their true edges dropped) move to where their
    # own edges agree, if that lowers the choice cost; the inliers then settle again.
    moved_rot, moves = relocalize_nodes(rot, i, j, R, w, cap, known)
    if moves:
        fit = (residual_angles(moved_rot, i, j, R) * np.sqrt(w) <= cap) | known
        moved_rot = refine_least_squares(moved_rot, i, j, R, w * fit)
        moved = _settle(moved_rot, i, j, R, w, fit, known, tree, rounds, max_threshold,
                        initial_threshold)
        if cost(moved[0]) < cost(rot):
            rot, inlier, noise, t = moved
            relocalized = moves
            cap = _cap(noise, initial_threshold)
    # A block of nodes that one wrong edge or one run of closures alone holds to the rest
    # turns where its rejected edges to the rest agree (:func:`turn_blocks`).
    # A trusted step may be cut there too (a wrong step the break test did not catch); a
    # jump cut so pays no penalty, as one the break test cut, where jumps are rare (where
    # they are common, a car's turns, a step's size is no evidence of a lost track).
    # Once a turn stands, more rounds turn the blocks left, many at a time
    # (``together``): a lost track can break many steps.
    for turn_round in range(1 + MORE_TURN_ROUNDS):
        turned = turn_blocks(rot, i, j, R, w, (inlier, noise, t), known, tree=tree,
                             rounds=rounds, max_threshold=max_threshold,
                             initial_threshold=initial_threshold,
                             closures=~odometry if has_odometry else None,
                             steps=odometry & ~jumps & ~(known & rare_jumps(R, odometry)),
                             breakable=odometry, together=turn_round > 0)
        if turned is None:
            break
        rot, inlier, noise, t, moved_nodes, still_trusted = turned
        relocalized += moved_nodes
        cap = _cap(noise, initial_threshold)
        if not np.array_equal(still_trusted, known):
            cut = known & ~still_trusted
            distrusted = cut if distrusted is None else distrusted | cut
            known = still_trusted
    # Least squares on a sparse graph has local minima (a block of nodes turned the wrong
    # way, every edge on its rim bent a little): the same inliers from the chordal
    # relaxation's solution may fit them better.
    restarted = least_squares_from_relaxation(rot, i, j, R, w, inlier)
    if restarted is not None:
        rot = restarted
        noise, _, t = _fit_and_classify(rot, i, j, R, w, inlier, max_threshold, tree)
        cap = _cap(noise, initial_threshold)
    gaussian = looks_gaussian(t, inlier, edge_residuals(rot, i, j, R))
    # Those steps are unchecked where the fit still rejects a closure out of their nodes
    # (where it keeps them all, a break elsewhere reconciled the two).
    unchecked = np.zeros(i.size, bool)
    for steps, closures in hanging:
        if (closures & ~inlier).any():
            unchecked |= steps & known
    return RobustSolve(rot, inlier, noise, t, cap, known, tree, start, relocalized,
                       restarted is not None, runs_left_out, gaussian, distrusted,
                       unchecked)


def turn_blocks(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    fit: tuple[BoolArray, NoiseModel, FloatArray], known: BoolArray, *, tree: BoolArray,
    rounds: int, max_threshold: float, initial_threshold: float,
    closures: BoolArray | None = None, steps: BoolArray | None = None,
    breakable: BoolArray | None = None, together: bool = False,
) -> tuple[FloatArray, BoolArray, NoiseModel, FloatArray, int, BoolArray] | None:
    """Step 5's block turns: the first turn proposed by
    :func:`~.relocalize_blocks.block_turns` (at the fit's cap, ``initial_threshold`` the
    tolerance of the agreement; runs of the ``closures`` edges, None: no runs) that
    stands, as step 3's fit (rotations, inliers, noise, standardized residuals) plus the
    nodes on the smaller side of its cut and the edges still trusted (``known`` less a cut
    through the ``breakable`` ones); None where none stands (or the fit's noise scale is not
    finite). ``fit``: the inliers, noise model and standardized residuals of ``rot``.

    Each turn is re-fitted on the inliers without the cut edges and with the edges that
    agree on the turn, then settles (step 3), and stands where that lowers the truncated
    squares (the GNC's objective, at ``GNC_SIGMAS`` times the lower of the two fits' noise
    scales, of those resting on enough residuals, :func:`_judged_scale`, at most
    ``initial_threshold``) with each run of closures one piece of evidence
    (:func:`squares_by_pieces`: the fit that cut a run of seven false closures must not
    pay seven caps where the one that kept it left out four true closures between
    different places). Not the choice's L1 cost: the turned block closes a long loop whose
    drift spreads over all its edges, which the L1 cost counts at full length and the
    squares, as the noise does, at almost nothing (the parking-garage of ``regime_stress``
    draw 97 with wrong odometry steps: L1 up by 0.2 rad, 6.6 caps, for a fit at the
    oracle's accuracy, 1.49 deg mean error where the block's 137 nodes had been 73 deg
    off). A cut through ``steps`` (odometry that is
    no rare jump, :func:`~.odometry_breaks.rare_jumps`) costs ``BREAK_PENALTY`` caps more, as in
    :func:`_breaks_explain_more`: odometry is rarely wrong, and two false edges that happen
    to agree must not cut a true step (a 50-keyframe chain with 7 false closures and two
    wrong steps: a true step cut for a wrong step and a false closure, 2.03 -> 7.83 deg
    mean without the penalty), unless the turn only moves a break: it joins a step left
    out, and the closures it joins vouch for it on their own (:func:`_breaks_added`).

    ``together``: the rounds after a turn stood (:data:`MORE_TURN_ROUNDS`), for graphs with
    many blocks to turn: up to :data:`MORE_TURNS` proposals, each judged alone on the edges
    that cross its block (:func:`_apart`); those that gain there and touch no other turn
    together, with one re-fit and the same test. Turning 40 blocks one at a time cost
    City10000 (gtsam's data, 200 wrong odometry steps) 40 re-fits of its 10,000 nodes."""
    inlier, noise, t_fit = fit
    if not math.isfinite(noise.sigma):
        return None
    turns = block_turns(rot, i, j, R, w, _cap(noise, initial_threshold), initial_threshold,
                        known, closures, breakable=breakable,
                        limit=MORE_TURNS if together else MAX_TURNS)
    runs = closure_runs(i, j, closures & ~known) if turns and closures is not None else []
    left_out = np.zeros(i.size, bool) if breakable is None else breakable & ~known
    breaks = functools.partial(_breaks_added, steps=steps, left_out=left_out,
                               closures=closures, i=i, j=j)
    judged = functools.partial(_turned_fit, rot, i, j, R, w, fit, known, tree=tree,
                               rounds=rounds, max_threshold=max_threshold,
                               initial_threshold=initial_threshold, runs=runs, breaks=breaks)
    if together:
        apart = _apart(rot, i, j, R, w, min(GNC_SIGMAS * noise.sigma, initial_threshold),
                       known, turns, breaks)
        return judged(apart) if apart else None
    for turn in turns:
        out = judged([turn])
        if out is not None:
            return out
    return None


def _turned_fit(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    fit: tuple[BoolArray, NoiseModel, FloatArray], known: BoolArray, turns: list[BlockTurn],
    *, tree: BoolArray, rounds: int, max_threshold: float, initial_threshold: float,
    runs: list[IntArray], breaks: Callable[[BlockTurn], int],
) -> tuple[FloatArray, BoolArray, NoiseModel, FloatArray, int, BoolArray] | None:
    """The block ``turns`` applied together to ``rot``, re-fitted by least squares on the
    inliers without their cuts and with their joins, settled (step 3), as
    :func:`turn_blocks` returns it, where that lowers the truncated squares by pieces
    (``runs``) by more than the penalties of the breaks they add (``breaks``, per turn);
    else None."""
    inlier, noise, t_fit = fit
    turned, trusted, held = rot.copy(), known.copy(), inlier | known
    for turn in turns:
        turned[turn.nodes] = rot[turn.nodes] @ turn.turn
        trusted[turn.cut] = False  # (a trusted step cut: capped in both fits' squares)
        held[turn.cut] = False
    for turn in turns:
        held[turn.joins] = True
    turned = refine_least_squares(turned, i, j, R, w * held)
    moved = _settle(turned, i, j, R, w, held, trusted, tree, rounds, max_threshold,
                    initial_threshold)
    sigma = _judged_scale((noise, t_fit, inlier), (moved[2], moved[3], moved[1]))
    c, mean_square = min(GNC_SIGMAS * sigma, initial_threshold), noise.axes * sigma ** 2
    penalty = sum(breaks(turn) for turn in turns)
    if (squares_by_pieces(moved[0], i, j, R, w, c, trusted, runs, mean_square)
            + BREAK_PENALTY * penalty * c * c
            < squares_by_pieces(rot, i, j, R, w, c, trusted, runs, mean_square)):
        return (*moved, sum(turn.relocalized for turn in turns), trusted)
    return None


def _apart(rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
           c: float, known: BoolArray, turns: list[BlockTurn],
           breaks: Callable[[BlockTurn], int]) -> list[BlockTurn]:
    """Of the block ``turns`` (the best supported first), those that lower the truncated
    squares (threshold ``c``; ``known`` edges uncapped, a trusted cut capped) of the edges
    that cross their block, before any re-fit, by more than the penalties of the breaks
    they add (``breaks``), and touch no block taken before them (no shared node, no edge
    between)."""
    squares = residual_angles(rot, i, j, R) ** 2 * w
    taken = np.zeros(rot.shape[0], bool)  # the chosen blocks' nodes
    touched = np.zeros(rot.shape[0], bool)  # and the nodes their crossing edges reach
    chosen: list[BlockTurn] = []
    for turn in turns:
        block = np.zeros(rot.shape[0], bool)
        block[turn.nodes] = True
        cross = np.flatnonzero(block[i] != block[j])
        ends = np.concatenate([i[cross], j[cross]])
        if touched[turn.nodes].any() or taken[ends].any():
            continue
        # The crossing edges' ends only, the block's turned (no copy of every rotation
        # for each of up to MORE_TURNS proposals).
        ends_rot = rot[ends]
        ends_rot[block[ends]] = ends_rot[block[ends]] @ turn.turn
        k = cross.size
        after = residual_angles(ends_rot, np.arange(k), np.arange(k, 2 * k),
                                R[cross]) ** 2 * w[cross]
        trusted = known[cross] & ~np.isin(cross, turn.cut)  # a trusted cut: capped
        if (_capped_sum(after, c * c, trusted)
                + BREAK_PENALTY * breaks(turn) * c * c
                < _capped_sum(squares[cross], c * c, known[cross])):
            chosen.append(turn)
            taken[turn.nodes] = True
            touched[ends] = True
    return chosen


def _breaks_added(turn: BlockTurn, *, steps: BoolArray | None, left_out: BoolArray,
                  closures: BoolArray | None, i: IntArray, j: IntArray) -> int:
    """Odometry breaks a block ``turn`` adds, each ``BREAK_PENALTY`` caps: the ``steps`` it
    cuts, less the ``left_out`` steps (odometry no longer trusted) it joins where the
    ``closures`` it joins are two independent pieces of evidence or more on their own
    (:func:`~.closure_runs.independent_pieces`). Such a turn moves a break from the step left
    out to the step it cuts and adds none, the closures vouching for it without the step: a
    node between a wrong step, trusted, and the true step the break test left out, its
    closures rejected (City10000's lost tracks). Where they do not, a wrong step left out
    and a false closure that happen to agree would cut a true step for nothing (the
    new-user chain with two wrong steps: 2.03 -> 7.83 deg mean)."""
    cut = 0 if steps is None else int(np.count_nonzero(steps[turn.cut]))
    moved = int(np.count_nonzero(left_out[turn.joins]))
    if not cut or not moved or closures is None:
        return cut
    joined = np.zeros(i.size, bool)
    joined[turn.joins[closures[turn.joins]]] = True
    if independent_pieces(i, j, joined) < 2:
        return cut
    return max(0, cut - moved)


@dataclass(frozen=True)
class TightFit:
    """Step 4's result: a least-squares fit and the edges it rests on, as step 3 gives it."""

    rotations: FloatArray
    inlier: BoolArray
    noise: NoiseModel
    t: FloatArray
    runs_left_out: int


def _tight_pass(
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    known: BoolArray, chain_starts: dict[str, FloatArray], *,
    step3: tuple[FloatArray, BoolArray, NoiseModel, FloatArray], tree: BoolArray,
    rounds: int, max_threshold: float, initial_threshold: float, workers: int,
    chain_like: bool, suspects: OdometrySuspects | None = None,
) -> TightFit:
    """Step 4 of the module docstring from step 3's fit ``step3`` (rotations, inliers,
    noise, standardized residuals): GNC at ``GNC_SIGMAS`` noise scales with the ``known``
    edges trusted, from step 3's solution, each of ``chain_starts`` and, where called for,
    pairwise-consistent closure sets; then runs of closures left out. With ``suspects``
    (the break test's pass, the suspects not ``known``): each chain start's truncated
    least-squares fit (:func:`_local_fit`) is one more consistent start, its noise scale
    counted only where ``MIN_NOISE_RESIDUALS`` of its informative residuals are in it, and
    the candidates pay the break test's ``BREAK_PENALTY`` caps for each suspect left out
    that is no jump (:func:`_breaks_explain_more`)."""
    rot, inlier, noise, t = step3
    inlier = inlier | known
    threshold = np.minimum(GNC_SIGMAS * noise.sigma / np.sqrt(w), initial_threshold)
    # GNC at a tight threshold depends on its start: from step 3's solution and from
    # the odometry chain (which no false closure bends), the lower cost wins; its
    # inliers then settle. Where those disagree, the result depends on the start, and
    # the best start from pairwise-consistent closure sets joins them (on a chain, and
    # where the closures are few enough for the test to be cheap, also where they
    # agree: both can end in the same bent fit). The fits compare by the
    # GNC's own objective, their truncated squares (:func:`truncated_squares`), not by
    # the choice's L1 cost.
    tls = functools.partial(truncated_squares, i=i, j=j, R=R, w=w,
                            c=GNC_SIGMAS * noise.sigma, trusted=known)
    candidates: list[tuple[float, FloatArray, BoolArray]] = []
    penalized = None if suspects is None else suspects.edges & ~suspects.jumps

    def cost(rotations: FloatArray, kept: BoolArray) -> float:
        """A candidate's truncated squares, plus the penalty of the suspects it cuts."""
        value = tls(rotations)
        if penalized is not None:
            value += BREAK_PENALTY * np.count_nonzero(penalized & ~kept) * tls.keywords["c"] ** 2
        return float(value)

    def tight_from(*begins: tuple[FloatArray, float]) -> None:
        """GNC at ``threshold`` from each ``(start, mu_min)``, on up to ``workers``
        threads; each new inlier set, in the starts' order, is a candidate."""
        fits = map_in_threads(
            lambda begin: robust_from(begin[0], i, j, R, w, threshold, known, begin[1]),
            begins, workers)
        for tight_rot, tight_inlier in fits:
            if not any(np.array_equal(tight_inlier, c[2]) for c in candidates):
                candidates.append((cost(tight_rot, tight_inlier), tight_rot, tight_inlier))

    def from_every_start(consistent_fits: list[FloatArray]) -> None:
        begins = [(rot, TIGHT_START_MU)] + [(start, 0.0) for start in chain_starts.values()]
        if consistent_fits:  # (the GNC keeps the order of the starts' costs: from the best)
            begins.append((min(consistent_fits, key=tls), TIGHT_START_MU))
        tight_from(*begins)

    from_every_start([])
    consistent = consistent_starts(num_nodes, i, j, R, w, known, noise.sigma) if (
        len(candidates) > 1 or chain_like or few_closures(known)) else ConsistentStarts()
    local = [fit for fit in (_local_fit(start, i, j, R, w, threshold, known)
                             for start in chain_starts.values()) if fit is not None
             ] if suspects is not None else []
    fits = [start for start, _ in (*consistent.starts, *local)]
    if fits:
        tight_from((min(fits, key=tls), TIGHT_START_MU))
    # The noise scale came from step 3's fit, which false closures the odometry's drift
    # can explain may have bent: then a consistent start fits its own edges at a clearly
    # lower scale, or the closures' loops over the odometry show one, and at step 3's
    # the bent fit costs least. The pass runs again at the lower scale, every candidate
    # costed there.
    scales = [_noise_of(start, i, j, R, w, kept, max_threshold, tree)
              for start, kept in consistent.starts]
    scales += [_noise_of(start, i, j, R, w, kept, max_threshold, tree, resting=True)
               for start, kept in local]
    # The loops' bound counts where it is below every consistent start's scale (also
    # where there is no such start), and only on a chain whose odometry does not turn
    # about one axis. Elsewhere step 3's scale rests on many redundant edges, and loops
    # over the odometry alone mistake the odometry's noise for every edge's where the
    # closures' differs (odometry at 0.5 deg, closures at 3 deg, every weight 1: the tight
    # pass at the loops' scale then cut true closures, up to 21% higher medians on the
    # stress variants of parking-garage and sphere2500). A planar robot's chain is fitted
    # with the three-axis model (``RotationAverager.solve_component``), whose chi-square
    # reads the loops' one-axis angles at a third of their scale or less: there the pass
    # cut true closures (the planar chain: higher by 5-27% at six of the seven stress
    # draws of twenty that moved).
    by_loops = False  # the lower scale is the loops' bound
    bound = consistent.loop_bound
    if (chain_like and math.isfinite(bound) and not any(s <= bound for s in scales)
            and noise_axes(R[known]) == 3):
        scales.append(bound)
        by_loops = True
    if scales and min(scales) < RESCALE_BELOW * noise.sigma:
        rescaled = min(scales)
        threshold = np.minimum(GNC_SIGMAS * rescaled / np.sqrt(w), initial_threshold)
        tls = functools.partial(truncated_squares, i=i, j=j, R=R, w=w,
                                c=GNC_SIGMAS * rescaled, trusted=known)
        candidates = [(cost(c[1], c[2]), c[1], c[2]) for c in candidates]
        from_every_start(fits)
    else:
        by_loops = False
    best = min(candidates, key=lambda c: c[0])
    if not np.array_equal(best[2], inlier):  # else: the same fit as step 3's
        if by_loops:
            # At the scale the loops show, which no fit enters, the inliers of the
            # candidate that costs least there stand (whichever round found it), with
            # the noise model of their own fit, its classification unused: step 3's
            # re-admission judges an edge outside the fit by its prediction variance,
            # which on a chain with long odometry between closures excuses closures
            # several degrees wrong (false ones 5-30 deg off the truth, six 300-keyframe
            # chains: settled, 68 of their 72 kept, as without the bound; unsettled, 38).
            fitted, _, fitted_t = _fit_and_classify(best[1], i, j, R, w, best[2],
                                                    max_threshold, tree)
            tight = (best[1], best[2], fitted, fitted_t)
        else:
            tight = _settle(best[1], i, j, R, w, best[2], known, tree, rounds,
                            max_threshold, initial_threshold)
        if cost(tight[0], tight[1]) < cost(rot, inlier):
            rot, inlier, noise, t = tight
    # Runs of consistent false closures the pairwise test could not reach (the odometry
    # between them and the true closures is long) pull the fit all one way.
    rot, inlier, noise, t, runs_left_out = _leave_runs_out(
        rot, i, j, R, w, inlier, noise, t, known, tree, rounds, max_threshold,
        initial_threshold)
    return TightFit(rot, inlier, noise, t, runs_left_out)


def _local_fit(start: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
               threshold: float | FloatArray, known: BoolArray,
               ) -> tuple[FloatArray, BoolArray] | None:
    """Truncated least squares from ``start``: least squares on the edges within
    ``threshold`` of the rotations (and the ``known`` ones), again from its fit until
    those edges repeat (at most ``LOCAL_FIT_ROUNDS`` fits), where they join every node:
    ``(rotations, edges kept)``, else None."""
    rot = start
    keep = np.zeros(i.size, bool)
    for _ in range(LOCAL_FIT_ROUNDS):
        within = (residual_angles(rot, i, j, R) <= threshold) | known
        if np.array_equal(within, keep):
            break
        keep = within
        if keep.all() or not connects_all(start.shape[0], i, j, keep):
            return None
        rot = refine_least_squares(rot, i, j, R, w * keep)
    return rot, keep


def _untrusting_pass(
    tight: Callable[..., TightFit], num_nodes: int, i: IntArray, j: IntArray, R: FloatArray,
    w: FloatArray, odometry: BoolArray, max_threshold: float, initial_threshold: float,
    tree: BoolArray, suspects: OdometrySuspects,
) -> tuple[TightFit, BoolArray]:
    """``(fit, trusted)``: the tight pass (``tight``, :func:`_tight_pass` bound to the
    graph) with the ``suspects`` as ordinary edges, from the odometry's pieces joined where
    the most closures agree, and the odometry it still trusts."""
    trusted = odometry & ~suspects.edges
    # The pieces join where the most closures agree: a suspect step counts as one
    # closure there, not at the odometry's weight, which would outvote them all. Where the
    # closures are few (``few_closures``), a join rests on one or two of them, and a
    # suspect that is no jump counts as 1 + BREAK_PENALTY closures, what cutting it costs
    # the pass's candidates: at one, a false closure tied with it, joined its piece turned,
    # and the GNC from there cut the true step (a 50-keyframe chain whose wrong step bent
    # step 3's fit until a true step beside it misfit: 6.47 deg mean against the oracle's
    # 1.90, which the firmer join reaches). Where they are many, the firmer joins let the
    # Manhattan world's 117 misfit steps outvote its closures, and the break test then cut
    # them for runs of false closures (20% random and 10 runs, seed 2: 5.72 -> 11.36 deg).
    one = float(np.median(w[~odometry]))
    firm = suspects.edges & ~suspects.jumps & few_closures(odometry)
    w_join = np.where(firm, (1.0 + BREAK_PENALTY) * one, np.where(suspects.edges, one, w))
    joined = odometry_start(num_nodes, i, j, R, w_join, trusted, initial_threshold)
    # Step 3's fit trusted the suspects, and where they are wrong it is bent and its
    # scale inflated: at 4 such scales the GNC from the joined pieces takes a wrong step
    # back in. The truncated least squares from those pieces fits their edges at the
    # data's scale, and the pass runs again at it.
    untrusting: TightFit = tight(trusted, {"odometry": joined}, suspects=suspects)
    # A cut the closures cannot tell from a jump's: on the jump.
    moved_rot, moved_inlier = cuts_onto_jumps(untrusting.rotations, i, j, R, odometry,
                                              untrusting.inlier, suspects)
    if not np.array_equal(moved_inlier, untrusting.inlier):
        moved_noise, _, moved_t = _fit_and_classify(moved_rot, i, j, R, w, moved_inlier,
                                                     max_threshold, tree)
        untrusting = TightFit(moved_rot, moved_inlier, moved_noise, moved_t,
                              untrusting.runs_left_out)
    return untrusting, trusted


def _more_suspects(num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
                   odometry: BoolArray, known: BoolArray, fit: TightFit,
                   distrusted: BoolArray, jumps: BoolArray) -> OdometrySuspects | None:
    """The break test's next suspects after a break (:func:`robust_resolve`): the steps of
    the odometry still trusted (``known``) that the fit ``fit`` points at
    (:func:`~.odometry_breaks.suspect_odometry` over the whole odometry, its misfits at
    ``GNC_SIGMAS`` noise scales), with the earlier rounds' suspects (``distrusted``, cut
    or left as ordinary edges), which count as jumps: no penalty again. None where it
    points at none."""
    misfit = (residual_angles(fit.rotations, i, j, R) * np.sqrt(w)
              > GNC_SIGMAS * fit.noise.sigma)
    found = suspect_odometry(num_nodes, i, j, R, odometry, fit.inlier, misfit)
    new = found.edges & known
    if not new.any():
        return None
    return OdometrySuspects(distrusted | new, jumps | (found.jumps & known) | distrusted)


def _breaks_explain_more(trusting: TightFit, untrusting: TightFit, i: IntArray,
                         j: IntArray, R: FloatArray, w: FloatArray, trusted: BoolArray,
                         suspects: OdometrySuspects, initial_threshold: float,
                         margin: float = 0.0) -> bool:
    """Whether the tight pass with the ``suspects`` (odometry) as ordinary edges explains
    the data better than the pass that trusted them: its truncated squares
    (:func:`truncated_squares`, at ``GNC_SIGMAS`` times the lower of the two fits' noise
    scales, of those resting on enough residuals, :func:`_judged_scale`, at most
    ``initial_threshold`` as in the GNC; the suspects capped in both) plus
    ``BREAK_PENALTY`` caps for each suspect it leaves out that is not among
    ``suspects.jumps`` are below the trusting pass's. Odometry
    is rarely wrong, and a group of consistent false closures can claim that a true step
    is: cutting a step suspect only as a misfit must free several closures, and more than
    one run of them (:func:`~.closure_runs.independent_pieces`): the closures of one run,
    between the same two stretches, are one wrong match repeated keyframe after keyframe
    (perceptual aliasing), one piece of evidence against the odometry. A jump the closures
    point at, or a rare one, needs only its own cap; one a first-pass fit left out
    (``suspects.left_out``) pays the penalty, but one run of freed closures is enough.
    ``margin``: caps the untrusting pass must gain beyond that. Noise scales that are not
    finite: no cut."""
    if not (math.isfinite(trusting.noise.sigma) and math.isfinite(untrusting.noise.sigma)):
        return False
    c = min(GNC_SIGMAS * _judged_scale(*((f.noise, f.t, f.inlier)
                                           for f in (trusting, untrusting))),
            initial_threshold)
    cut_edges = suspects.edges & ~untrusting.inlier & ~suspects.jumps
    cut = int(np.count_nonzero(cut_edges))
    freed = untrusting.inlier & ~trusting.inlier & ~(trusted | suspects.edges)
    misfits_cut = cut_edges if suspects.left_out is None else cut_edges & ~suspects.left_out
    if misfits_cut.any() and independent_pieces(i, j, freed) <= 1:
        return False
    return bool(truncated_squares(untrusting.rotations, i, j, R, w, c, trusted)
                + (BREAK_PENALTY * cut + margin) * c * c
                < truncated_squares(trusting.rotations, i, j, R, w, c, trusted))


def _hanging_cuts(trusting: TightFit, untrusting: TightFit, i: IntArray, j: IntArray,
                  R: FloatArray, trusted: BoolArray, suspects: OdometrySuspects,
                  ) -> tuple[BoolArray, BoolArray]:
    """``(steps, closures)``: the steps the untrusting pass cuts (``suspects`` it leaves
    out) that nodes hang by, against one run of loop closures and nothing else, and those
    closures (:func:`hanging_steps`): one piece of evidence against one trusted step that
    nothing else checks. Not the steps whose size alone is evidence of a lost track
    (:func:`outsized_steps`), nor jumps a first-pass fit left out (``suspects.left_out``:
    that fit's word besides). Such steps stay trusted (:func:`robust_resolve`)."""
    odometry = trusted | suspects.edges
    judged = _suspect_by_closures_only(R, odometry, suspects) & ~untrusting.inlier
    if not judged.any():
        return judged, judged
    freed = untrusting.inlier & ~trusting.inlier & ~odometry
    return hanging_steps(i, j, odometry, untrusting.inlier | trusted, freed, judged)


def _suspect_by_closures_only(R: FloatArray, odometry: BoolArray,
                          suspects: OdometrySuspects) -> BoolArray:
    """The ``suspects`` that nothing but the closures across them made suspect: not
    outsized (:func:`outsized_steps`: their size is evidence by itself), not left out by a
    first-pass fit (``suspects.left_out``: that fit's word besides)."""
    judged = suspects.edges & ~outsized_steps(R, odometry)
    if suspects.left_out is not None:
        judged &= ~suspects.left_out
    return judged


def _judged_scale(*fits: tuple[NoiseModel, FloatArray, BoolArray]) -> float:
    """The lowest finite noise scale of the ``(noise, t, inlier)`` fits, among those that
    rest on at least ``MIN_NOISE_RESIDUALS`` informative inliers (finite ``t``); the lowest
    finite one where none does (NaN where none is finite)."""
    finite = [f for f in fits if math.isfinite(f[0].sigma)]
    resting = [f for f in finite
               if np.count_nonzero(np.isfinite(f[1]) & f[2]) >= MIN_NOISE_RESIDUALS]
    return min((f[0].sigma for f in resting or finite), default=math.nan)


def _leave_runs_out(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    inlier: BoolArray, noise: NoiseModel, t: FloatArray, known: BoolArray, tree: BoolArray,
    rounds: int, max_threshold: float, initial_threshold: float,
) -> tuple[FloatArray, BoolArray, NoiseModel, FloatArray, int]:
    """Step 4's last part: up to ``RUN_ROUNDS`` times, each suspect run of loop closures
    (:func:`~.closure_runs.suspect_runs` on the least-squares fit ``rot`` of ``inlier``), the
    most suspect first, leaves the fit where least squares without it, then step 3, lowers
    the choice cost (at the cap of the round's noise scale). Returns the fit as step 3
    does, and the number of runs left out."""
    left_out = 0
    for _ in range(RUN_ROUNDS):
        cost = functools.partial(truncated_l1, i=i, j=j, R=R, w=w,
                                 c=_cap(noise, initial_threshold), trusted=known)
        before = left_out
        current = cost(rot)
        for run in suspect_runs(rot, i, j, R, w, inlier, ~known, noise.sigma):
            trial = inlier.copy()
            trial[run] = False
            without = refine_least_squares(rot, i, j, R, w * trial)
            if not cost(without) < current:  # (settling would not save it: a true run's
                continue  # closures each cost a cap once it is out)
            settled = _settle(without, i, j, R, w, trial, known, tree, rounds, max_threshold,
                              initial_threshold)
            settled_cost = cost(settled[0])
            if settled_cost < current:
                rot, inlier, noise, t = settled
                current = settled_cost
                left_out += 1
        if left_out == before:  # (else the runs are judged again on the new fit)
            break
    return rot, inlier, noise, t, left_out


@dataclass(frozen=True)
class ConsistentStarts:
    """:func:`consistent_starts`' answer."""

    starts: tuple[tuple[FloatArray, BoolArray], ...] = ()
    """``(rotations, edges kept)`` per start."""
    loop_bound: float = math.nan
    """An upper bound of the noise scale the closures' loops over the odometry show
    (:func:`~.closure_consistency.loop_noise_scale` with ``upper``; NaN: too few closures
    to tell)."""


def consistent_starts(num_nodes: int, i: IntArray, j: IntArray, R: FloatArray,
                      w: FloatArray, odometry: BoolArray, sigma: float,
                      ) -> ConsistentStarts:
    """Starts for the tight GNC that no group of mutually consistent false closures bends:
    least squares, from their chordal relaxation, on the odometry and a pairwise-consistent
    set of loop closures (:func:`~.closure_consistency.consistent_closures`), the test run
    at ``sigma`` times each of ``CONSISTENCY_SCALES`` (a noise scale fitted where false
    closures bent the solution is too large, and lets a group through), and at the scale the
    closures' loops over the odometry show (:func:`~.closure_consistency.loop_noise_scale`)
    where it is below all of those (a 1,000-keyframe chain with 40% random false closures:
    step 3's fit bent so far that it read 10.5 deg per axis against the odometry's 0.87,
    and a quarter of it still kept 9 false closures). One start per distinct set that
    drops a closure and connects every node, with that set; and the loops' upper bound of
    the noise scale (:class:`ConsistentStarts`)."""
    starts: list[tuple[FloatArray, BoolArray]] = []
    seen: list[BoolArray] = []
    sigmas = [sigma * scale for scale in CONSISTENCY_SCALES]
    loops = closure_loops(num_nodes, i, j, R, w, odometry)
    scale, bound = loop_noise_scale_and_bound(num_nodes, i, j, R, w, odometry, loops)
    if scale < sigmas[-1]:
        sigmas.append(scale)
    for keep in consistent_closures(num_nodes, i, j, R, w, odometry, sigmas, loops):
        if keep.all() or any(np.array_equal(keep, k) for k in seen):
            continue
        seen.append(keep)
        if connects_all(num_nodes, i, j, keep):
            start = chordal_rotations(num_nodes, i[keep], j[keep], R[keep], w[keep])
            starts.append((refine_least_squares(start, i, j, R, w * keep), keep))
    return ConsistentStarts(starts=tuple(starts), loop_bound=bound)


def supported_closures_start(num_nodes: int, i: IntArray, j: IntArray, R: FloatArray,
                             w: FloatArray, odometry: BoolArray) -> FloatArray | None:
    """A start for the first re-solve: least squares, from their chordal relaxation, on
    the ``odometry`` and the loop closures their neighbours support
    (:func:`~.closure_consistency.neighbour_supported`, at the noise scale the closures'
    loops over the odometry show). It drops the random false closures, which bend every
    fit of all the edges, without a threshold on any one residual, and keeps the runs of
    true closures that fix how the headings wind around a revisited place, which a start
    drifting along a tree can miss. Where GNC from the other starts ends in a basin whose
    headings wind by a turn around the graph (the Manhattan world at 5 deg + 20% random
    false closures, seed 2: 24.65 deg mean after GNC from the filter's tree, 17.30 deg
    at the end), GNC from this one reaches the truth's basin, whose likelihood is higher
    (6.78 deg; the whole solve 6.59 deg, the oracle's 6.49). A run of false closures
    supports itself, so one run may hold at most :data:`MIN_SUPPORTED_SHARE` of the
    supported closures (a 50-keyframe chain with a wrong step, 8 lone true closures and a
    run of 7 false ones: the run was the start, and it won, 2.00 deg -> 36.8 deg mean).
    None where fewer than :data:`MIN_SUPPORTED_SHARE` of the closures are supported, one
    run holds more than that share of them, every edge is kept, or the odometry and the
    supported closures do not connect every node."""
    loops = closure_loops(num_nodes, i, j, R, w, odometry)
    if loops is None:
        return None
    scale, _ = loop_noise_scale_and_bound(num_nodes, i, j, R, w, odometry, loops)
    support, run = neighbour_supported(num_nodes, i, j, loops, scale)
    count = np.count_nonzero(support)
    if not count or count < MIN_SUPPORTED_SHARE * np.count_nonzero(~odometry):
        return None
    # A run of false closures supports itself: the support must not rest on one run.
    if np.bincount(run[support]).max() > MIN_SUPPORTED_SHARE * count:
        return None
    keep = odometry.copy()
    keep[loops.testable[support]] = True
    if keep.all() or not connects_all(num_nodes, i, j, keep):
        return None
    start = chordal_rotations(num_nodes, i[keep], j[keep], R[keep], w[keep])
    return refine_least_squares(start, i, j, R, w * keep)


def connects_all(n: int, i: IntArray, j: IntArray, keep: BoolArray) -> bool:
    """Whether the edges ``keep`` connect all ``n`` nodes."""
    labels = connected_components(coo_matrix(
        (np.ones(int(keep.sum())), (i[keep], j[keep])), shape=(n, n)), directed=False)[1]
    return bool(np.all(labels == labels[0]))


def least_squares_from_relaxation(
    rot: FloatArray, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    inlier: BoolArray,
) -> FloatArray | None:
    """Least squares on the ``inlier`` edges from the chordal relaxation's solution of them
    (:func:`~rotavg_ros.core.chordal_init.chordal_rotations`), if it fits them better than
    ``rot`` (a least-squares fit of the same edges): a weighted sum of squared residual
    angles lower by more than ``RESTART_MARGIN`` (relative). None where it does not, where
    the inliers do not connect every node, and on well-connected graphs
    (:data:`~.gauss_newton.WELL_CONNECTED`: their least squares has no such minima in
    practice, and the relaxation's sparse factorization would fill in)."""
    n = rot.shape[0]
    if WELL_CONNECTED.get() or n < 3 or not connects_all(n, i, j, inlier):
        return None
    ii, jj, RR, ww = i[inlier], j[inlier], R[inlier], w[inlier]

    def sse(rotations: FloatArray) -> float:
        r = residual_angles(rotations, ii, jj, RR)
        return float(np.sum(ww * r * r))

    start = chordal_rotations(n, ii, jj, RR, ww)
    candidate = refine_least_squares(start, ii, jj, RR, ww)
    if sse(candidate) < (1.0 - RESTART_MARGIN) * sse(rot):
        return candidate
    return None


@_linear_solves_set_for_the_graph
def choose(
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    robust: RobustSolve, dmf_rotations: FloatArray | None, dmf_kept: BoolArray,
    max_threshold: float = math.radians(90.0), margin: float = 0.02,
    least_squares_below: float = 0.0,
) -> VerifyOutcome:
    """Step 6 of the module docstring: the DMF solution (its far-off nodes first moved, if
    that lowers its cost) or the robust re-solve, by the truncated L1 cost over every
    edge; the DMF solution stands unless the re-solve is ``margin`` (relative) better.
    Where the re-solve's standardized inlier residuals look Gaussian
    (:attr:`RobustSolve.gaussian`) the margin goes the other way: least squares is the
    better estimator there, and an L1 cost favours the L1 fit, so the re-solve stands
    unless the DMF solution is ``margin`` better. Where the re-solve's inliers have a
    redundancy (:func:`~.noise.redundancy`) below ``least_squares_below`` (an odometry chain
    with sparse loop closures, where an L1 fit has no redundant edges to gain from) the two
    are compared by their truncated squares (:func:`truncated_squares`, same cap, odometry
    uncapped), and the re-solve stands unless the DMF solution's is ``margin`` lower.
    ``dmf_rotations`` None: no DMF solution (the solver fitted none), the re-solve stands."""
    known, cap, tree = robust.known, robust.cap, robust.tree

    def cost(rotations: FloatArray) -> float:
        return truncated_l1(rotations, i, j, R, w, cap, known)

    costs = {"robust": cost(robust.rotations)}
    if dmf_rotations is None:
        return _resolve_stands(robust, costs)
    # The DMF solution's far-off nodes move the same way (each move lowers its cost); it
    # then rests on the edges it explains, not on the filter's.
    dmf_moved, dmf_moves = relocalize_nodes(dmf_rotations, i, j, R, w, cap, known)
    dmf_inlier = dmf_kept | known
    if dmf_moves and cost(dmf_moved) < cost(dmf_rotations):
        dmf_rotations = dmf_moved
        dmf_inlier = (residual_angles(dmf_rotations, i, j, R) * np.sqrt(w) <= cap) | known
    else:
        dmf_moves = 0
    # The choice, by the truncated L1 cost over every input edge (Eq. 3 of the paper with
    # each edge's say capped at CHOICE_SIGMAS noise scales, the scale fitted above): a
    # filter that condemned a subtree, or false closures the DMF bent to fit, leave many
    # edges unexplained, each at the cap; outliers cost both solutions the same cap. The
    # re-solve must be clearly better (by ``margin``) to replace the DMF solution, whose L1
    # fit is the more accurate of the two when both explain the data.
    # A DMF solution that needed nodes moved has no claim to the margin: it did not explain
    # the data by itself.
    costs["dmf"] = cost(dmf_rotations)
    if redundancy(num_nodes, robust.inlier) < least_squares_below:
        # Little redundancy: the L1 fit zeroes most residuals, so its L1 cost is far lower
        # (20% on a route driven three times) for a less accurate solution. Judged by the
        # truncated squares instead, it must explain the data better to stand.
        for name, rotations in (("robust", robust.rotations), ("dmf", dmf_rotations)):
            costs[f"{name}_squares"] = truncated_squares(rotations, i, j, R, w, cap, known)
        dmf_stands = costs["dmf_squares"] < (1.0 - margin) * costs["robust_squares"]
    elif robust.gaussian:
        dmf_stands = costs["dmf"] < (1.0 - margin) * costs["robust"]
    else:
        dmf_stands = not costs["robust"] < (1.0 - (0.0 if dmf_moves else margin)) * costs["dmf"]
    if not dmf_stands:
        return _resolve_stands(robust, costs)
    dmf_noise, classified, t_dmf = _fit_and_classify(dmf_rotations, i, j, R, w, dmf_inlier,
                                                     max_threshold, tree)
    return VerifyOutcome(dmf_rotations, dmf_inlier, dmf_noise, "dmf", costs, robust.start,
                         int(np.sum(np.isnan(t_dmf) & ~tree)), cap, dmf_moves, known,
                         classified | known, runs_left_out=robust.runs_left_out,
                         resolve_gaussian=robust.gaussian,
                         distrusted=_count(robust.distrusted, ~(classified | known)),
                         unchecked=_count(robust.unchecked, classified | known))


def _count(edges: BoolArray | None, among: BoolArray) -> int:
    """How many of the ``edges`` (None: none) are ``among`` these (e.g. those a kept
    solution leaves out)."""
    return 0 if edges is None else int(np.count_nonzero(edges & among))


def _resolve_stands(robust: RobustSolve, costs: dict[str, float]) -> VerifyOutcome:
    """The outcome where the robust re-solve is kept."""
    return VerifyOutcome(robust.rotations, robust.inlier, robust.noise, "robust", costs,
                         robust.start, int(np.sum(np.isnan(robust.t) & ~robust.tree)),
                         robust.cap, robust.relocalized, robust.known, robust.inlier,
                         robust.restarted, robust.runs_left_out, robust.gaussian,
                         _count(robust.distrusted, ~robust.inlier),
                         _count(robust.unchecked, robust.inlier | robust.known))

