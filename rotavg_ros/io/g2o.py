"""Read and write pose graphs in the g2o text format (rotation part only; 3D, and 2D read).

Conventions
-----------
* g2o ``VERTEX_SE3:QUAT id x y z qx qy qz qw`` stores the pose of body ``id`` in the world,
  so its quaternion (ROS order x, y, z, w) is **node-to-world**. This module returns and
  accepts **world-to-node** rotations ``R_i`` (the transpose), like the rest of the package.
* ``EDGE_SE3:QUAT i j x y z qx qy qz qw I11 I12 .. I66`` measures ``T_i^-1 T_j``; its rotation
  is ``Rg_i^T Rg_j`` with body-to-world ``Rg``, which equals ``R_i R_j^T`` for world-to-node
  ``R_i = Rg_i^T``: the quaternion's matrix is used unchanged as the edge ``R_ij``.
* The 21 information entries are the row-major upper triangle of the 6x6 information matrix
  in the order (x, y, z, rx, ry, rz); entries 15..20 are the 3x3 rotation block. The edge
  weight is ``trace(rotation block) / 3`` (raw, not normalised; 1 when the information part
  is absent). Translations are parsed, checked for finiteness and ignored.
* 2D graphs: ``VERTEX_SE2 id x y theta`` is the pose of body ``id`` in the world, so its
  world-to-node rotation is ``Rz(theta)^T``; ``EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22
  I23 I33`` measures ``T_i^-1 T_j``, so its ``R_ij`` is ``Rz(dtheta)`` (about z, the plane's
  normal). The information entries are the row-major upper triangle of the 3x3 information
  in the order (x, y, theta); the edge weight is ``I33``, the heading's (1 when absent).
  Each such line is read as the 3D line of the same rotation and weight (a quaternion
  about z, a rotation block ``I33 * identity``), so both kinds may share one file.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Hashable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import numpy as np
from numpy.typing import ArrayLike

from rotavg_ros.core.so3 import matrix_to_quat, quat_to_matrix
from rotavg_ros.core.types import FloatArray, IntArray
from rotavg_ros.core.view_graph import ViewGraph
from rotavg_ros.errors import InputError

PathLike = str | os.PathLike[str]

VERTEX_TAG = "VERTEX_SE3:QUAT"
EDGE_TAG = "EDGE_SE3:QUAT"
VERTEX_SE2_TAG = "VERTEX_SE2"
EDGE_SE2_TAG = "EDGE_SE2"

#: g2o tags that are recognised but not used for rotation averaging (counted and skipped).
UNSUPPORTED_TAGS: frozenset[str] = frozenset({
    "FIX", "PARAMS_SE3OFFSET", "PARAMS_CAMERAPARAMETERS",
    "VERTEX_XY", "EDGE_SE2_XY", "EDGE_SE2_PRIOR",
    "VERTEX_SE3:EXPMAP", "VERTEX_SE3:EULER", "EDGE_SE3:EULER", "EDGE_SE3_PRIOR",
    "VERTEX_TRACKXYZ", "VERTEX_POINT_XYZ", "EDGE_SE3_TRACKXYZ", "EDGE_SE3_POINTXYZ",
    "EDGE_PROJECT_XYZ2UV:EXPMAP", "EDGE_SE3_EXPMAP",
})

_N_INFO = 21
_N_INFO_SE2 = 6
_ROT_INFO = slice(15, 21)  # I44 I45 I46 I55 I56 I66
_MIN_QUAT_NORM = 1e-6
QUAT_NORM_TOL = 1e-3
"""Largest accepted | ||q|| - 1 | of a quaternion (as the node's ``quaternion_tolerance``);
within it q is normalised, beyond it the line is rejected as not a rotation."""


class G2oFormatError(InputError):
    """Malformed g2o input; the message starts with ``<file>:<1-based line>:``."""

    def __init__(self, path: PathLike, line: int, message: str) -> None:
        super().__init__(f"{os.fspath(path)}:{line}: {message}")
        self.path = os.fspath(path)
        self.line = line


@dataclass
class G2oGraph:
    """Result of :func:`read_g2o`.

    ``graph`` has integer node ids equal to the g2o vertex ids (vertices first, in file
    order, then nodes first seen on an edge). ``vertex_rotations`` maps vertex id to the
    world-to-node rotation of its ``VERTEX_SE3:QUAT`` or ``VERTEX_SE2`` line (empty when
    there is none).
    """

    graph: ViewGraph
    vertex_rotations: dict[int, FloatArray]
    num_lines: int
    num_vertices: int = 0
    num_edges: int = 0
    num_unsupported: int = 0
    """Lines with a known g2o tag that is not used here (``FIX``, ``EDGE_SE2_XY``, ...)."""
    num_unknown: int = 0
    """Lines with an unknown tag (only non-zero with ``strict=False``)."""
    skipped_tags: dict[str, int] = field(default_factory=dict)
    """Count of every skipped tag (unsupported and unknown)."""


class EdgeLike(Protocol):
    """Anything with dense-index edge arrays (:class:`~rotavg_ros.core.view_graph.EdgeArrays`)."""

    @property
    def i(self) -> IntArray: ...
    @property
    def j(self) -> IntArray: ...
    @property
    def R(self) -> FloatArray: ...
    @property
    def weight(self) -> FloatArray: ...


# ------------------------------------------------------------------ parsing helpers
def _read_lines(path: PathLike) -> list[str]:
    with open(path, "rb") as fh:
        raw = fh.read()
    try:
        return raw.decode("utf-8-sig").splitlines()  # a leading byte-order mark is dropped
    except UnicodeDecodeError as exc:
        line = len(raw[:exc.start].decode("utf-8", errors="replace").splitlines()) or 1
        if raw[:exc.start].endswith((b"\n", b"\r")):
            line += 1
        raise G2oFormatError(path, line, "not UTF-8 text (binary data or another "
                                         "encoding)") from None


def _tokenized(lines: Iterable[str]) -> Iterator[tuple[int, list[str]]]:
    """Yield ``(1-based line number, tokens)`` for non-blank, non-comment lines."""
    for lineno, raw in enumerate(lines, start=1):
        tokens = raw.split()
        if tokens and not tokens[0].startswith("#"):
            yield lineno, tokens


def _int(path: PathLike, lineno: int, tok: str, what: str) -> int:
    try:
        return int(tok)
    except ValueError:
        raise G2oFormatError(path, lineno, f"{what} must be an integer, got {tok!r}") from None


def _floats(path: PathLike, lineno: int, toks: Sequence[str], what: str) -> list[float]:
    try:
        vals = [float(t) for t in toks]
    except ValueError as exc:
        raise G2oFormatError(path, lineno, f"{what}: not a number ({exc})") from None
    if not all(math.isfinite(v) for v in vals):
        raise G2oFormatError(path, lineno, f"{what}: non-finite value (NaN/Inf)")
    return vals


def _quat(path: PathLike, lineno: int, q: Sequence[float]) -> FloatArray:
    norm = math.sqrt(sum(v * v for v in q))
    if norm < _MIN_QUAT_NORM:
        raise G2oFormatError(path, lineno, f"degenerate quaternion (norm {norm:.3g})")
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise G2oFormatError(path, lineno, f"quaternion norm {norm:.6g} is not 1 (tolerance "
                             f"{QUAT_NORM_TOL:g}): not a rotation")
    return quat_to_matrix(np.asarray(q, dtype=np.float64))


def _rotation_weight(path: PathLike, lineno: int, block: Sequence[float]) -> float:
    """``trace / 3`` of the rotation information block (its 6 upper-triangle entries),
    which must be positive definite."""
    a, b, c, d, e, f = block
    if min(a, d, f) <= 0.0:
        raise G2oFormatError(
            path, lineno, f"rotation information diagonal must be > 0, got ({a}, {d}, {f})")
    matrix = np.array([[a, b, c], [b, d, e], [c, e, f]])
    if np.linalg.eigvalsh(matrix)[0] <= 0.0:
        raise G2oFormatError(path, lineno, "rotation information block not positive definite")
    return (a + d + f) / 3.0


def _parse_vertex(path: PathLike, lineno: int, tokens: list[str]) -> tuple[int, FloatArray]:
    if len(tokens) != 9:
        raise G2oFormatError(
            path, lineno, f"{VERTEX_TAG} expects 8 fields (id x y z qx qy qz qw), "
            f"got {len(tokens) - 1}")
    vid = _int(path, lineno, tokens[1], "vertex id")
    vals = _floats(path, lineno, tokens[2:], VERTEX_TAG)
    return vid, _quat(path, lineno, vals[3:7]).T  # node-to-world -> world-to-node


def _parse_edge(
    path: PathLike, lineno: int, tokens: list[str]
) -> tuple[int, int, list[str]]:
    """``(i, j, the 7 or 28 number tokens after the ids)``: the line's structure checked;
    the numbers are converted by :func:`_edge_numbers` and the quaternion and the
    information block checked by :func:`_edge_rotations`, for many edges at once."""
    if len(tokens) not in (10, 10 + _N_INFO):
        raise G2oFormatError(
            path, lineno, f"{EDGE_TAG} expects 9 fields (i j x y z qx qy qz qw) plus "
            f"optionally {_N_INFO} information entries, got {len(tokens) - 1}")
    i, j = _edge_ends(path, lineno, tokens)
    return i, j, tokens[3:]


def _edge_ends(path: PathLike, lineno: int, tokens: list[str]) -> tuple[int, int]:
    """The two vertex ids of an edge line; a self-loop raises."""
    i = _int(path, lineno, tokens[1], "edge vertex id")
    j = _int(path, lineno, tokens[2], "edge vertex id")
    if i == j:
        raise G2oFormatError(path, lineno, f"self-loop on vertex {i}")
    return i, j


def _parse_vertex_se2(path: PathLike, lineno: int, tokens: list[str]
                      ) -> tuple[int, FloatArray]:
    if len(tokens) != 5:
        raise G2oFormatError(
            path, lineno, f"{VERTEX_SE2_TAG} expects 4 fields (id x y theta), "
            f"got {len(tokens) - 1}")
    vid = _int(path, lineno, tokens[1], "vertex id")
    theta = _floats(path, lineno, tokens[2:], VERTEX_SE2_TAG)[2]
    return vid, _about_z(theta).T  # node-to-world -> world-to-node


def _parse_edge_se2(
    path: PathLike, lineno: int, tokens: list[str]
) -> tuple[int, int, list[str]]:
    """As :func:`_parse_edge` for an ``EDGE_SE2`` line: ``(i, j, the number tokens of the
    ``EDGE_SE3:QUAT`` line of the same rotation and weight)``. Its numbers are checked
    here (a finite heading, and ``I33 > 0`` with the 3x3 information positive definite)."""
    if len(tokens) not in (6, 6 + _N_INFO_SE2):
        raise G2oFormatError(
            path, lineno, f"{EDGE_SE2_TAG} expects 5 fields (i j dx dy dtheta) plus "
            f"optionally {_N_INFO_SE2} information entries, got {len(tokens) - 1}")
    i, j = _edge_ends(path, lineno, tokens)
    vals = _floats(path, lineno, tokens[3:], EDGE_SE2_TAG)
    dx, dy, theta = vals[:3]
    numbers = [dx, dy, 0.0, 0.0, 0.0, math.sin(theta / 2.0), math.cos(theta / 2.0)]
    if len(vals) > 3:
        a, b, c, d, e, f = vals[3:]
        info = np.array([[a, b, c], [b, d, e], [c, e, f]])
        if f <= 0.0 or np.linalg.eigvalsh(info)[0] <= 0.0:
            raise G2oFormatError(path, lineno, "information matrix not positive definite "
                                 f"(heading entry I33 = {f})")
        numbers += [0.0] * 15 + [f, 0.0, 0.0, f, 0.0, f]
    return i, j, [repr(v) for v in numbers]


def _about_z(theta: float) -> FloatArray:
    """The rotation by ``theta`` radians about z."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class _EdgeNumbers(NamedTuple):
    """The numbers of parsed edge lines: quaternions (E, 4) and rotation information
    blocks (E, 6; NaN where a line has no information part)."""

    quats: FloatArray
    blocks: FloatArray


def _edge_numbers(path: PathLike, linenos: list[int], tokens: list[list[str]]
                  ) -> tuple[_EdgeNumbers, G2oFormatError | None]:
    """The numbers of edge lines (their tokens after the ids), converted all at once, up to
    the first line with a token that is not a finite number (its error, as :func:`_floats`
    words it, or None)."""
    count = len(tokens)
    sizes = np.fromiter((len(t) for t in tokens), np.int64, count)
    try:
        flat = np.array([t for toks in tokens for t in toks], dtype=np.float64)
        good = bool(np.isfinite(flat).all())
    except ValueError:
        good = False
    error = None
    if not good:  # the first bad line, in file order, and the numbers before it
        for k, (lineno, toks) in enumerate(zip(linenos, tokens, strict=True)):
            try:
                _floats(path, lineno, toks, EDGE_TAG)
            except G2oFormatError as exc:
                error, count = exc, k
                break
        sizes = sizes[:count]
        flat = np.array([t for toks in tokens[:count] for t in toks], dtype=np.float64)
    start = np.cumsum(sizes) - sizes  # of each line's numbers in ``flat``
    quats = flat[start[:, None] + np.arange(3, 7)].reshape(count, 4)
    blocks = np.full((count, 6), np.nan)
    has = sizes > 7
    blocks[has] = flat[start[has, None] + 7 + np.arange(_ROT_INFO.start, _ROT_INFO.stop)]
    return _EdgeNumbers(quats, blocks), error


def _edge_rotations(path: PathLike, linenos: list[int], numbers: _EdgeNumbers
                    ) -> tuple[FloatArray, FloatArray, G2oFormatError | None]:
    """``(R (E, 3, 3), weights (E,), the error of the first bad edge or None)`` for parsed
    edge lines, checked as :func:`_quat` and :func:`_rotation_weight` check one edge.
    Edges from the first bad one on are not returned."""
    quats, blocks = numbers
    count = quats.shape[0]
    weights = np.ones(count)
    bad = np.zeros(count, bool)
    norms = np.linalg.norm(quats, axis=1)
    bad |= (norms < _MIN_QUAT_NORM) | (np.abs(norms - 1.0) > QUAT_NORM_TOL)
    with_info = ~np.isnan(blocks[:, 0])
    if with_info.any():
        a, b, c, d, e, f = blocks[with_info].T
        full = np.stack([np.stack([a, b, c], -1), np.stack([b, d, e], -1),
                         np.stack([c, e, f], -1)], 1)
        positive = (np.minimum(np.minimum(a, d), f) > 0.0)
        positive &= np.linalg.eigvalsh(np.where(positive[:, None, None], full,
                                                np.eye(3)))[:, 0] > 0.0
        bad[with_info] |= ~positive
        weights[with_info] = (a + d + f) / 3.0
    error = None
    first = int(np.argmax(bad)) if bad.any() else count
    if first < count:  # the one-edge checks give the message
        try:
            _quat(path, linenos[first], quats[first].tolist())
            if with_info[first]:
                _rotation_weight(path, linenos[first], blocks[first].tolist())
        except G2oFormatError as exc:
            error = exc
        else:  # (the batch and the one-edge checks agree; never lose edges silently)
            error = G2oFormatError(path, linenos[first], "invalid rotation or information")
    return quat_to_matrix(quats[:first]), weights[:first], error


# ---------------------------------------------------------------------- public API
def read_g2o(path: PathLike, strict: bool = True) -> G2oGraph:
    """Parse the ``VERTEX_SE3:QUAT`` and ``EDGE_SE3:QUAT`` lines of a g2o file, and the
    ``VERTEX_SE2`` and ``EDGE_SE2`` lines of a 2D one (see the module docstring).

    Edge rotations become ``R_ij ~= R_i R_j^T`` (world-to-node ``R_i``) with raw weight
    ``trace(rotation information) / 3`` (2D: ``I33``). Known but unused tags are counted
    and skipped; an unknown tag raises :class:`G2oFormatError` unless ``strict=False``
    (then it is counted and skipped). Malformed lines, self-loops, NaN/Inf, zero or
    non-unit quaternions (beyond :data:`QUAT_NORM_TOL`), a non-positive-definite rotation
    information block and duplicate vertex ids always raise.
    """
    graph = ViewGraph()
    vertices: dict[int, FloatArray] = {}
    skipped: dict[str, int] = {}
    lines = _read_lines(path)
    # Edge lines are parsed line by line and their rotations converted all at once; the
    # first error in file order is raised either way.
    ends: list[tuple[int, int]] = []
    linenos: list[int] = []
    tokens: list[list[str]] = []
    error: G2oFormatError | None = None
    try:
        _read_lines_into(path, lines, strict, graph, vertices, skipped, ends, linenos, tokens)
    except G2oFormatError as exc:
        error = exc
    # Every edge read precedes ``error``'s line: the first bad edge comes first.
    numbers, bad_number = _edge_numbers(path, linenos, tokens)
    R, w, bad_edge = _edge_rotations(path, linenos, numbers)
    for first in (bad_edge, bad_number, error):
        if first is not None:
            raise first
    graph.add_edges([a for a, _ in ends], [b for _, b in ends], R, w)
    num_edges = len(ends)
    num_unsupported = sum(skipped.get(tag, 0) for tag in UNSUPPORTED_TAGS)
    num_unknown = sum(k for tag, k in skipped.items() if tag not in UNSUPPORTED_TAGS)
    return G2oGraph(graph, vertices, len(lines), len(vertices), num_edges,
                    num_unsupported, num_unknown, skipped)


def _read_lines_into(path: PathLike, lines: list[str], strict: bool, graph: ViewGraph,
                     vertices: dict[int, FloatArray], skipped: dict[str, int],
                     ends: list[tuple[int, int]], linenos: list[int],
                     tokens: list[list[str]]) -> None:
    """First pass of :func:`read_g2o`: vertices, node order, skipped tags, and each edge
    line's ids and number tokens (converted later, all at once)."""
    for lineno, line in _tokenized(lines):
        tag = line[0]
        if tag in (EDGE_TAG, EDGE_SE2_TAG):
            i, j, numbers = (_parse_edge if tag == EDGE_TAG else _parse_edge_se2)(
                path, lineno, line)
            graph.add_node(i)  # nodes in the order the file names them
            graph.add_node(j)
            ends.append((i, j))
            linenos.append(lineno)
            tokens.append(numbers)
        elif tag in (VERTEX_TAG, VERTEX_SE2_TAG):
            vid, Rv = (_parse_vertex if tag == VERTEX_TAG else _parse_vertex_se2)(
                path, lineno, line)
            if vid in vertices:
                raise G2oFormatError(path, lineno, f"duplicate vertex id {vid}")
            vertices[vid] = Rv
            graph.add_node(vid)
        elif tag in UNSUPPORTED_TAGS or not strict:
            skipped[tag] = skipped.get(tag, 0) + 1
        else:
            raise G2oFormatError(path, lineno, f"unknown tag {tag!r}")


def read_g2o_vertices(path: PathLike) -> tuple[list[int], FloatArray]:
    """Vertex ids (file order) and their world-to-node rotations ``(N, 3, 3)``.

    Meant for reading solver output written by :func:`write_g2o`; every other line is
    ignored (edges are not parsed), but malformed vertex lines raise.
    """
    ids: list[int] = []
    rots: list[FloatArray] = []
    seen: set[int] = set()
    for lineno, tokens in _tokenized(_read_lines(path)):
        if tokens[0] != VERTEX_TAG:
            continue
        vid, Rv = _parse_vertex(path, lineno, tokens)
        if vid in seen:
            raise G2oFormatError(path, lineno, f"duplicate vertex id {vid}")
        seen.add(vid)
        ids.append(vid)
        rots.append(Rv)
    return ids, (np.stack(rots) if rots else np.zeros((0, 3, 3)))


def write_g2o(
    path: PathLike,
    node_ids: Sequence[Hashable],
    rotations_world_to_node: ArrayLike,
    edges: EdgeLike | None = None,
) -> None:
    """Write ``VERTEX_SE3:QUAT id 0 0 0 qx qy qz qw`` per node (+ optional edges).

    ``node_ids`` must be integers (g2o ids). The vertex quaternion is that of the
    node-to-world rotation ``R_i^T`` (g2o convention), printed with full precision (``repr``)
    so :func:`read_g2o_vertices` recovers the rotations to ~1e-16. ``edges`` (dense indices
    ``i``, ``j`` into ``node_ids``, ``R ~= R_i R_j^T``, ``weight``) become ``EDGE_SE3:QUAT``
    lines with zero translation and information ``diag(1, 1, 1, w, w, w)``, so that
    :func:`read_g2o` gives back the same rotations and weights.
    """
    text = g2o_text(node_ids, rotations_world_to_node, edges)
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(text)


def g2o_text(
    node_ids: Sequence[Hashable],
    rotations_world_to_node: ArrayLike,
    edges: EdgeLike | None = None,
) -> str:
    """The text :func:`write_g2o` writes."""
    R = np.asarray(rotations_world_to_node, dtype=np.float64)
    ids = [_as_int_id(v) for v in node_ids]
    if R.shape != (len(ids), 3, 3):
        raise ValueError(f"rotations must have shape ({len(ids)}, 3, 3), got {R.shape}")
    if not np.all(np.isfinite(R)):
        raise ValueError("rotations must be finite")
    out: list[str] = []
    if ids:
        q = matrix_to_quat(np.swapaxes(R, -1, -2))
        for vid, qk in zip(ids, q, strict=False):
            out.append(f"{VERTEX_TAG} {vid} 0 0 0 {_fmt(qk)}")
    if edges is not None:
        ei = np.asarray(edges.i, dtype=np.int64)
        ej = np.asarray(edges.j, dtype=np.int64)
        ew = np.asarray(edges.weight, dtype=np.float64)
        eR = np.asarray(edges.R, dtype=np.float64).reshape(-1, 3, 3)
        if not (ei.shape == ej.shape == ew.shape == (eR.shape[0],)):
            raise ValueError("edges.i, edges.j, edges.R and edges.weight lengths differ")
        if ei.size and (min(ei.min(), ej.min()) < 0 or max(ei.max(), ej.max()) >= len(ids)):
            raise ValueError("edge indices out of range of node_ids")
        if not np.all(np.isfinite(ew) & (ew > 0)):
            raise ValueError("edge weights must be finite and > 0")
        eq = matrix_to_quat(eR) if ei.size else np.zeros((0, 4))
        for a, b, qk, w in zip(ei, ej, eq, ew, strict=False):
            info = np.zeros(_N_INFO)
            info[[0, 6, 11]] = 1.0
            info[[15, 18, 20]] = w
            out.append(f"{EDGE_TAG} {ids[a]} {ids[b]} 0 0 0 {_fmt(qk)} {_fmt(info)}")
    return "\n".join(out) + ("\n" if out else "")


def _as_int_id(v: Hashable) -> int:
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
        raise ValueError(f"g2o vertex ids must be integers, got {v!r}")
    return int(v)


def _fmt(values: FloatArray) -> str:
    return " ".join(repr(float(v)) for v in values)


# ---------------------------------------------------------------------- ids for frames
_ID_PATTERN = re.compile(r"^(.*?)(0|[1-9][0-9]*)$")


def g2o_id_mapping(node_ids: Sequence[Hashable]) -> tuple[list[int], str]:
    """g2o integer ids for ``node_ids`` and a description of the mapping.

    ``<prefix><int>`` with one common prefix and round-tripping integers (no leading zeros,
    all distinct) -> those integers; otherwise ``0..N-1`` in order.
    """
    names = [str(n) for n in node_ids]
    matches = [_ID_PATTERN.match(n) for n in names]
    if names and all(matches):
        prefixes = {m.group(1) for m in matches if m}
        ints = [int(m.group(2)) for m in matches if m]
        if len(prefixes) == 1 and len(set(ints)) == len(ints):
            prefix = prefixes.pop()
            how = (f"g2o id = the integer in frame id '{prefix}<id>'" if prefix
                   else "g2o id = frame id")
            return ints, how
    return list(range(len(names))), "sequential g2o ids; see the .frames.tsv file"


def write_g2o_with_mapping(path: Path, result: Any) -> str:
    """Write the orientations to ``path`` (plus ``path.frames.tsv`` if ids are sequential)."""
    ids, how = g2o_id_mapping(result.node_ids)
    write_g2o(path, ids, result.rotations)
    header = [f"# rotavg replay: node-to-world orientations of {len(ids)} frames; {how}"]
    if how.startswith("sequential"):
        sidecar = Path(f"{path}.frames.tsv") if not str(path).endswith(".g2o") else \
            Path(str(path)[:-4] + ".frames.tsv")
        with open(sidecar, "w", encoding="utf-8") as fh:
            fh.write("g2o_id\tframe_id\n")
            for i, node in zip(ids, result.node_ids, strict=True):
                fh.write(f"{i}\t{node}\n")
        header[0] = header[0].replace("the .frames.tsv file", sidecar.name)
        how = how.replace("the .frames.tsv file", str(sidecar))
    if len(set(map(str, result.anchors))) > 1:
        header.append(f"# {len(result.anchors) - 1} component(s) not connected to the anchor "
                      f"{result.anchors[0]} have their own gauge")
    body = Path(path).read_text(encoding="utf-8")
    Path(path).write_text("\n".join(header) + "\n" + body, encoding="utf-8")
    return how
