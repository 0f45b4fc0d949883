"""Options of the rotation averager (no solver logic here), grouped by pipeline stage.

:class:`SolverOptions` holds ``mode`` and one options object per stage: the edge filter
(:class:`FilterOptions`), the DMF model and its Adam fit (:class:`DenseFitOptions`), the
sparse-graph L-BFGS fit (:class:`SparseFitOptions`), warm-started re-solves
(:class:`WarmStartOptions`) and where the solve runs (:class:`RuntimeOptions`). Every default
is written once, here. The command line, the node parameters and older code name the options
by their flat names (``sigma``, ``sparse_rounds``, ``warm_lr``, ...):
:meth:`SolverOptions.from_flat`, :meth:`SolverOptions.flat` and
:meth:`SolverOptions.replace_flat` translate.

Conventions: rotations are world-to-node (``x_node = R_i x_world``); edges carry
``R_ij ~= R_i R_j^T``. The anchor node of each connected component gets identity.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, TypeGuard

import numpy as np

from rotavg_ros.core.types import ProgressFn
from rotavg_ros.errors import InputError


def _flat(name: str) -> dict[str, str]:
    """Field metadata: the option's flat name when it differs from the field's."""
    return {"flat": name}


@dataclass
class FilterOptions:
    """Spanning-tree edge filtering (Sec. IV-A)."""

    use_filter: bool = True
    """Filter edges at all (ablation (a) turns it off)."""
    use_support_count: bool = True
    """Order tree edges by support count first (ablation (b): mean error only)."""
    sigma: float = 0.2
    """Filter threshold on d_chord(R_ij, R_ij^tree) (0.2 = 8.1 deg)."""
    sigma_untested: float | None = 0.6
    """Threshold for edges on no triangle whose tree path is triangle-verified
    (0.6 = 24.5 deg, allowing for path drift); None never removes such edges."""


@dataclass
class DenseFitOptions:
    """The DMF model H H^T and its Adam fit (Sec. IV-B to IV-D): dense mode, and the model
    (width, initial scale, ablations) the sparse fit shares."""

    depths: tuple[int, ...] = (2, 4, 6, 8)
    """Candidate depths d (even); H has d/2 factors. The best by the Eq. 3 cost wins."""
    bracket_depths: bool = True
    """Cold dense fits: fit only the shallowest and the deepest of ``depths`` (beyond the
    paper; False: every candidate, profile ``paper``). Two fits instead of four, one per core
    of a 2-core CPU. Evidence (``python -m benchmarks.depth_bracket``, 2026-12-03): the ten
    ``sfm/`` regime cases at draws 0, 1, 2 and tangent 3, and nine stress / ad-hoc dense
    graphs at draws 0, tangent 1, 21 and tangent 22 (76 solves): the same errors on 72, to
    the printed digit; Ellis + 30% at draws 0 and tangent 3, where depth 6 had won, median
    0.397 -> 0.425 and 0.393 -> 0.425 deg (mean +0.004, +0.008; the best peer's median
    0.93); Ellis + 15% at draw 2 0.383 -> 0.386 (depth 4 had won); dense400/out30 at draw 2
    0.149 -> 0.145. Depth 4 or 6 had won 7 of the 76 choices."""
    prune_ratio: float | None = 0.3
    """Candidate race (beyond the paper; :mod:`rotavg_ros.core.dmf.race`): from iteration
    ``prune_after`` on, every ``prune_every`` iterations, a cold dense fit stops when its
    Eq. 3 cost is above ``1 + prune_ratio`` times the cost of the shallowest candidate (the
    pace-setter) at the same iteration (its final cost once it has ended); a stopped
    candidate is never chosen. None: every candidate runs to the end (profile ``paper``).
    Evidence (``python -m benchmarks.depth_race``), the 9 dense cases of the regime
    benchmark (10 choices between depths, with the verification's refits; costs every 25
    iterations): from iteration 400 on, the depth finally chosen was at most 14.5% above
    depth 2 (before 400, up to 58%: from a near-zero start deeper factors learn more
    slowly), so 0.3 leaves a 2x margin. It stops depth 8 at iteration 400 on Ellis Island
    (42% above depth 2; a quarter less DMF CPU time) and with 30% false edges (270%
    above), and changes no choice. Deep candidates often win by < 0.2% at the end
    (synthetic graphs), so a rule that stops them earlier or closer is not safe."""
    prune_after: int = 400
    """First checkpoint of the candidate race (a multiple of ``check_every``)."""
    prune_every: int = 100
    """Checkpoint spacing of the candidate race (a multiple of ``check_every``); each
    checkpoint costs one Eq. 3 evaluation per running candidate (about 4 ms for 20k
    edges)."""
    iterations: int = 1000
    """Adam iterations at most (fewer when ``tolerance`` stops the fit)."""
    tolerance: float = 5e-4
    """Early stopping: relative change of H per ``check_every`` iterations below which the
    fit counts as converged (``patience`` times in a row, after the warm-up); 0 = run every
    iteration. On Ellis Island the depth-2 fit stops after about 600 of 1000 iterations
    (mean error +0.007 deg); deeper fits converge later and mostly run to the end."""
    dense_product_density: float | None = 0.35
    """CPU: evaluate the loss and its gradient from the whole ``H H^T`` (two 3N x 3N
    matrix products) instead of gathering the observed blocks, when at least this fraction
    of the node pairs carries an edge and there are at most ``dense_product_max_nodes``
    nodes; None: always gather (profile ``paper``). The same loss and gradient to float32
    rounding, and faster on small dense graphs (depth 2, one thread, CPU time per
    iteration dense / gathered): 100 nodes 0.39 at 53% of the pairs observed, 0.45 at 32%;
    227 (Ellis Island) 0.47 at 78%, 0.54 at 54% (filtered), 0.74 at 39%, about 1 at 31%,
    1.10 at 23%; 300 nodes 0.59 at 51%, 0.81 at 34%; 400 nodes 0.8-1.0 at 50%, 1.17 at
    30%, 4.1 at 10%; 1000 nodes 2.3 at 50%. The rounding differences grow over a fit and
    can flip a near-tied depth choice, as another seed does; over seeds 0-3 (with
    ``max_full_width_nodes`` = 0) the errors stayed within the spread between seeds
    (Ellis + 30% mean 4.08 against 4.10 gathered, N = 100/10% median 0.143 against
    0.143; Ellis Island 2.210 / 0.395 against 2.209 / 0.393 at seed 0)."""
    dense_product_max_nodes: int = 300
    """Largest graph for ``dense_product_density``: the 3N x 3N matrices outgrow the CPU
    caches (at 400 nodes the two ways cost the same at 50% observed)."""
    dtype: str = "float32"
    """Torch dtype of the Adam fit (``float32`` or ``float64``). float32 is about twice as
    fast (the full-width factors are memory-bound) and gave the same Ellis Island errors to
    0.002 deg; sparse mode always runs in float64."""
    lr: float = 0.01
    """Initial Adam step size; cosine decay to ``lr * lr_final_ratio``."""
    lr_final_ratio: float = 0.01
    reweighting: bool = True
    """IRLS-style reweighting of Sec. IV-C (ablation (d) turns it off; sparse mode too)."""
    reweight_floor: float | None = 0.1
    """How the reweighting sets the weights (beyond the paper; None: the paper's rule,
    profile ``paper``). The paper multiplies ``w_ij`` by ``tau / r_ij`` where ``r_ij > tau``
    at every reweighting, so an edge above the median residual a few times in a row has
    almost no say, and the fit is an L1 fit of the better half of the edges. With a floor
    ``f``, each reweighting sets ``w_ij = w0_ij * tau / max(r_ij, f * tau)`` afresh from the
    input weights ``w0``: iteratively reweighted L1 towards a log-like loss, every edge
    weighted by its own residual (at most ``1 / f`` times a median edge's weight). See
    docs/method.md ("Reweighting") for the evidence."""
    reweight_every: int = 25
    """lambda: reweight every this many iterations ..."""
    warmup: int = 200
    """lambda_warm: ... after this many warm-up iterations."""
    init_scale: float = 1e-2
    """Entries of the near-zero initial product (a warm start's noise on the hidden
    directions, in sparse mode too)."""
    diagonal_weight: float = 1.0
    """Weight of the |H_i H_i^T - I|_1 terms."""
    check_every: int = 25
    """Early stopping (and the fit's monitor) looks at H every this many iterations."""
    patience: int = 2
    """Converged after this many consecutive checks below ``tolerance``; the fit then
    anneals the step size over ``cooldown`` iterations and stops."""
    cooldown: int = 50
    explicit_constraint: bool = True
    """Rank-3 symmetric H H^T (ablation (c): vanilla 3N x 3N factors + eigendecomposition)."""
    hidden_width: int | None = None
    """Width of the hidden factors; None: :meth:`width_for` decides."""
    max_full_width_nodes: int = 0
    """Graphs of at most this many nodes get the paper's full width 3N (profile ``paper``:
    300); larger ones ``min(3N, scalable_width)``. The width only matters at depth 4 and
    more (depth 2 has no hidden factor). Evidence for 0 (beyond the paper): on the dense
    regime cases below 300 nodes (Ellis Island, + 15%, + 30%, synthetic N = 100 with 10%
    and 50% outliers), seeds 0-3, width 64 gave the same errors as 3N to within the
    spread between seeds (Ellis Island bit-identical, depth 2 chosen; Ellis + 30% mean
    over seeds 4.10 with 3N, 3.95 with 64; N = 100/10%: median 0.143 and 0.144), and cut
    the DMF time by a third or more (Ellis Island solve 6.2 -> 3.9 s): a 3N x 3N factor
    makes every Adam step memory-bound. Against it: Ellis Island in the sample bag's
    arrival order averaged 2.03 / 0.406 deg over seeds 0-3 with 3N and 2.15 / 0.390 with
    64 (a higher mean, a lower median; docs/benchmarks.md, "Bags")."""
    scalable_width: int = 64

    def width_for(self, num_nodes: int) -> int:
        """Hidden width of the factors for a component of ``num_nodes`` nodes."""
        if self.hidden_width is not None:
            return self.hidden_width
        full = 3 * num_nodes
        if num_nodes <= self.max_full_width_nodes:
            return full
        return min(full, self.scalable_width)


@dataclass
class SparseFitOptions:
    """Sparse mode: chordal warm start, entry-wise Huber loss, L-BFGS (chain-like SLAM
    graphs)."""

    mean_degree: float = field(default=10.0, metadata=_flat("sparse_mean_degree"))
    """Mode ``auto`` picks sparse mode when the mean degree 2|E|/N is below this."""
    depths: tuple[int, ...] = field(default=(2,), metadata=_flat("sparse_depths"))
    """Depth candidates. Depth matters through DMF's implicit bias from a near-zero start;
    a warm-started L-BFGS fit of a smooth loss has none, so one is enough."""
    huber_factor: float = 30.0
    """Huber delta = this x median |entry residual| of the chordal start, over the entries
    that carry noise (:func:`~rotavg_ros.core.dmf.sparse.huber_delta`)."""
    rounds: int = field(default=8, metadata=_flat("sparse_rounds"))
    """At most this many L-BFGS runs, with an outlier reweighting between."""
    inner_iterations: int = field(default=300, metadata=_flat("sparse_inner_iterations"))
    """L-BFGS steps per run at most."""
    diagonal_weight: float = field(default=10.0, metadata=_flat("sparse_diagonal_weight"))
    """Weight of the Huber |H_i H_i^T - I| terms."""
    outlier_factor: float = field(default=5.0, metadata=_flat("sparse_outlier_factor"))
    """Edges whose noise-scaled residual exceeds this x the median are down-weighted
    between L-BFGS runs."""
    precondition: bool = field(default=True, metadata=_flat("sparse_precondition"))
    """Depth 2: precondition L-BFGS with the graph Laplacian of the loss's curvature
    (:mod:`rotavg_ros.core.dmf.precondition`; beyond the paper, off in profile ``paper``)."""
    loose_rounds: bool = field(default=True, metadata=_flat("sparse_loose_rounds"))
    """A reweighting round that another follows ends once its L-BFGS stalls
    (:data:`~rotavg_ros.core.dmf.sparse.ROUND_LOOSE_FTOL`) instead of converging fully:
    the next round's weights need the residuals, not the last digits of the fit. The last
    round converges as before. Off in profile ``paper``."""


@dataclass
class WarmStartOptions:
    """Re-solves warm-started from a previous solution (a growing graph)."""

    min_known: float = field(default=0.5, metadata=_flat("warm_min_known"))
    """Warm start only when at least this fraction of a component's nodes is known."""
    iterations: int = field(default=100, metadata=_flat("warm_iterations"))
    """Dense mode: Adam iterations (vs ``DenseFitOptions.iterations`` cold), no warm-up.
    100 was as accurate as 150 (2000 nodes +1% edges: median 0.288 vs 0.291 deg; a
    1000-node stream: 0.369 vs 0.394) in two thirds of the time; 50 lost accuracy."""
    lr: float = field(default=1e-3, metadata=_flat("warm_lr"))
    """Dense mode: initial learning rate."""


@dataclass
class VerifyOptions:
    """Verification after the solve (beyond the paper; :mod:`rotavg_ros.core.robust`): a
    robust re-solve on every input edge with a noise scale estimated from the data, and the
    choice between it and the filtered-DMF solution by a truncated L1 cost over every
    edge."""

    enabled: bool = field(default=True, metadata=_flat("verify"))
    """Run it (the ``paper`` profile turns it off)."""
    initial_threshold_deg: float = field(default=30.0,
                                         metadata=_flat("verify_initial_threshold_deg"))
    """Residual angle of the first GNC-TLS pass, before the noise is known: a random
    rotation is this close to a given one with probability 0.7%, and inlier noise up to
    about 10 deg per edge stays inside it. The noise fit then sets the threshold."""
    max_threshold_deg: float = field(default=90.0, metadata=_flat("verify_max_threshold_deg"))
    """Cap of the fitted inlier threshold (in standardized units, degrees)."""
    rounds: int = field(default=2, metadata=_flat("verify_rounds"))
    """Re-admit / drop rounds with the fitted threshold."""
    robust_first: bool = field(default=True, metadata=_flat("robust_first"))
    """Sparse mode: when the chordal solution shows outliers, run the robust re-solve
    (steps 1-5 of the verification) first and fit the DMF on its inliers only, instead of
    on every edge the filter kept; the choice (step 6) then judges that fit. From a start
    that false closures bent, the fit on every edge ran its whole budget of L-BFGS steps
    for a solution the verification then replaced by a refit on those same inliers."""
    refit_from_resolve: bool = field(default=True, metadata=_flat("refit_from_resolve"))
    """The DMF fits on the edges the verification calls inliers (sparse mode: robust first's
    fit, the refit without the outliers a kept DMF shows; either mode: the refit after the
    re-solve wins) skip the edge filter, and those after a re-solve start from its rotations.
    The re-solve has already judged every edge against the fitted noise; the filter's
    fixed 8.1 deg would drop good edges of a high-noise graph again (parking-garage at
    5 deg: 1,057 of 6,274), and a fit from its own chordal start can settle far off (at
    20 deg: 44-70 deg median against the re-solve's 21-24). The first two stay filtered
    and cold where the re-solve's residuals look Gaussian
    (:data:`~rotavg_ros.core.robust.noise.GAUSSIAN_SHAPE`): least squares is the better
    estimator there. In dense mode the refit after the re-solve started filtered and cold
    until 2026-12-02: on a clean dense graph at 5 deg folded noise the filter removed a
    third to a half of the true edges, the DMF on the rest lost to the re-solve, and so did
    its refit (150 nodes: least squares' 0.95 deg median; now 0.56). Off: the filtered
    refit from the fit's own start (as before)."""
    least_squares_where_gaussian: bool = field(
        default=True, metadata=_flat("least_squares_where_gaussian"))
    """Sparse mode, robust first: where the re-solve's standardized inlier residuals look
    Gaussian (:data:`~rotavg_ros.core.robust.noise.GAUSSIAN_SHAPE`), the re-solve (least
    squares on its inliers) is the answer and no DMF is fitted on those inliers. There the
    choice keeps the re-solve unless the DMF's cost is 2% lower, and over four draws of the
    regime benchmark (seeds 0 and 1, folded and tangent noise) it kept the re-solve every
    time (35 of 35 solves; the rotations are bit-identical with the option on and off); the
    fit, cold from the chordal start, ran its whole budget of L-BFGS steps on a 3,000-keyframe
    chain (6.0 s, against 0.67 s without it). The same where the inliers' redundancy is
    below ``least_squares_below_redundancy``. Off: the fit runs and the choice judges it."""
    least_squares_below_redundancy: float = field(
        default=0.15, metadata=_flat("least_squares_below_redundancy"))
    """With ``least_squares_where_gaussian``: the re-solve is also the answer where the mean
    redundancy of its inliers, ``(m - n + 1) / m`` (one minus the mean leverage), is below
    this, whatever the residuals' shape: an odometry chain with sparse loop closures
    (0.03-0.13 on the regime benchmark's chains and revisited routes; SLAM grids 0.42-0.74,
    view graphs 0.75-0.93). There an L1 fit cannot use noise peaked at zero, and it puts
    each loop's misclosure on a few edges instead of spreading it along the loop: on a route
    driven three times with its closures in 12 runs (redundancy 0.09-0.13), the kept DMF's
    median was 0.3-24% above the re-solve's on 5 of 6 draws (clean, and with 20% false
    closures) and 10% below on one, and a geodesic L1 fit of the true edges was 12-62% above
    least squares' on 3 of 3. With 24 runs (0.19-0.21) the DMF was the better on 2 of 3
    draws; on random-closure chains the two agree. Where the DMF is fitted first (the
    node's warm solves, graphs whose chordal solution shows no outlier) the choice compares
    it with the re-solve by their truncated squares there, not by the L1 cost, and no DMF
    refit replaces a re-solve that stands. 0 turns this off. The same bound marks the graphs
    (with odometry) on which the re-solve always runs its tight pass with the pairwise
    closure test (:func:`~rotavg_ros.core.robust.verify.robust_resolve`), whatever
    ``least_squares_where_gaussian``: there a few false closures can bend the fit until none
    shows as an outlier."""
    l1_by_cross_validation: bool = field(default=True,
                                         metadata=_flat("l1_by_cross_validation"))
    """Sparse mode, on graphs of at most ``l1_max_nodes`` nodes whose inliers' redundancy
    is at least ``least_squares_below_redundancy``: the kept solution, or the L1 fit of the
    inliers where 10-fold cross-validation says it predicts held-out inliers better
    (:mod:`rotavg_ros.core.robust.l1_choice`). Least squares is the better estimator under
    Gaussian noise, L1 under noise peaked at zero. On the regime benchmark (seeds 0, 5, 6
    folded, 0 tangent) it chose L1 on the smallGrid3D and sparse view-graph cases under
    folded noise (medians 1-30% lower but on two cases, at most 2.3% higher), least squares
    on every case under tangent noise and on real/smallGrid3D, whose reference is the
    least-squares optimum (docs/method.md, verification step 9). Where leaving out a fold
    would split the inliers (odometry runs that are bridges: parking-garage, sphere2500,
    torus3D), a spanning tree stays in every fold's fit and the alternative is a Huber fit
    instead of L1 (``+huber``; before, no verdict there). Where the kept solution is a robust
    fit (more than 1% above the least-squares optimum's cost), least squares' optimum
    replaces it where least squares wins (``+ls``), Huber's fit where Huber wins (a pose
    graph's DMF fit is least squares in the bulk), and it stands where L1 wins. Off: the
    kept solution stands."""
    l1_over_robust_with_odometry: bool = field(
        default=True, metadata=_flat("l1_over_robust_with_odometry"))
    """Where ``l1_by_cross_validation``'s verdict is L1 (the folds keep no tree) and the
    kept solution is a robust fit, on a graph with odometry (a pose graph): Huber's fit of
    the inliers replaces it, as where the folds keep a tree (a pose graph's sparse DMF fit
    is least squares in the bulk, so a verdict for L1 over least squares speaks against it
    too; Huber averages the bulk and caps the tails, where the L1 fit was 18.7% worse on
    one weighted draw). Off, or on a graph without odometry (a view graph, whose sparse DMF
    fit reweighted towards L1 and beat the L1 fit): the robust fit stands, as until
    2026-12-05. On, over the stress draws measured: 7 medians lower by 4-22%
    (heteroscedastic sphere2500 2.02 -> 1.57 deg at seed 76), 1 higher by 4.8% (weighted
    sphere2500 at seed 20), every record case bit for bit the same (docs/benchmarks.md,
    "Huber over a pose graph's robust fit, where L1 wins")."""
    huber_where_weights_differ: bool = field(
        default=True, metadata=_flat("huber_where_weights_differ"))
    """Where ``l1_by_cross_validation``'s verdict is L1 over a least-squares-like solution
    and the edges' weights differ (the input's information weights, or the odometry's
    weight from ``class_noise``, tell each edge's noise scale): Huber's fit of the inliers
    in place of the L1 fit. L1 gains where the noise scale differs from edge to edge and
    the weights do not say so (odometry at 0.5 deg and loop closures at 3 deg, every weight
    1: L1's fit of the true edges below Huber's on 14 of 15 L1 verdicts, by 1-32%); where
    the weights say it, Huber's fit, least squares in the bulk, was the lower on 22 of 24
    (the same measurements weighted, smallGrid3D and sphere2500, folded and anisotropic
    noise; median -8%). In the solver, over 140 stress graphs with weights or
    heteroscedastic noise at ten draws: 8 medians lower by 3-17%, 2 higher (+2.1%,
    +10.6%), the rest the same. Off: the L1 fit, as until 2026-12-05 (docs/benchmarks.md,
    "Weighted graphs: Huber where L1 wins")."""
    cauchy_where_decided: bool = field(default=True, metadata=_flat("cauchy_where_decided"))
    """Where ``l1_by_cross_validation``'s verdict is L1 or Huber: a second cross-validation
    on the same folds pits Cauchy's redescending estimator against that fit, and Cauchy's
    fit of the inliers replaces the answer where the folds decide for it early (the t-test
    that stops the first one early; never on a sum over all folds): noise whose level
    differs from edge to edge, unreported. Heteroscedastic parking-garage (lognormal
    levels about 3 deg), 22 draws, folded and tangent: 9 medians lower by 5-32%, 4 higher
    by 3-13%, 9 the same; the regime record at three seeds, stress draw 0 (folded and
    tangent, but that graph), City10000 regenerated and the new-user chains the same
    (docs/benchmarks.md, "Cauchy where the folds decide for it"). Off: as until
    2026-12-07."""
    settle_parallel: bool = field(default=True, metadata=_flat("settle_parallel"))
    """Where a node pair is measured more than once and its measurements disagree (the view
    graph's ``merge`` policy averages them into one edge between them): after the solve,
    set aside those that disagree with the solution where others of the pair agree, and
    solve again (:mod:`~rotavg_ros.core.robust.parallel_measurements`; a front end that
    sends two hypotheses for one pair); pairs it cannot settle are withheld from one more
    solve and judged against it. Nothing runs where no pair is measured twice; one more
    solve where measurements are set aside, two where a pair is undecided. Off: the merged
    edge stands, as until 2026-12-08."""
    halfway_where_tied: bool = field(default=True, metadata=_flat("halfway_where_tied"))
    """Where ``l1_by_cross_validation``'s verdict is the alternative (L1 or Huber) but all
    ten folds ran and their t statistic stays inside Student's two-sided 95% band (a tie,
    ``l1_choice.TIE_QUANTILES``): the answer is the geodesic midpoint of the alternative's
    fit and least squares' optimum (``+l1-halfway``, ``+huber-halfway``). On 72 fresh
    clean smallGrid3D draws (5 and 10 deg, three noise models) it acted on 21: medians
    more than 5% above GTSAM chordal's 4 -> 0 (the L1 fit up to 1.11x, the midpoint up to
    1.02x), folded noise's 9 ties 3% above L1's fit at the geometric mean, still below
    chordal's; over six record and six stress draws 38 medians moved, 23 lower, 15
    higher by at most 5.6% (docs/benchmarks.md, "Halfway where the folds tie"). Off: the
    alternative's fit, as until 2026-12-07."""
    l1_max_nodes: int = field(default=10000, metadata=_flat("l1_max_nodes"))
    """Largest graph that ``l1_by_cross_validation`` runs on. It costs 100-320 Gauss-Newton
    steps on the inliers (3-10 folds), each as costly as one of the verification's: about
    as much again as the solve (125 nodes 0.1 s; sphere2500 0.4-1.1 s; a random 3,000-node
    graph of mean degree 6, whose factorizations fill in, 14.8 s beside a 20.7 s solve).
    Until 2026-12-02 it was 2,000 nodes; at 10,000 (the scale target's size) the
    cross-validation also reaches sphere2500, where over seeds 0, 5, 6, 7 it chose L1 on 10
    of the 12 folded-noise cases (medians 3.7-13% lower but on one case, 6.7% higher), least
    squares on the real graph and under tangent noise (docs/benchmarks.md, "An L1
    refinement?")."""
    refit_where_folds_replace: bool = field(default=False,
                                            metadata=_flat("refit_where_folds_replace"))
    """Sparse mode, where ``l1_by_cross_validation`` runs with a spanning tree in every fold
    (pose graphs whose odometry runs are bridges): its verdict puts least squares' optimum
    or Huber's fit of the inliers in place of any robust fit, so the DMF refits
    (``refit_readmitted``, the refit on the re-solve's inliers) are skipped there and least
    squares of the inliers takes their place (off, the default). On: they run, as until
    2026-12-05 (heteroscedastic parking-garage: 11.7 of a 17 s solve, for a fit that was
    then replaced; docs/benchmarks.md, "Refits the folds replace")."""
    dmf_where_folds_replace: bool = field(default=True,
                                          metadata=_flat("dmf_where_folds_replace"))
    """Sparse mode, robust first: fit the DMF on the re-solve's inliers even where the
    cross-validation will keep a spanning tree in its folds (on, the default). Off: the
    re-solve is kept there without a DMF fit, whose only say left is which inliers the
    choice keeps. Off, on 175 solves (record folded seeds 0 and 5, tangent 0; stress
    folded 73, tangent 74; 2026-12-05): 165 the same to 0.1%, heteroscedastic noise 0.1-2.5%
    higher on all four such graphs, five others lower (weighted torus3D 16%, where the
    cross-validation's verdict changed), pose-graph solves up to 3x faster (heteroscedastic
    torus3D 13.3 -> 4.3 s). A regime made worse: on stays (docs/benchmarks.md, "Refits the
    folds replace")."""
    refit_readmitted: bool = field(default=True, metadata=_flat("refit_readmitted"))
    """Dense mode: where the DMF solution is kept but more than a third of the edges the
    verification calls inliers (``solver.DENSE_UNFITTED_SHARE``) were not in its fit (the
    filter removed them and the verification re-admitted them), a short DMF fit
    warm-started from it on those inliers (the warm re-solve's: depth 2,
    ``warm_iterations`` steps, no filter) replaces it unless its cost is higher. Sparse
    mode: the same where the re-admitted edges are more than ``solver.READMITTED_SHARE``
    (5%) of its fit's, by sparse mode's refit without outliers (kept unless its cost is 2%
    higher). Off: the kept solution stands as fitted."""
    odometry: str = field(default="auto", metadata=_flat("odometry"))
    """Which edges are odometry, trusted as inliers by the re-solve and never capped in the
    choice cost: ``consecutive`` (nodes adjacent in the graph's sequence, e.g.
    consecutive keyframes: their ids' natural order, integers by value and names with
    their digits read as numbers, where that chains more nodes than the order they were
    first added, else that order; where neither chains 90% of the nodes, the graph's own
    paths of nodes of degree at most two; :mod:`~rotavg_ros.core.node_sequence`), ``none``, or
    ``auto`` (consecutive, when they chain at least 90% of the nodes of a graph that joins
    at most half its node pairs: a trajectory, however often revisited, not a near-complete
    view graph whose ids chain by accident; else none). A SLAM front end's
    odometry is rarely wrong, and a group of consistent false closures can outvote the few
    edges that cross a weakly connected part of the graph, unless those edges are trusted.
    Rarely is not never: a step that is a jump (far above the usual step) where the loop
    closures across it are rejected, or where jumps are rare, or that a fit leaves far off,
    is judged as any edge where that explains the data better
    (:mod:`~rotavg_ros.core.robust.odometry_breaks`; diagnostic
    ``distrusted_odometry_edges``)."""
    class_noise: bool = field(default=True, metadata=_flat("class_noise"))
    """Where the weights do not tell the odometry (``odometry``) from the loop closures (the
    same median weight in both: a front end that reports no covariances, pairs measured
    twice merged at weight 2): estimate one noise scale for the odometry and
    one for the loop closures from the solution's inliers (variance components,
    :mod:`rotavg_ros.core.robust.class_noise`) and, where they differ beyond doubt, solve
    again with the odometry weighted by their ratio. A front end's odometry is usually far
    more precise than its loop closures; with equal weights least squares spreads each
    loop's misclosure over both alike (parking-garage, odometry at 0.5 deg and closures at
    3 deg, unweighted: 2.55 -> 1.38 deg median; docs/benchmarks.md). Weights that differ
    between the classes are trusted as they are. Off: the weights stay as given."""
    odometry_bias: bool = field(default=True, metadata=_flat("odometry_bias"))
    """On an odometry chain with sparse loop closures (``odometry``; the redundancy of all
    its edges below ``least_squares_below_redundancy``) with at least 8 closures on one
    unbroken piece of it: estimate a systematic bias of the odometry (one rotation a step,
    in the step's first frame: a gyro's bias) from the loops the closures close over it,
    and remove it from every odometry measurement before the solve where the loops show it
    beyond the odometry's own drift, in both halves of the trajectory (a generalized least
    squares over the odometry the loops share; :mod:`rotavg_ros.core.robust.odometry_bias`;
    diagnostic ``odometry_bias_deg_per_step``). A bias makes the loop errors grow with the loop's
    length, where the loop tests assume a random walk's square root, and they reject true
    closures (chains of 1,000-3,000 keyframes at 0.5-1 deg a step: up to 70 deg mean error
    without it; docs/benchmarks.md). Off: the odometry stays as measured."""


@dataclass
class RuntimeOptions:
    """Where and how the solve runs; none of these changes the method."""

    seed: int = 0
    """Random seed; the fit of depth d uses ``seed + d``."""
    device: str = "cpu"
    """Torch device: ``cpu``, ``cuda`` (or ``cuda:N``), or ``auto`` (CUDA when available)."""
    cuda_graphs: bool = True
    """CUDA, dense mode: record each fit's Adam step once as a CUDA graph and replay it
    (its ~40 small kernels otherwise cost more to launch than to run), and fit the depth
    candidates in parallel threads, each on its own stream."""
    threads: int | None = None
    """CPU threads for the solve: torch's, split among the depth candidates fitted in
    parallel, and the verification's GNC re-solves from different starts, run side by
    side on graphs of ``PARALLEL_MIN_EDGES`` edges or more (:mod:`rotavg_ros.core.threads`;
    the same results). None: one thread per candidate, as many candidates at once as there
    are CPUs (robust when the CPU is shared; see ``depth_choice._thread_plan``), and as many
    re-solves."""
    progress: ProgressFn | None = field(default=None, repr=False, compare=False)
    """Called with a line of text at each stage (None: quiet)."""


_GROUPS: dict[str, type] = {
    "filter": FilterOptions,
    "dense": DenseFitOptions,
    "sparse": SparseFitOptions,
    "warm": WarmStartOptions,
    "verify": VerifyOptions,
    "runtime": RuntimeOptions,
}

PROFILES: dict[str, dict[str, Any]] = {
    "default": {},
    "paper": {"verify": False, "prune_ratio": None, "sparse_precondition": False,
              "sparse_loose_rounds": False,
              "max_full_width_nodes": 300, "dense_product_density": None,
              "reweight_floor": None, "bracket_depths": False},
}
"""Named option sets by flat name. ``paper`` is Algorithm 1 and the DMF of the paper to the
letter (with our documented tie rule): every depth candidate runs to the end, with the
full hidden width 3N up to 300 nodes and the loss gathered over the observed blocks;
``default`` adds the verification stage, reweights every edge afresh by its own residual,
fits the shallowest and the deepest depth candidate only and stops one that has clearly
lost, uses hidden width ``min(3N, 64)`` and, on small dense graphs, the whole-matrix
loss."""


@dataclass
class SolverOptions:
    """Every knob of the filtered-DMF pipeline, one options object per stage; the defaults
    (the measured choices) are those of the stage classes."""

    mode: str = "auto"
    """``dense``: the paper's DMF (near-zero init, entry-wise L1, Adam, Sec. IV-C
    reweighting). ``sparse``: chordal warm start, entry-wise Huber, L-BFGS (for chain-like
    SLAM graphs). ``auto``: sparse when the mean degree 2|E|/N < ``sparse.mean_degree``."""
    filter: FilterOptions = field(default_factory=FilterOptions)
    dense: DenseFitOptions = field(default_factory=DenseFitOptions)
    sparse: SparseFitOptions = field(default_factory=SparseFitOptions)
    warm: WarmStartOptions = field(default_factory=WarmStartOptions)
    verify: VerifyOptions = field(default_factory=VerifyOptions)
    runtime: RuntimeOptions = field(default_factory=RuntimeOptions)

    @classmethod
    def for_profile(cls, profile: str = "default", **values: Any) -> SolverOptions:
        """The options of a named profile (:data:`PROFILES`), then ``values`` by flat name.
        Raises :class:`~rotavg_ros.errors.InputError` for an unknown profile."""
        if profile not in PROFILES:
            raise InputError(f"invalid solver option: profile must be one of "
                             f"{', '.join(PROFILES)}, got {profile!r}")
        return cls.from_flat(**{**PROFILES[profile], **values})

    # ------------------------------------------------------------ flat names
    @classmethod
    def from_flat(cls, **values: Any) -> SolverOptions:
        """Options from flat names (``sigma=0.3, sparse_rounds=4, seed=1``); the others keep
        their defaults. Raises ``TypeError`` for an unknown name."""
        return cls().replace_flat(**values)

    def replace_flat(self, **values: Any) -> SolverOptions:
        """A copy with the options named by flat name changed (``TypeError`` for an unknown
        name); the stage objects are copied, never shared with ``self``."""
        unknown = sorted(set(values) - set(FLAT_NAMES))
        if unknown:
            raise TypeError(f"unknown solver option(s): {', '.join(unknown)}")
        changes: dict[str, dict[str, Any]] = {group: {} for group in _GROUPS}
        for name, value in values.items():
            group, attr = FLAT_NAMES[name]
            if group:
                changes[group][attr] = value
        return SolverOptions(
            mode=values.get("mode", self.mode),
            **{group: dataclasses.replace(getattr(self, group), **changes[group])
               for group in _GROUPS},
        )

    def flat(self) -> dict[str, Any]:
        """Every option by its flat name."""
        return {name: getattr(getattr(self, group), attr) if group else getattr(self, attr)
                for name, (group, attr) in FLAT_NAMES.items()}

    # ------------------------------------------------------------ validation
    def validate(self) -> None:
        """Raise :class:`~rotavg_ros.errors.InputError` (a ``ValueError``) naming the first
        option (by its flat name) whose value cannot work.

        Checks ranges only (no device probing: an unavailable CUDA device is reported
        when the solve starts).
        """
        reason = next(_problems(self.flat()), None)
        if reason is not None:
            raise InputError(f"invalid solver option: {reason}")


def _flat_names() -> dict[str, tuple[str, str]]:
    names: dict[str, tuple[str, str]] = {"mode": ("", "mode")}
    for group, cls in _GROUPS.items():
        for f in dataclasses.fields(cls):
            names[f.metadata.get("flat", f.name)] = (group, f.name)
    return names


FLAT_NAMES: Mapping[str, tuple[str, str]] = _flat_names()
"""Flat option name -> ``(stage attribute of SolverOptions, field)``; ``mode`` -> ``("",
"mode")``."""


def _problems(o: Mapping[str, Any]) -> Iterator[str]:
    """What is wrong with the flat options ``o``, first problem first."""
    if o["mode"] not in ("auto", "dense", "sparse"):
        yield f"mode must be auto, dense or sparse, got {o['mode']!r}"
    for name in ("depths", "sparse_depths"):
        depths = o[name]
        if not depths or any(not _is_int(d) or d < 2 or d % 2 for d in depths):
            yield f"{name} must be a non-empty list of even integers >= 2, got {depths!r}"
    for name in ("iterations", "warm_iterations", "reweight_every", "sparse_rounds",
                 "sparse_inner_iterations", "verify_rounds"):
        if not _is_int(o[name]) or o[name] < 1:
            yield f"{name} must be an integer >= 1, got {o[name]!r}"
    floor = o["reweight_floor"]
    if floor is not None and not (_positive(floor) and floor <= 1.0):
        yield f"reweight_floor must be None or in (0, 1], got {floor!r}"
    if o["prune_ratio"] is not None and not _positive(o["prune_ratio"]):
        yield f"prune_ratio must be None or a finite number > 0, got {o['prune_ratio']!r}"
    check, every, after = o["check_every"], o["prune_every"], o["prune_after"]
    if not _is_int(check) or check < 1:
        yield f"check_every must be an integer >= 1, got {check!r}"
    elif not _is_int(every) or every < 1 or every % check:
        yield f"prune_every must be a positive multiple of check_every ({check}), got {every!r}"
    elif not _is_int(after) or after < 0 or after % check:
        yield (f"prune_after must be an integer >= 0 and a multiple of check_every ({check}), "
               f"got {after!r}")
    for name in ("warmup", "max_full_width_nodes", "dense_product_max_nodes"):
        if not _is_int(o[name]) or o[name] < 0:
            yield f"{name} must be an integer >= 0, got {o[name]!r}"
    for name in ("lr", "warm_lr", "init_scale", "sigma", "huber_factor",
                 "sparse_outlier_factor", "verify_initial_threshold_deg",
                 "verify_max_threshold_deg"):
        if not _positive(o[name]):
            yield f"{name} must be a finite number > 0, got {o[name]!r}"
    if o["sigma_untested"] is not None and not _positive(o["sigma_untested"]):
        yield f"sigma_untested must be None or a finite number > 0, " \
              f"got {o['sigma_untested']!r}"
    for name in ("tolerance", "sparse_mean_degree", "sparse_diagonal_weight"):
        value = o[name]
        if not (_is_number(value) and math.isfinite(value) and value >= 0):
            yield f"{name} must be a finite number >= 0, got {value!r}"
    if not (_is_number(o["warm_min_known"]) and 0.0 <= o["warm_min_known"] <= 1.0):
        yield f"warm_min_known must be in [0, 1], got {o['warm_min_known']!r}"
    if o["dense_product_density"] is not None and not (
            _is_number(o["dense_product_density"]) and 0.0 <= o["dense_product_density"] <= 1.0):
        yield (f"dense_product_density must be None or in [0, 1], "
               f"got {o['dense_product_density']!r}")
    if o["dtype"] not in ("float32", "float64"):
        yield f"dtype must be float32 or float64, got {o['dtype']!r}"
    if o["hidden_width"] is not None and (not _is_int(o["hidden_width"])
                                          or o["hidden_width"] < 3):
        yield f"hidden_width must be None or an integer >= 3 (H has rank 3), " \
              f"got {o['hidden_width']!r}"
    if not _is_int(o["scalable_width"]) or o["scalable_width"] < 3:
        yield f"scalable_width must be an integer >= 3 (H has rank 3), " \
              f"got {o['scalable_width']!r}"
    if o["threads"] is not None and (not _is_int(o["threads"]) or o["threads"] < 1):
        yield f"threads must be None or an integer >= 1, got {o['threads']!r}"
    if not _DEVICE.fullmatch(str(o["device"])):
        yield f"device must be cpu, cuda, cuda:N or auto, got {o['device']!r}"
    if not _is_int(o["seed"]) or o["seed"] < 0:
        yield f"seed must be an integer >= 0, got {o['seed']!r}"


_DEVICE = re.compile(r"cpu|auto|cuda(:\d+)?")


def _is_int(value: object) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _is_number(value: object) -> TypeGuard[float]:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, bool)


def _positive(value: object) -> bool:
    return _is_number(value) and math.isfinite(value) and value > 0
