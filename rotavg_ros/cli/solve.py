"""``rotavg solve INPUT -o OUT.g2o``: solve a graph file.

The output g2o file holds one ``VERTEX_SE3:QUAT id 0 0 0 qx qy qz qw`` per node with the
**node-to-world** quaternion (g2o's vertex convention), the transpose of our world-to-node
``R_i``. For 1DSfM input, ids are the dataset's camera indices.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from rotavg_ros.cli.output import warn
from rotavg_ros.cli.solver_args import options_from_args
from rotavg_ros.core.result import components_warning, contested_warning, parallel_warning
from rotavg_ros.core.solver import RotationAverager
from rotavg_ros.errors import InputError
from rotavg_ros.io.g2o import write_g2o
from rotavg_ros.io.graph_files import read_graph_file


def cmd_solve(args: argparse.Namespace) -> int:
    options = options_from_args(args)
    options.validate()  # before reading a large input
    out_dir = Path(args.output).resolve().parent
    if Path(args.output).is_dir():
        raise InputError(f"{args.output}: is a directory; --output names the .g2o file")
    if not out_dir.is_dir():
        raise InputError(f"{args.output}: output directory {out_dir} does not exist")
    graph, _ = read_graph_file(Path(args.input), gt_only=args.gt_only, warn=warn)
    if graph.num_nodes == 0:
        raise InputError(f"{args.input}: no edges")
    t0 = time.perf_counter()
    result = RotationAverager(options).solve(graph)
    wall = time.perf_counter() - t0
    try:
        write_g2o(args.output, result.node_ids, result.rotations)
    except OSError as exc:
        raise InputError(f"{args.output}: {exc.strerror or exc}") from exc
    ncomp = int(result.component.max()) + 1 if result.component.size else 0
    for line in (components_warning(result), parallel_warning(result),
                 contested_warning(result)):
        if line is not None:
            warn(line)
    if not args.quiet:
        inl = result.residuals_deg[result.edge_inlier]
        print(f"solved {graph.num_nodes} nodes, {graph.edge_arrays().num_edges} edges in "
              f"{wall:.2f} s: depth {result.depth}, {result.num_filtered} edges filtered, "
              f"{ncomp} component(s), inlier residual median "
              f"{f'{np.median(inl):.3f} deg' if inl.size else 'n/a'} -> {args.output}")
    return 0
