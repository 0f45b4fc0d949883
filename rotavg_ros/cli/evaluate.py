"""``rotavg evaluate EST.g2o GT.npz``: gauge-align an estimate and print its errors."""

from __future__ import annotations

import argparse
from pathlib import Path

from rotavg_ros.cli.output import warn
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.errors import InputError
from rotavg_ros.io.g2o import VERTEX_TAG, read_g2o_vertices
from rotavg_ros.io.onedsfm import open_npz, read_1dsfm_npz, read_rotations_npz


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
    missing = len(set(gt) - set(est))
    extra = len(set(est) - set(gt))
    if missing or extra:
        warn(f"scored the {stats.num_nodes} common node(s) only: {missing} ground-truth "
              f"node(s) have no estimate, {extra} estimated node(s) have no ground truth")
    print(f"nodes {stats.num_nodes}  mean {stats.mean_deg:.3f} deg  "
          f"median {stats.median_deg:.3f} deg  max {stats.max_deg:.3f} deg")
    return 0
