"""Readers for 1DSfM relative-rotation benchmarks (npz conversions and raw ``EGs.txt``).

Conventions
-----------
* Node ids are the integer camera (image) indices of the file, 0-based.
* Absolute rotations ``R_i`` are Bundler **world-to-camera** rotations.
* Edges carry ``R_ij ~= R_i R_j^T``: this is the raw 1DSfM ``EGs.txt`` rotation and the
  shared npz key ``R_rel`` (the Chatterjee-Govindu ``.mat`` ``RR`` stores the transpose).
* Rotations are accepted when ``||R^T R - I||_F <= 1e-3`` and ``det R > 0``, then projected
  onto SO(3); anything else is an error naming the file and the offending key/row or line.
"""

from __future__ import annotations

import math
import os
import pickle
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rotavg_ros.core.so3 import project_to_so3
from rotavg_ros.core.types import FloatArray, IntArray
from rotavg_ros.core.view_graph import ViewGraph
from rotavg_ros.errors import InputError

PathLike = str | os.PathLike[str]

ORTHOGONALITY_TOL = 1e-3
"""Largest accepted ``||R^T R - I||_F`` before projection onto SO(3)."""


class DatasetFormatError(InputError):
    """Malformed dataset file; the message names the file and the key/row or line."""


@dataclass
class Dataset1DSfM:
    """A 1DSfM scene: view graph, world-to-camera ground truth (may be empty) and name."""

    graph: ViewGraph
    gt: dict[int, FloatArray] = field(default_factory=dict)
    name: str = ""


# ------------------------------------------------------------------ validation
@contextmanager
def open_npz(path: PathLike) -> Iterator[np.lib.npyio.NpzFile]:
    """``np.load`` of an ``.npz`` archive; an empty, truncated or damaged file, or one that
    is not an archive, raises :class:`DatasetFormatError` naming it."""
    p = os.fspath(path)
    try:
        data = np.load(path, allow_pickle=False)
    except (EOFError, zipfile.BadZipFile, pickle.UnpicklingError) as exc:
        raise DatasetFormatError(f"{p}: not a readable .npz archive ({exc})") from exc
    except ValueError as exc:  # numpy: "pickled data" / "not an npy file"
        raise DatasetFormatError(f"{p}: not an .npz archive ({exc})") from exc
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise DatasetFormatError(f"{p}: a single .npy array, not an .npz archive")
    try:
        with data:
            yield data
    except (EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise DatasetFormatError(f"{p}: damaged .npz archive ({exc})") from exc

def _orthogonality_error(R: FloatArray) -> FloatArray:
    E = np.einsum("kji,kjl->kil", R, R) - np.eye(3)
    return np.sqrt(np.einsum("kab,kab->k", E, E))


def _bad_rotations(R: FloatArray) -> IntArray:
    """Indices of rows that are not finite, not orthogonal enough, or reflections."""
    finite = np.all(np.isfinite(R), axis=(1, 2))
    ok = finite.copy()
    if np.any(finite):
        Rf = R[finite]
        ok[finite] = (_orthogonality_error(Rf) <= ORTHOGONALITY_TOL) & (np.linalg.det(Rf) > 0)
    return np.flatnonzero(~ok).astype(np.int64)


def _describe(R: FloatArray) -> str:
    if not np.all(np.isfinite(R)):
        return "non-finite entries"
    err = float(_orthogonality_error(R[None])[0])
    return f"not a rotation (||R^T R - I|| = {err:.3g}, det = {float(np.linalg.det(R)):.6g})"


def _load_key(data: np.lib.npyio.NpzFile, path: PathLike, key: str) -> np.ndarray:
    if key not in data.files:
        raise DatasetFormatError(f"{os.fspath(path)}: missing key {key!r} (has {data.files})")
    return np.asarray(data[key])


def _checked_rotations(path: PathLike, key: str, R: np.ndarray, rows: IntArray) -> FloatArray:
    """Validate ``R[rows]`` (shape ``(N, 3, 3)``) and return all of ``R`` projected."""
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise DatasetFormatError(
            f"{os.fspath(path)}: {key!r} must have shape (N, 3, 3), got {R.shape}")
    if not np.issubdtype(R.dtype, np.floating):
        raise DatasetFormatError(f"{os.fspath(path)}: {key!r} must be float, got {R.dtype}")
    R = R.astype(np.float64)
    bad = _bad_rotations(R[rows])
    if bad.size:
        row = int(rows[bad[0]])
        raise DatasetFormatError(
            f"{os.fspath(path)}: {key}[{row}] is {_describe(R[row])} "
            f"({bad.size} bad row(s) in total)")
    out = R.copy()
    out[rows] = project_to_so3(R[rows])
    return out


def _edge_index(path: PathLike, edges: np.ndarray) -> IntArray:
    p = os.fspath(path)
    if edges.ndim != 2 or edges.shape[1] != 2:
        raise DatasetFormatError(f"{p}: 'edges' must have shape (E, 2), got {edges.shape}")
    if not np.issubdtype(edges.dtype, np.integer):
        raise DatasetFormatError(f"{p}: 'edges' must be integer, got {edges.dtype}")
    e = edges.astype(np.int64)
    neg = np.flatnonzero(np.any(e < 0, axis=1))
    if neg.size:
        raise DatasetFormatError(f"{p}: edges[{int(neg[0])}] = {e[neg[0]].tolist()} is negative")
    loops = np.flatnonzero(e[:, 0] == e[:, 1])
    if loops.size:
        raise DatasetFormatError(f"{p}: edges[{int(loops[0])}] is a self-loop on {e[loops[0], 0]}")
    return e


def _gt_mask(path: PathLike, data: np.lib.npyio.NpzFile, key: str, R: np.ndarray) -> np.ndarray:
    """``has_gt`` if present, else rows that are not all zero (1DSfM's "no GT" marker)."""
    if "has_gt" in data.files:
        mask = np.asarray(data["has_gt"])
        if mask.shape != (R.shape[0],) or mask.dtype != np.bool_:
            raise DatasetFormatError(
                f"{os.fspath(path)}: 'has_gt' must be bool of shape ({R.shape[0]},), "
                f"got {mask.dtype} {mask.shape}")
        return mask
    if R.ndim != 3:
        raise DatasetFormatError(
            f"{os.fspath(path)}: {key!r} must have shape (N, 3, 3), got {R.shape}")
    return np.asarray(np.any(R.reshape(R.shape[0], -1) != 0, axis=1))


def _build_graph(e: IntArray, R: FloatArray) -> ViewGraph:
    """Graph whose dense indices follow ascending node id."""
    graph = ViewGraph()
    for node in np.unique(e):
        graph.add_node(int(node))
    graph.add_edges(e[:, 0].tolist(), e[:, 1].tolist(), R)  # (same lengths: checked)
    return graph


# ---------------------------------------------------------------------- public API
def read_1dsfm_npz(path: PathLike, gt_only: bool = False) -> Dataset1DSfM:
    """Read the shared npz form: ``edges`` (E, 2), ``R_rel`` (E, 3, 3) ``= R_i R_j^T``,
    optional ``R_gt`` (N, 3, 3) world-to-camera and ``has_gt`` (N,) bool.

    With ``gt_only`` only cameras with ground truth and the edges between them are kept
    (the paper's protocol). Nodes are the cameras that appear on a kept edge, with dense
    indices in ascending id order; all edges have unit weight.
    """
    p = os.fspath(path)
    with open_npz(path) as data:
        e = _edge_index(path, _load_key(data, path, "edges"))
        R_rel_raw = _load_key(data, path, "R_rel")
        if R_rel_raw.shape[:1] != (e.shape[0],):
            raise DatasetFormatError(
                f"{p}: 'R_rel' has {R_rel_raw.shape[:1]} rows but 'edges' has {e.shape[0]}")
        R_rel = _checked_rotations(path, "R_rel", R_rel_raw, np.arange(e.shape[0]))
        gt: dict[int, FloatArray] = {}
        has_gt = np.zeros(0, dtype=bool)
        if "R_gt" in data.files:
            R_gt_raw = np.asarray(data["R_gt"])
            has_gt = _gt_mask(path, data, "R_gt", R_gt_raw)
            R_gt = _checked_rotations(path, "R_gt", R_gt_raw, np.flatnonzero(has_gt))
            if e.size and int(e.max()) >= R_gt.shape[0]:
                raise DatasetFormatError(
                    f"{p}: edge index {int(e.max())} out of range of 'R_gt' ({R_gt.shape[0]})")
            gt = {int(k): R_gt[k] for k in np.flatnonzero(has_gt)}
        elif gt_only:
            raise DatasetFormatError(
                f"{p}: no ground truth ('R_gt') in this file; --gt-only and evaluation need it")
    if gt_only:
        keep = has_gt[e[:, 0]] & has_gt[e[:, 1]]
        e, R_rel = e[keep], R_rel[keep]
        nodes = set(np.unique(e).tolist())
        gt = {k: v for k, v in gt.items() if k in nodes}
    return Dataset1DSfM(_build_graph(e, R_rel), gt, Path(path).stem)


def read_1dsfm_egs(path: PathLike) -> Dataset1DSfM:
    """Read a raw 1DSfM ``EGs.txt``: lines ``i j R11 R12 .. R33 [t1 t2 t3]``.

    The rotation is row-major and ``R_ij = R_i R_j^T`` (world-to-camera); the translation
    direction is ignored. Blank lines and ``#`` comments are skipped. The name is the parent
    folder's name (e.g. ``Madrid_Metropolis``); there is no ground truth.
    """
    p = os.fspath(path)
    ij: list[tuple[int, int]] = []
    mats: list[list[float]] = []
    line_of: list[int] = []
    with open(path, encoding="utf-8") as fh:
        for lineno, raw in enumerate(fh, start=1):
            tok = raw.split()
            if not tok or tok[0].startswith("#"):
                continue
            if len(tok) not in (11, 14):
                raise DatasetFormatError(
                    f"{p}:{lineno}: expected 14 fields (i j R11..R33 t1 t2 t3), got {len(tok)}")
            try:
                a, b = int(tok[0]), int(tok[1])
                vals = [float(t) for t in tok[2:]]
            except ValueError as exc:
                raise DatasetFormatError(f"{p}:{lineno}: not a number ({exc})") from None
            if a < 0 or b < 0:
                raise DatasetFormatError(f"{p}:{lineno}: negative camera index")
            if a == b:
                raise DatasetFormatError(f"{p}:{lineno}: self-loop on camera {a}")
            if not all(math.isfinite(v) for v in vals):
                raise DatasetFormatError(f"{p}:{lineno}: non-finite value (NaN/Inf)")
            ij.append((a, b))
            mats.append(vals[:9])
            line_of.append(lineno)
    e = np.asarray(ij, dtype=np.int64).reshape(-1, 2)
    R = np.asarray(mats, dtype=np.float64).reshape(-1, 3, 3)
    bad = _bad_rotations(R)
    if bad.size:
        k = int(bad[0])
        raise DatasetFormatError(f"{p}:{line_of[k]}: rotation is {_describe(R[k])}")
    if R.shape[0]:
        R = project_to_so3(R)
    return Dataset1DSfM(_build_graph(e, R), {}, Path(path).resolve().parent.name)


def read_rotations_npz(path: PathLike) -> dict[int, FloatArray]:
    """Reference absolute rotations (world-to-node), keyed by row index.

    Reads ``R_ref`` or else ``R_gt`` (N, 3, 3); rows with ``has_gt`` false (or, without
    ``has_gt``, all-zero ``R_gt`` rows) are left out. Rotations are validated and projected.
    """
    with open_npz(path) as data:
        if "R_ref" in data.files:
            key = "R_ref"
        elif "R_gt" in data.files:
            key = "R_gt"
        else:
            raise DatasetFormatError(
                f"{os.fspath(path)}: no 'R_ref' or 'R_gt' key (has {data.files})")
        R_raw = np.asarray(data[key])
        if key == "R_gt" or "has_gt" in data.files:
            mask = _gt_mask(path, data, key, R_raw)
        else:
            mask = np.ones(R_raw.shape[0], dtype=bool)
    rows = np.flatnonzero(mask)
    R = _checked_rotations(path, key, R_raw, rows)
    return {int(k): R[k] for k in rows}
