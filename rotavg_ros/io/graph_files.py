"""Read a relative-rotation graph from a file, by its extension: ``.g2o``, 1DSfM ``.npz`` or
``EGs.txt``. Ground truth, where the file has it, is world-to-node ``R_i``."""

from __future__ import annotations

from collections.abc import Callable, Hashable
from pathlib import Path

import numpy as np

from rotavg_ros.core.view_graph import ViewGraph
from rotavg_ros.errors import InputError
from rotavg_ros.io.g2o import EDGE_SE2_TAG, EDGE_TAG, read_g2o
from rotavg_ros.io.onedsfm import read_1dsfm_egs, read_1dsfm_npz


def read_graph_file(
    path: Path, gt_only: bool = False, warn: Callable[[str], None] | None = None,
) -> tuple[ViewGraph, dict[Hashable, np.ndarray]]:
    """Read ``.g2o``, a 1DSfM ``.npz`` or ``EGs.txt``; returns the graph and any GT.

    ``warn`` gets a line about g2o lines skipped for their tag (e.g. ``EDGE_SE2_XY``).
    """
    if not path.exists():
        raise InputError(f"{path}: no such file")
    if path.is_dir():
        raise InputError(f"{path}: is a directory, not a graph file")
    name = path.name.lower()
    try:
        if name.endswith(".g2o"):
            g2o = read_g2o(path)
            skipped = ", ".join(f"{tag} x{n}" for tag, n in sorted(g2o.skipped_tags.items()))
            if g2o.num_edges == 0:
                raise InputError(f"{path}: no {EDGE_TAG} or {EDGE_SE2_TAG} edges"
                                 + (f" (skipped lines: {skipped})" if skipped else ""))
            if skipped and warn is not None:
                warn(f"{path}: skipped lines with tags not used for rotation averaging: "
                     f"{skipped}")
            return g2o.graph, {}
        if name.endswith(".npz"):
            ds = read_1dsfm_npz(path, gt_only=gt_only)
            return ds.graph, {k: r for k, r in ds.gt.items()}
        if name.endswith(".txt"):
            ds = read_1dsfm_egs(path)
            return ds.graph, {k: r for k, r in ds.gt.items()}
    except (ValueError, KeyError, OSError) as exc:
        raise InputError(str(exc) if str(path) in str(exc) else f"{path}: {exc}") from exc
    raise InputError(f"{path}: unknown input format (expected .g2o, .npz or EGs .txt)")
