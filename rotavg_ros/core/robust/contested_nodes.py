"""Nodes whose rotation rests on one measurement that other measurements contradict.

The solution keeps some edges (its inliers) and leaves the others out. Where the kept
edges join a block of nodes to the rest by one edge only (a bridge of the kept graph) and
other measured edges between the block and the rest were left out, the block's rotation
relative to the rest rests on that one measurement against every other one between them.
Had the others agreed with each other, they would have outvoted it (the verification's
block turns move such a block where two independent pieces of evidence agree,
:mod:`.relocalize_blocks`); they did not, so the data holds one measurement against one or
more that disagree with it and with each other, and cannot say which is right: a node
measured by one true edge and four false ones, each pointing elsewhere, is placed by
whichever edge the fit happened to keep (162 deg off in a draw of the regime benchmark's
``sfm/sparse200/out30``). Nodes no kept edge joins to the root at all are contested as
well: every measurement of them was left out.

A bridge the caller trusts (kept odometry) is no contest: the solver trusts odometry over
a lone loop closure by design, and reports odometry kept against closures on its own
(:attr:`~rotavg_ros.core.result.SolveResult.num_unchecked_odometry`). That holds where an
odometry step left out crosses it too: the solver chose which of two contradicting steps
to leave out by their size (a lost track's step is rarely as small as a keyframe's usual
motion), and counting those choices as contests marked 1,297 nodes of 132 of the 158
short chains with one wrong step, 171 of them 5 deg or more off (docs/benchmarks.md,
"Contested nodes"). The smaller side of a contested bridge is the contested block (the side
away from node 0 where the two are equal): the block rests on the bridge relative to the
bulk of the graph, wherever the anchor lies.

The answer for these nodes is not wrong for sure, only unchecked: the caller says so
(the node's ``nodes_contested`` diagnostic, a WARN), so that a user does not take their
rotations for verified ones.
"""

from __future__ import annotations

import numpy as np

from rotavg_ros.core.robust.relocalize_blocks import find_bridges
from rotavg_ros.core.types import BoolArray, IntArray


def contested_nodes(num_nodes: int, i: IntArray, j: IntArray, kept: BoolArray,
                    trusted: BoolArray) -> BoolArray:
    """Per node: whether its rotation rests on one kept edge that edges left out contradict
    (module docstring): it lies on the smaller side of a bridge of the ``kept`` edges that
    is not ``trusted`` and that some edge not kept crosses, or no kept edge joins it to
    node 0. ``i``, ``j``: the edges' ends (any orientation); a graph of one connected
    component."""
    contested = np.zeros(num_nodes, bool)
    if num_nodes < 2:
        return contested
    bridges = find_bridges(num_nodes, i, j, kept)
    # The search starts at node 0: its tree holds preorder numbers 0 .. its size - 1.
    contested |= bridges.pre >= bridges.component_size[0]
    left_out = np.flatnonzero(~kept)
    cuts = np.flatnonzero(~trusted[bridges.edges]) if bridges.edges.size else bridges.edges
    if left_out.size == 0 or cuts.size == 0:
        return contested
    # A left-out edge crosses a bridge where exactly one of its ends lies in the block:
    # give each a random 64-bit tag and XOR it into both its ends; a block's XOR over its
    # nodes (a range of preorder numbers) then cancels every edge inside it and keeps those
    # that cross (zero by chance with probability 2^-64 per block).
    tags = np.random.default_rng(0).integers(1, np.iinfo(np.int64).max, left_out.size)
    by_pre = np.zeros(num_nodes, np.int64)  # per preorder number: its node's tags, XORed
    np.bitwise_xor.at(by_pre, bridges.pre[i[left_out]], tags)
    np.bitwise_xor.at(by_pre, bridges.pre[j[left_out]], tags)
    prefix = np.concatenate([[0], np.bitwise_xor.accumulate(by_pre)])
    lo = bridges.pre[bridges.child[cuts]]
    hi = lo + bridges.size[bridges.child[cuts]]  # the block: preorder numbers lo .. hi - 1
    crossed = (prefix[hi] ^ prefix[lo]) != 0
    # Each crossed block: +1 where it starts, -1 past its end; where it is the larger side
    # of its bridge, its complement in node 0's part instead (+1 over the part, -1 over the
    # block). A node inside any marked side has a positive running sum.
    whole = int(bridges.component_size[0])
    larger = 2 * (hi - lo) > whole
    lo_c, hi_c = lo[crossed], hi[crossed]
    flip = larger[crossed]
    marks = np.zeros(num_nodes + 1, np.int64)
    np.add.at(marks, lo_c, np.where(flip, -1, 1))
    np.add.at(marks, hi_c, np.where(flip, 1, -1))
    flipped = int(np.count_nonzero(flip))
    marks[0] += flipped
    marks[whole] -= flipped
    in_block = np.cumsum(marks[:num_nodes]) > 0  # by preorder number
    reached = bridges.pre < bridges.component_size[0]
    contested[reached] |= in_block[bridges.pre[reached]]
    return contested
