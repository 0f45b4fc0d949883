"""Odometry steps that the loop closures across them disagree with: suspects of a break.

A front end that loses its track can report one wrong odometry step. Trusted, that step
turns every node after it, and the re-solve rejects the true loop closures across it
instead (``regime_stress``'s 1,000-keyframe chain with 36 true closures and two wrong
steps, seed 0: 50.9 deg mean error). The suspects:

- **Jumps the closures point at.** A closure ``(a, b)``, ``a < b``, both ends on one
  unbroken piece of the odometry, spans the step ``(m, m + 1)`` when ``a <= m < b``: the
  loop it closes over the odometry runs through that step. The closures point at a step
  where the fit that trusts the odometry rejects at least ``MIN_REJECTED_ACROSS`` of those
  spanning it and keeps fewer than one in ``REJECTED_PER_KEPT`` of them. Random false
  closures are rejected wherever they lie, a minority among the closures across any step;
  a wrong step has the closures across it all rejected. But the closures cannot tell
  which step between their ends broke (cutting any of them fits them alike), and a group
  of consistent false closures points the same way at true steps. So of the steps pointed
  at, only the jumps are suspects: a measured rotation far above the odometry's usual
  step (``JUMP_MADS`` robust spreads above the median angle), a track lost and found
  again, not a keyframe's usual motion.
- **Rare jumps.** Where at most ``RARE_JUMPS`` of the steps, or ``RARE_JUMPS_AT_LEAST``,
  are jumps, every jump: the fit that trusts several wrong steps can keep the closures
  that their combined turns happen to fit, and point at none; and on a short chain, the
  few closures across a wrong step bend the trusted odometry until too few of them are
  rejected to point at it.
- **Jumps a fit without trust left out** (:func:`left_out_jumps`). The first pass of the
  verification judges the odometry as any other edge, from several starts; a jump that one
  of them left out is pointed at by the data as a whole, not by the closures across it
  alone. On a route driven twice the closures across a wrong step are those of the other
  pass too: the fit that trusts the step leaves out one run of them and bends the rest, and
  no step is pointed at (a car's route, one wrong step of 101 deg among 76 true turns:
  21.4 deg mean error against the oracle's 3.4, where the first pass from the spanning tree
  had left out exactly that step); a step left out that is no jump counts on the jump
  beside it that no kept closure tells it from. Cutting one must pay for itself as a
  misfit's cut does, but the one run of closures it frees is evidence enough. They are
  tried first; a pass that cuts none of them, or that the break test refuses, gives way
  to the pass without them (:func:`~.verify.robust_resolve`).
- **Steps a fit leaves far off** (``misfit``, the caller's tests). Step 3 of the
  verification judges the odometry as any other edge; a step it leaves outside by more
  than the initial threshold is suspect (a graph whose steps are no smaller than its
  jumps, smallGrid3D, has no jump to point at). So is a step that the fit trusting the
  odometry leaves beyond its own threshold: trusted edges are never rejected, and where
  many closures cross a wrong step least squares bends the step itself.

A suspect is only that: the verification re-solves with the suspects as ordinary edges and
keeps that fit only where it explains the data clearly better
(:func:`~.verify.robust_resolve`), and where no step it cuts leaves nodes hanging by it
against one run of closures alone (:func:`hanging_steps`): one piece of evidence against one
step that nothing else checks, perceptual aliasing as well as a lost track. Such a step
stands, unless its size alone is evidence of a lost track (:func:`outsized_steps`: a rare
jump, or one far above the route's other turns) or a first-pass fit left it out; the
verification says it kept it unchecked. Where no loop closure that fit keeps ends between a
suspect it cut and a jump it kept, the closures cannot tell the two cuts apart, and the fit
leaves out the jump instead (:func:`cuts_onto_jumps`): a cut that is only a misfit costs
more in that comparison than a jump's.

Conventions: odometry edges join consecutive node indices; ``R_ij ~= R_i R_j^T``.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from rotavg_ros.core.robust.closure_runs import independent_pieces
from rotavg_ros.core.so3 import rotation_angle
from rotavg_ros.core.types import BoolArray, FloatArray, IntArray

MIN_REJECTED_ACROSS = 3
"""A step is suspect by its closures when at least this many closures across it are
rejected (fewer: one or two false closures, which no step explains)."""

REJECTED_PER_KEPT = 3.0
"""... and the rejected ones are at least this many times the kept ones plus one."""

RARE_JUMPS = 0.01
"""Where at most this share of the odometry steps are jumps, every jump is suspect: the
closures across a wrong step need not all be rejected (several wrong steps on a route
driven three times: a fit keeps the closures that their combined turns happen to fit).
On a short chain ``RARE_JUMPS_AT_LEAST`` stands instead."""

RARE_JUMPS_AT_LEAST = 3
"""Jumps are rare where they are at most this many, whatever the chain's length: on a
50-keyframe chain with 8 true closures, seven of them across one wrong step, least squares
bent the trusted odometry to them and rejected three, too few to point at it (25.7 deg mean
against the oracle's 1.7), where below 100 steps no jump was rare. The issue's new-user
chains with N wrong steps (``benchmarks.short_chains --broken-steps N``), medians above
1.5x the oracle's: N = 1, 229 of 778 without the floor, 77 with a floor of 1, 2 or 3;
N = 2, 197 of 392 with a floor of 1, 83 with 2 or 3; N = 3, 212 of 392 with a floor of 2,
108 with 3. The same chains without a wrong step, the stress chains and the regime record:
the same with any of these floors."""

MIN_SPREAD = np.radians(1.0)
"""Floor of the robust spread of the steps' angles, radians: where most steps are exactly
alike (noise-free straight driving) the median absolute deviation is zero, and every step
above the median would be a jump."""

JUMP_MADS = 5.0
"""A step is a jump when its measured rotation angle exceeds the odometry's median step
angle by this many robust spreads (1.4826 median absolute deviations)."""


@dataclass(frozen=True)
class OdometrySuspects:
    """The odometry edges suspect of a break (module docstring)."""

    edges: BoolArray
    """Every suspect."""
    jumps: BoolArray
    """The suspects that are jumps pointed at or rare (:func:`odometry_jumps`): evident
    enough that cutting one needs no more than its own cap
    (:func:`~.verify._breaks_explain_more`)."""
    left_out: BoolArray | None = None
    """The other suspects that are jumps a fit without trust left out
    (:func:`left_out_jumps`): cutting one must pay for itself, but one run of the closures
    it frees is evidence enough. None: no such suspect."""

    def trusting(self, steps: BoolArray) -> OdometrySuspects:
        """These suspects less the ``steps`` (trusted again)."""
        left_out = None if self.left_out is None else self.left_out & ~steps
        return OdometrySuspects(self.edges & ~steps, self.jumps & ~steps, left_out)

    def with_left_out(self, left_out: BoolArray) -> OdometrySuspects:
        """These suspects and the ``left_out`` jumps that are not among them yet."""
        new = left_out & ~self.edges
        return OdometrySuspects(self.edges | new, self.jumps, new)


def suspect_odometry(num_nodes: int, i: IntArray, j: IntArray, R: FloatArray,
                     odometry: BoolArray, inlier: BoolArray, misfit: BoolArray,
                     ) -> OdometrySuspects:
    """The odometry edges suspect of a break (module docstring): those ``misfit`` (the
    caller's residual tests), the jumps (:func:`odometry_jumps`) among the steps the
    closures across them point at (rejected, ``~inlier``, by a fit that trusted the
    odometry), and every jump where jumps are rare (at most ``RARE_JUMPS`` of the steps, or
    ``RARE_JUMPS_AT_LEAST``)."""
    jump = odometry_jumps(R, odometry)
    # Only a closure whose ends lie on one unbroken piece of the odometry closes a loop over
    # the steps between them (two sessions: a closure between them crosses no step).
    linked = np.zeros(num_nodes, bool)  # linked[k]: k -- k+1 is odometry
    linked[np.minimum(i[odometry], j[odometry])] = True
    piece = np.concatenate([[0], np.cumsum(~linked[:-1])])
    a_all, b_all = np.minimum(i, j), np.maximum(i, j)
    closure = ~odometry & (piece[a_all] == piece[b_all])
    a, b = a_all[closure], b_all[closure]
    kept = inlier[closure]
    # Closures across step m (a <= m < b), rejected and kept: difference arrays over m.
    rejected_across = _count_across(a[~kept], b[~kept], num_nodes)
    kept_across = _count_across(a[kept], b[kept], num_nodes)
    broken = ((rejected_across >= MIN_REJECTED_ACROSS)
              & (rejected_across >= REJECTED_PER_KEPT * (kept_across + 1)))
    pointed_jumps = odometry & broken[np.minimum(i, j)] & jump
    jumps = pointed_jumps | (jump & _rare(jump, odometry))
    return OdometrySuspects((odometry & misfit) | jumps, jumps)


def left_out_jumps(i: IntArray, j: IntArray, R: FloatArray, odometry: BoolArray,
                   fits: Iterable[BoolArray]) -> BoolArray:
    """The jumps (:func:`odometry_jumps`) that a fit left out, of the ``fits`` (the inliers
    of fits that judged the odometry as any other edge) that left out few steps: at most
    ``RARE_JUMPS`` of them, or ``RARE_JUMPS_AT_LEAST``, as a lost track breaks few. A fit
    that leaves out more is lost itself (a route driven twice, two wrong steps, 20% false
    closures: a first pass 100 deg off left out 18 steps, three of them true turns, and
    cutting two of those doubled the mean error). A step left out that is no jump counts on
    the kept jump beside it that no kept closure tells it from (:func:`cuts_onto_jumps`):
    the fit could as well have cut there (a wrong step of 157 deg, the cut eight keyframes
    on, at a 3 deg step)."""
    jump = odometry_jumps(R, odometry)
    step_from = _steps_from(int(max(i.max(initial=-1), j.max(initial=-1))) + 1, i, j,
                            odometry)
    out = np.zeros(R.shape[0], bool)
    for inlier in fits:
        if not _rare(odometry & ~inlier, odometry):
            continue
        kept = inlier.copy()  # each move below cuts the jump instead, in ``kept``
        for _ in _moves_onto_jumps(i, j, odometry, kept, odometry & ~inlier & ~jump, jump,
                                   step_from):
            pass
        out |= odometry & ~kept
    return jump & out


def rare_jumps(R: FloatArray, odometry: BoolArray) -> BoolArray:
    """The jumps (:func:`odometry_jumps`) where they are rare (at most ``RARE_JUMPS`` of the
    steps, or ``RARE_JUMPS_AT_LEAST``), else none: where large steps are common, a step's
    size alone says nothing of a lost track (a car turning at corners between sparse
    keyframes, one step in ten; parking-garage's own trajectory, 422 of its 1,660 steps)."""
    jump = odometry_jumps(R, odometry)
    return jump & _rare(jump, odometry)


def common_jumps(R: FloatArray, odometry: BoolArray) -> BoolArray:
    """The jumps (:func:`odometry_jumps`) where they are common, else none: the
    complement of :func:`rare_jumps` among the jumps (a car's turns)."""
    jump = odometry_jumps(R, odometry)
    return jump & (not _rare(jump, odometry))


def outsized_steps(R: FloatArray, odometry: BoolArray) -> BoolArray:
    """The steps whose size alone is evidence of a lost track: the jumps where they are
    rare (:func:`rare_jumps`), and where they are common, the jumps far above the others
    (their angle ``JUMP_MADS`` robust spreads above the jumps' median: a car's turns of
    11-90 deg a step, parking-garage's of 20 deg typically, a wrong step of 140 deg). A turn
    like the route's others (the Manhattan world's 90 deg turns) is not one."""
    angle = rotation_angle(R)
    jump = _far_above(angle, odometry)  # (odometry_jumps, the angles computed once)
    if _rare(jump, odometry):
        return jump
    return _far_above(angle, jump)


def _far_above(angle: FloatArray, among: BoolArray) -> BoolArray:
    """The ``among`` edges whose ``angle`` exceeds their median by ``JUMP_MADS`` robust
    spreads (1.4826 median absolute deviations, at least ``MIN_SPREAD``)."""
    if not among.any():
        return np.zeros(angle.shape[0], bool)
    values = angle[among]
    median = float(np.median(values))
    spread = max(1.4826 * float(np.median(np.abs(values - median))), MIN_SPREAD)
    return among & (angle > median + JUMP_MADS * spread)


def _rare(steps: BoolArray, odometry: BoolArray) -> bool:
    """Whether the ``steps`` are rare among the ``odometry`` ones (:data:`RARE_JUMPS`,
    :data:`RARE_JUMPS_AT_LEAST`)."""
    return bool(np.count_nonzero(steps) <= max(RARE_JUMPS_AT_LEAST,
                                               RARE_JUMPS * np.count_nonzero(odometry)))


def odometry_jumps(R: FloatArray, odometry: BoolArray) -> BoolArray:
    """The odometry steps whose measured rotation angle exceeds the odometry's median step
    angle by ``JUMP_MADS`` robust spreads (1.4826 median absolute deviations)."""
    return _far_above(rotation_angle(R), odometry)


def cuts_onto_jumps(rotations: FloatArray, i: IntArray, j: IntArray, R: FloatArray,
                    odometry: BoolArray, inlier: BoolArray, suspects: OdometrySuspects,
                    ) -> tuple[FloatArray, BoolArray]:
    """The fit ``(rotations, inlier)`` with each suspect it cuts (``~inlier``) that is not a
    jump moved onto a jump suspect it keeps, where the odometry between the two is kept and
    no loop closure the fit keeps ends on the nodes between them. No kept edge then tells
    the two cuts apart: the nodes between follow the odometry from the other side instead
    (world-to-node rotations composed along the measured steps, ``R_b = R_ab^T R_a``);
    every kept edge's residual is the same but for the two steps' swap, and a rejected
    closure that ends between costs at most its cap either way. Returns new arrays; the
    input is not changed."""
    rot, kept = rotations.copy(), inlier.copy()
    step_from = _steps_from(rot.shape[0], i, j, odometry)
    cuts = suspects.edges & ~suspects.jumps & ~inlier
    for cut, jump, direction in _moves_onto_jumps(i, j, odometry, kept, cuts,
                                                  suspects.jumps, step_from):
        # The nodes between follow the odometry from the cut's side, now joined.
        m, k = int(min(i[cut], j[cut])), int(min(i[jump], j[jump]))
        path = range(m + 1, k + 1) if direction > 0 else range(m, k, -1)
        for node in path:
            edge = step_from[node - 1] if direction > 0 else step_from[node]
            other = node - direction
            rot[node] = (R[edge].T @ rot[other] if i[edge] == other
                         else R[edge] @ rot[other])
    return rot, kept


def hanging_steps(i: IntArray, j: IntArray, odometry: BoolArray, kept: BoolArray,
                  freed: BoolArray, cuts: BoolArray) -> tuple[BoolArray, BoolArray]:
    """``(steps, closures)``: the ``cuts`` (odometry steps a fit leaves out) that nodes hang
    by alone, and the loop closures out of those nodes. Nodes hang by a cut where the fit's
    ``kept`` edges hold them to the rest only through its ``freed`` closures (those a fit
    trusting the steps rejected), no other ``odometry`` step out of them is left out, and
    every loop closure out of them, freed or rejected, is one piece of evidence
    (:func:`~.closure_runs.independent_pieces`: one run, or a single closure; a run the
    fit kept only in part is still one). There one run of consistent closures stands
    against one trusted step that nothing else checks: perceptual aliasing as well as a
    lost track (the Manhattan world's last 244 poses, held by one true 90 deg turn and one
    run of nine false closures: the turn was cut, every pose after it 73 deg off). Nodes
    between two steps left out do not hang by one: the two check each other through them
    (City10000's lost track, steps two keyframes apart both wrong, the nodes between held
    by one run of true closures)."""
    num_nodes = int(max(i.max(initial=-1), j.max(initial=-1))) + 1
    held = kept & ~freed
    graph = coo_matrix((np.ones(np.count_nonzero(held)), (i[held], j[held])),
                       shape=(num_nodes, num_nodes))
    label = connected_components(graph, directed=False)[1]
    main = np.bincount(label).argmax()
    steps_out = odometry & ~kept
    steps = np.zeros(i.size, bool)
    closures = np.zeros(i.size, bool)
    for cut in np.flatnonzero(cuts):
        for end in (int(i[cut]), int(j[cut])):
            part = label[end]
            if part == main:
                continue
            rim = (label[i] == part) != (label[j] == part)
            if (np.count_nonzero(steps_out & rim) == 1
                    and independent_pieces(i, j, ~odometry & rim) <= 1):
                steps[cut] = True
                closures |= ~odometry & rim
    return steps, closures


def steps_spanned(i: IntArray, j: IntArray, closures: BoolArray,
                  odometry: BoolArray) -> BoolArray:
    """The ``odometry`` steps ``(m, m + 1)`` that one of the ``closures`` ``(a, b)``,
    ``a < b``, spans (``a <= m < b``): the steps its loop over the odometry runs through,
    any of which a cut could fit it by."""
    num_nodes = int(max(i.max(initial=-1), j.max(initial=-1))) + 1
    a, b = np.minimum(i[closures], j[closures]), np.maximum(i[closures], j[closures])
    across = _count_across(a, b, num_nodes) > 0
    return odometry & across[np.minimum(i, j)]


def _steps_from(num_nodes: int, i: IntArray, j: IntArray, odometry: BoolArray) -> IntArray:
    """``step_from[k]``: the odometry edge ``k -- k + 1`` (-1: none)."""
    step_from = np.full(num_nodes, -1)
    odometry_edges = np.flatnonzero(odometry)
    step_from[np.minimum(i, j)[odometry_edges]] = odometry_edges
    return step_from


def _moves_onto_jumps(i: IntArray, j: IntArray, odometry: BoolArray, kept: BoolArray,
                      cuts: BoolArray, jumps: BoolArray, step_from: IntArray,
                      ) -> Iterator[tuple[int, int, int]]:
    """``(cut, jump, direction)`` for each of the ``cuts`` (odometry edges ``kept`` leaves
    out) that moves onto a kept ``jumps`` edge beside it (:func:`cuts_onto_jumps`), the
    later jump first; ``kept`` is updated in place as each cut moves. ``step_from``:
    :func:`_steps_from` over every node."""
    # Nodes a kept closure ends on (a rejected one costs its cap wherever they lie: no say).
    kept_closure = ~odometry & kept
    closure_end = np.zeros(step_from.shape[0], bool)
    closure_end[i[kept_closure]] = True
    closure_end[j[kept_closure]] = True
    for cut in np.flatnonzero(cuts):
        m = int(min(i[cut], j[cut]))
        for direction in (1, -1):  # the jump after the cut, then before it
            jump = _kept_jump_beside(m, direction, step_from, closure_end, kept, jumps)
            if jump is not None:
                kept[cut], kept[jump] = True, False
                yield int(cut), jump, direction
                break


def _kept_jump_beside(m: int, direction: int, step_from: IntArray, closure_end: BoolArray,
                      kept: BoolArray, jumps: BoolArray) -> int | None:
    """The ``jumps`` edge kept in ``kept`` that the walk from the step ``m -- m + 1`` in
    ``direction`` (+1: later steps) meets over kept odometry steps and nodes no closure ends
    on, or None."""
    num_nodes = step_from.shape[0]
    node = m + 1 if direction > 0 else m  # the first node past the cut step
    while 0 <= node < num_nodes and not closure_end[node]:
        if direction > 0:
            step = int(step_from[node])  # node -- node + 1
        else:
            step = int(step_from[node - 1]) if node > 0 else -1  # node - 1 -- node
        if step < 0 or not kept[step]:
            return None
        if jumps[step]:
            return step
        node += direction
    return None


def _count_across(a: IntArray, b: IntArray, num_nodes: int) -> FloatArray:
    """Per node ``m``, how many of the spans ``[a, b)`` hold it."""
    delta = np.zeros(num_nodes + 1)
    np.add.at(delta, a, 1.0)
    np.add.at(delta, b, -1.0)
    return np.cumsum(delta)[:num_nodes]
