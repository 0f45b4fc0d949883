"""Locate the shared benchmark data and load it as (graph, reference) pairs.

The data lives outside the repository (``../shared`` next to the checkout, or the folder in
``$ROTAVG_SHARED``); callers get ``None`` from :func:`find_shared_dir` when it is absent and
must skip with a clear message.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from collections.abc import Hashable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rotavg_ros.core.types import FloatArray, IntArray
from rotavg_ros.core.view_graph import ViewGraph
from rotavg_ros.io.g2o import read_g2o
from rotavg_ros.io.onedsfm import read_1dsfm_npz, read_rotations_npz

REPO_ROOT = Path(__file__).resolve().parents[1]
SE_SYNC_GRAPHS = ("smallGrid3D", "parking-garage", "sphere2500", "torus3D")
CITY10000_FILES = ("T1_city10000_04.txt", "ISAM2_GT_city10000.txt")
"""gtsam's City10000 (its hybrid-inference example): the measurements, two hypotheses at
200 odometry steps, and the ground-truth poses (x, y, heading per line)."""


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


def find_gtsam_data() -> Path | None:
    """The ``Data`` folder that the gtsam wheel (the ``bench`` extra) installs, found
    without importing gtsam; None where gtsam is not installed or ships no such folder."""
    spec = importlib.util.find_spec("gtsam")
    if spec is None or not spec.submodule_search_locations:
        return None
    return next((Path(loc) / "Data" for loc in spec.submodule_search_locations
                 if (Path(loc) / "Data").is_dir()), None)

MANHATTAN_FILE = "w10000.graph"
"""gtsam's copy of Olson's Manhattan world: a simulated planar robot on a city grid, 10,000
poses, 9,999 odometry steps and 54,312 loop closures (``EDGE2 i j x y theta`` and the
information matrix), ``VERTEX2`` rows of its initial estimate; no ground truth."""


@dataclass
class PlanarHeadings:
    """A planar pose graph's headings (radians): each edge ``(i, j)`` measures ``theta_j -
    theta_i`` (the rotation of ``pose_i^-1 pose_j``); ``alternative`` is an edge's second
    hypothesis (NaN where the front end gave one)."""

    i: IntArray
    j: IntArray
    measured: FloatArray
    alternative: FloatArray
    truth: FloatArray
    """Ground-truth heading of each node."""


def load_city10000(data: Path) -> PlanarHeadings:
    """City10000 from gtsam's data folder (:data:`CITY10000_FILES`): 10,000 poses, 9,999
    odometry steps, 10,688 loop closures; at 200 steps the front end gave two hypotheses
    (``EDGE2 i _ j _ count x y theta [x y theta]``)."""
    i, j, measured, alternative = [], [], [], []
    with open(data / CITY10000_FILES[0], encoding="ascii") as f:
        for line in f:
            field = line.split()
            if not field or field[0] != "EDGE2":
                continue
            count = int(field[5])
            if count not in (1, 2) or len(field) != 6 + 3 * count:
                raise ValueError(f"City10000: unexpected line {line.strip()!r}")
            i.append(int(field[1]))
            j.append(int(field[3]))
            measured.append(float(field[8]))
            alternative.append(float(field[11]) if count == 2 else np.nan)
    truth = np.loadtxt(data / CITY10000_FILES[1], ndmin=2)[:, 2]
    return PlanarHeadings(np.array(i, np.int64), np.array(j, np.int64), np.array(measured),
                          np.array(alternative), truth)


def load_manhattan(data: Path) -> PlanarHeadings:
    """The Manhattan world from gtsam's data folder (:data:`MANHATTAN_FILE`): its 64,311
    edges (every ``EDGE2 i j x y theta ...`` row; the ``EQUIV`` rows are left out) and, as
    ``truth``, the headings of its ``VERTEX2`` rows. The file carries no ground truth: those
    are its initial estimate, a plausible trajectory on the same topology (turns of about
    90 deg at the corners), which the regenerated cases take as their truth."""
    vertices: dict[int, float] = {}
    i, j, measured = [], [], []
    with open(data / MANHATTAN_FILE, encoding="ascii") as f:
        for line in f:
            field = line.split()
            if field and field[0] == "VERTEX2":
                vertices[int(field[1])] = float(field[4])
            elif field and field[0] == "EDGE2":
                i.append(int(field[1]))
                j.append(int(field[2]))
                measured.append(float(field[5]))
    if sorted(vertices) != list(range(len(vertices))):
        raise ValueError("Manhattan world: vertex ids are not 0 .. N-1")
    truth = np.array([vertices[k] for k in range(len(vertices))])
    return PlanarHeadings(np.array(i, np.int64), np.array(j, np.int64), np.array(measured),
                          np.full(len(i), np.nan), truth)
