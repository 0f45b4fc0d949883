"""Save and load the live view graph as g2o, so a restarted node continues where it stopped.

File format: standard g2o, readable by any g2o tool, plus comment lines for what g2o lacks.

* ``# rotavg_ros graph v2``, then ``# FRAME <g2o id> <frame id>`` per node: node ids are
  frame-id strings, g2o ids are ``0..N-1`` in the graph's node order.
* ``# SOLVED <g2o id> ...``: the nodes whose vertex holds a solved orientation, and
  ``# DEPTH <d>``: the DMF depth of that solve (0: unknown).
* ``VERTEX_SE3:QUAT id 0 0 0 qx qy qz qw``: the last solved orientation (node-to-world,
  g2o's convention), identity for nodes never solved (a placeholder, not listed in
  ``SOLVED``). The solved ones are loaded back as a warm start. Version 1 files (no
  ``SOLVED`` line) load without orientations: their placeholders cannot be told apart.
* ``EDGE_SE3:QUAT i j 0 0 0 qx qy qz qw`` + information ``diag(1, 1, 1, w, w, w)``: every raw
  measurement (parallel ones included) in arrival order, ``R_ij ~= R_i R_j^T``, so the repeat
  policy gives the same edges after a reload.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rotavg_ros.core.measurement import EdgeMeasurement
from rotavg_ros.core.types import FloatArray, IntArray
from rotavg_ros.core.view_graph import ViewGraph
from rotavg_ros.errors import InputError
from rotavg_ros.io.g2o import g2o_text, read_g2o

MAGIC = "# rotavg_ros graph v2"
_MAGIC_V1 = "# rotavg_ros graph v1"


@dataclass(frozen=True)
class _Edges:
    i: IntArray
    j: IntArray
    R: FloatArray
    weight: FloatArray


@dataclass
class StoredGraph:
    """What :func:`load_graph` read: measurements in arrival order and last orientations."""

    measurements: list[EdgeMeasurement]
    orientations: dict[str, FloatArray]
    """World-to-node rotations of the nodes solved when the file was written."""
    depth: int | None = None
    """DMF depth of that solve, if known."""


def save_graph(
    path: str | os.PathLike[str], graph: ViewGraph,
    orientations: Mapping[Any, FloatArray] | None = None, depth: int | None = None,
) -> int:
    """Write ``graph`` (and the world-to-node ``orientations`` of the solved nodes, with the
    ``depth`` of that solve, if any) atomically (see :func:`write_atomic`).

    Returns the number of measurements written; raises ``OSError`` if it could not write.
    """
    path = Path(path)
    ids = graph.node_ids
    rot = np.tile(np.eye(3), (len(ids), 1, 1))
    solved: list[int] = []
    for k, node in enumerate(ids):
        if orientations is not None and node in orientations:
            rot[k] = orientations[node]
            solved.append(k)
    i, j, R, w = graph.measurement_arrays()
    body = g2o_text(list(range(len(ids))), rot, _Edges(i, j, R, w))
    header = ([MAGIC] + [f"# FRAME {k} {node}" for k, node in enumerate(ids)]
              + ["# SOLVED" + "".join(f" {k}" for k in solved), f"# DEPTH {depth or 0}"])
    write_atomic(path, "\n".join(header) + "\n" + body)
    return int(i.size)


def write_atomic(path: str | os.PathLike[str], text: str) -> None:
    """Replace ``path`` by a file holding ``text``, all or nothing.

    Writes a temporary file in the same directory, fsyncs it, renames it over ``path``
    (``os.replace``) and fsyncs the directory: a crash or a full disk leaves the old file
    or the new one, never a torn one. The temporary file is removed if anything fails.
    """
    path = Path(path)
    try:  # keep the old file's permissions; mkstemp's 0600 otherwise
        mode = path.stat().st_mode & 0o7777
    except OSError:
        mode = 0o644
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):  # the rename itself; not every OS opens directories
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


def check_writable(path: str | os.PathLike[str]) -> None:
    """Raise ``InputError`` unless a file at ``path`` can be written atomically.

    Checks that the directory exists and that a file can be created there (by creating and
    removing an empty temporary file, which also holds for root and read-only mounts), and
    that ``path`` is not a directory.
    """
    path = Path(path)
    folder = path.parent
    if not folder.is_dir():
        raise InputError(f"{path}: directory {str(folder)!r} does not exist")
    if path.is_dir():
        raise InputError(f"{path}: is a directory")
    try:
        fd, probe = tempfile.mkstemp(dir=folder, prefix=f".{path.name}.", suffix=".probe")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise InputError(f"{path}: directory {str(folder)!r} is not writable "
                         f"({exc.strerror or exc})") from exc


def load_graph(path: str | os.PathLike[str]) -> StoredGraph:
    """Read a file written by :func:`save_graph` (ValueError names the file if it is not)."""
    path = Path(path)
    frames: dict[int, str] = {}
    solved: set[int] = set()
    depth: int | None = None
    with path.open() as fh:
        first = fh.readline().rstrip("\n")
        if first not in (MAGIC, _MAGIC_V1):
            raise InputError(f"{path}: not a rotavg_ros graph file (first line {first!r})")
        for lineno, line in enumerate(fh, start=2):
            text = line.rstrip("\n")
            if text.startswith("# SOLVED"):
                fields = text.split()[2:]
                if not all(f.isdigit() for f in fields):
                    raise InputError(f"{path}:{lineno}: malformed SOLVED line")
                solved = {int(f) for f in fields}
                continue
            if text.startswith("# DEPTH "):
                value = text[len("# DEPTH "):].strip()
                if not value.isdigit():
                    raise InputError(f"{path}:{lineno}: malformed DEPTH line")
                depth = int(value) or None
                continue
            if not text.startswith("# FRAME "):
                break
            parts = text.split(" ", 3)
            if len(parts) != 4 or not parts[2].isdigit() or not parts[3]:
                raise InputError(f"{path}:{lineno}: malformed FRAME line")
            frames[int(parts[2])] = parts[3]
    g2o = read_g2o(path)
    graph = g2o.graph
    names = [frames.get(int(node)) for node in graph.node_ids]  # type: ignore[call-overload]
    if any(n is None for n in names):
        raise InputError(f"{path}: a g2o id has no FRAME line")
    i, j, R, w = graph.measurement_arrays()
    measurements = [EdgeMeasurement(str(names[a]), str(names[b]), Rk, float(wk))
                    for a, b, Rk, wk in zip(i, j, R, w, strict=True)]
    orientations = {frames[int(k)]: v for k, v in g2o.vertex_rotations.items()
                    if int(k) in frames and int(k) in solved}
    return StoredGraph(measurements, orientations, depth if orientations else None)
