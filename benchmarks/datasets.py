"""Locate the shared benchmark data and load it as (graph, reference) pairs.

The data lives outside the repository (``../shared`` next to the checkout, or the folder in
``$ROTAVG_SHARED``); callers get ``None`` from :func:`find_shared_dir` when it is absent and
must skip with a clear message.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Hashable
from dataclasses import dataclass, field
from pathlib import Path

from rotavg_ros.core.types import FloatArray
from rotavg_ros.core.view_graph import ViewGraph
from rotavg_ros.io.g2o import read_g2o
from rotavg_ros.io.onedsfm import read_1dsfm_npz, read_rotations_npz

REPO_ROOT = Path(__file__).resolve().parents[1]
SE_SYNC_GRAPHS = ("smallGrid3D", "parking-garage", "sphere2500", "torus3D")


@dataclass
class Benchmark:
    """A graph with the rotations it is scored against (GT or certified optimum)."""

    name: str
    graph: ViewGraph
    reference: dict[Hashable, FloatArray] = field(default_factory=dict)
    reference_kind: str = ""


def find_shared_dir() -> Path | None:
    """``$ROTAVG_SHARED`` if set and valid, else ``../shared`` beside the repo or the cwd."""
    candidates = []
    if os.environ.get("ROTAVG_SHARED"):
        candidates.append(Path(os.environ["ROTAVG_SHARED"]))
    candidates += [REPO_ROOT.parent / "shared", Path.cwd().parent / "shared"]
    return next((c for c in candidates if (c / "data").is_dir()), None)


def shared_dir_or_say(prog: str) -> Path | None:
    """:func:`find_shared_dir`, printing why ``prog`` has nothing to do when it is absent."""
    shared = find_shared_dir()
    if shared is None:
        print(f"{prog}: shared data not found (../shared or $ROTAVG_SHARED); nothing to do",
              file=sys.stderr)
    return shared


def load_ellis_island(shared: Path) -> Benchmark:
    """Ellis Island, the paper's protocol: GT cameras only (227 nodes, 20,010 edges)."""
    ds = read_1dsfm_npz(shared / "data/1dsfm/Ellis_Island/Ellis_Island.npz", gt_only=True)
    return Benchmark("Ellis Island", ds.graph, {k: r for k, r in ds.gt.items()},
                     "1DSfM ground truth")


def load_se_sync(shared: Path, name: str) -> Benchmark:
    """An SE-Sync graph with its certified-optimal reference rotations."""
    g = read_g2o(shared / f"data/se_sync_3d/{name}.g2o")
    ref = read_rotations_npz(shared / f"reference/se_sync_3d/{name}.npz")
    return Benchmark(name, g.graph, {k: r for k, r in ref.items()}, "certified optimum")
