"""``rotavg evaluate EST.g2o GT.npz``: gauge-align an estimate and print its errors.

Ground truth is world-to-node (``R_i``, ``x_node = R_i x_world``; an edge is
``R_ij = R_i R_j^T``); the estimate's g2o vertices are node-to-world and are transposed on
reading. A ground truth that fits far better transposed draws a warning
(:data:`rotavg_ros.cli.EVALUATE_HELP`).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from rotavg_ros.cli.output import warn
from rotavg_ros.core.metrics import ErrorStats, evaluate
from rotavg_ros.errors import InputError
from rotavg_ros.io.g2o import VERTEX_TAG, read_g2o_vertices
from rotavg_ros.io.onedsfm import open_npz, read_1dsfm_npz, read_rotations_npz

TRANSPOSED_RATIO = 0.5
TRANSPOSED_MIN_GAIN_DEG = 5.0


def transposed_warning(est: dict[int, Any], gt: dict[int, Any],
                       stats: ErrorStats) -> str | None:
    """A warning when ``gt`` transposed (read as node-to-world) fits far better."""
    flipped = evaluate(est, {k: np.asarray(r).T for k, r in gt.items()})
    if (flipped.mean_deg < TRANSPOSED_RATIO * stats.mean_deg
            and stats.mean_deg - flipped.mean_deg >= TRANSPOSED_MIN_GAIN_DEG):
        return (f"ground truth looks transposed (node-to-world?): transposed it fits with "
                f"mean {flipped.mean_deg:.3f} deg instead of {stats.mean_deg:.3f} deg; "
                "evaluate expects world-to-node rotations (R_ij = R_i R_j^T)")
    return None


def cmd_evaluate(args: argparse.Namespace) -> int:
    try:
        ids, rots = read_g2o_vertices(args.estimate)
    except OSError as exc:
        raise InputError(f"{args.estimate}: {exc.strerror or exc}") from exc
    est = {k: r for k, r in zip(ids, rots, strict=True)}
    gt_path = Path(args.ground_truth)
    if not gt_path.is_file():
        raise InputError(f"{gt_path}: no such file")
    if gt_path.suffix == ".npz":
        with open_npz(gt_path) as data:
            is_dataset = "edges" in data.files
        gt = (dict(read_1dsfm_npz(gt_path, gt_only=True).gt) if is_dataset
              else dict(read_rotations_npz(gt_path)))
    else:
        raise InputError(f"{gt_path}: ground truth must be a 1DSfM .npz or a reference .npz")
    if not est:
        raise InputError(f"{args.estimate}: no {VERTEX_TAG} lines")
    try:
        stats = evaluate(est, gt)
    except ValueError as exc:  # no common ids, or malformed rotations
        raise InputError(f"{args.estimate} vs {gt_path}: {exc}") from exc
    if (flipped := transposed_warning(est, gt, stats)) is not None:
        warn(flipped)
    missing = len(set(gt) - set(est))
    extra = len(set(est) - set(gt))
    if missing or extra:
        warn(f"scored the {stats.num_nodes} common node(s) only: {missing} ground-truth "
              f"node(s) have no estimate, {extra} estimated node(s) have no ground truth")
    print(f"nodes {stats.num_nodes}  mean {stats.mean_deg:.3f} deg  "
          f"median {stats.median_deg:.3f} deg  max {stats.max_deg:.3f} deg")
    return 0
