from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rotavg_ros.core.so3 import geodesic_distance, quat_to_matrix, random_rotations
from rotavg_ros.core.view_graph import EdgeArrays
from rotavg_ros.io.g2o import G2oFormatError, read_g2o, read_g2o_vertices, write_g2o

INFO = "100 0 0 0 0 0 100 0 0 0 0 100 0 0 0 {a} 0 0 {b} 0 {c}"
FIXTURE = "\n".join([
    "# comment line",
    "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1",
    "VERTEX_SE3:QUAT 1 1 2 3 0 0 0.7071067811865476 0.7071067811865476",
    "",
    "FIX 0",
    "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0.7071067811865476 0.7071067811865476 "
    + INFO.format(a=4, b=5, c=6),
    "EDGE_SE3:QUAT 2 1 0 0 0 1 0 0 0 " + INFO.format(a=9, b=9, c=9),
])


def _write(tmp_path: Path, text: str, name: str = "g.g2o") -> Path:
    p = tmp_path / name
    p.write_text(text + "\n")
    return p


def test_parse_fixture_weights_rotations_and_counts(tmp_path: Path) -> None:
    g = read_g2o(_write(tmp_path, FIXTURE))
    assert (g.num_lines, g.num_vertices, g.num_edges) == (7, 2, 2)
    assert g.num_unsupported == 1 and g.skipped_tags == {"FIX": 1}
    assert g.graph.node_ids == [0, 1, 2]
    e = g.graph.edge_arrays()
    assert e.i.tolist() == [0, 1] and e.j.tolist() == [1, 2]
    np.testing.assert_allclose(e.weight, [5.0, 9.0])
    Rz90 = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(e.R[0], Rz90, atol=1e-15)
    # Edge written as (2, 1) with a 180 deg x-rotation: stored (1, 2) with the transpose.
    np.testing.assert_allclose(e.R[1], np.diag([1.0, -1, -1]).T, atol=1e-15)
    # Vertex quaternion is node-to-world; the reader returns world-to-node.
    np.testing.assert_allclose(g.vertex_rotations[1], Rz90.T, atol=1e-15)


def test_missing_information_gives_unit_weight(tmp_path: Path) -> None:
    g = read_g2o(_write(tmp_path, "EDGE_SE3:QUAT 3 7 0 0 0 0 0 0 1"))
    assert g.graph.edge_arrays().weight.tolist() == [1.0]


@pytest.mark.parametrize("line, fragment", [
    ("EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1 1 2", "expects"),
    ("EDGE_SE3:QUAT 0 1 0 0 0 0 0 zero 1", "not a number"),
    ("EDGE_SE3:QUAT 0 1 0 0 nan 0 0 0 1", "non-finite"),
    ("EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 0", "quaternion"),
    ("EDGE_SE3:QUAT 4 4 0 0 0 0 0 0 1", "self-loop"),
    ("EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1 " + INFO.format(a=1, b=0, c=1), "diagonal"),
    ("EDGE_SE3:QUAT 0 1.5 0 0 0 0 0 0 1", "integer"),
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 1", "expects"),
    ("BOGUS_TAG 1 2 3", "unknown tag"),
    ("EDGE_SE2 0 1 0 0 0.5 1 0", "expects"),
    ("EDGE_SE2 0 1 0 0 nan", "non-finite"),
    ("EDGE_SE2 2 2 0 0 0.5", "self-loop"),
    ("EDGE_SE2 0 1 0 0 0.5 1 0 0 1 0 0", "positive definite"),
    ("VERTEX_SE2 0 1 2", "expects"),
])
def test_malformed_line_names_file_and_line(tmp_path: Path, line: str, fragment: str) -> None:
    p = _write(tmp_path, "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n\n" + line, name="bad.g2o")
    with pytest.raises(G2oFormatError, match=fragment) as info:
        read_g2o(p)
    assert str(info.value).startswith(f"{p}:3:")
    assert info.value.line == 3


@pytest.mark.parametrize("order", ["rotation first", "structure first"])
def test_the_first_bad_line_in_the_file_is_the_one_reported(tmp_path: Path,
                                                            order: str) -> None:
    """Edge rotations are checked in one batch after the line-by-line pass; the error
    still names the first bad line of the file, whichever check finds it."""
    good = "EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1"
    non_unit = "EDGE_SE3:QUAT 1 2 0 0 0 0 0 0 2"
    not_pd = "EDGE_SE3:QUAT 2 3 0 0 0 0 0 0 1 " + INFO.format(a=1, b=0, c=1)
    malformed = "EDGE_SE3:QUAT 3 4 0 0 0"
    lines = ([good, non_unit, good, malformed, not_pd] if order == "rotation first"
             else [good, malformed, non_unit, not_pd])
    with pytest.raises(G2oFormatError) as info:
        read_g2o(_write(tmp_path, "\n".join(lines)))
    assert info.value.line == 2
    assert ("not 1" if order == "rotation first" else "expects") in str(info.value)
    with pytest.raises(G2oFormatError, match="information") as info:
        read_g2o(_write(tmp_path, "\n".join([good, good, not_pd, non_unit])))
    assert info.value.line == 3
    indefinite = "EDGE_SE3:QUAT 2 3 0 0 0 0 0 0 1 100 0 0 0 0 0 100 0 0 0 0 100 0 0 0 1 2 0 1 0 1"
    with pytest.raises(G2oFormatError, match="positive definite") as info:
        read_g2o(_write(tmp_path, "\n".join([good, indefinite, non_unit])))
    assert info.value.line == 2
    not_a_number = "EDGE_SE3:QUAT 4 5 0 0 0 0 0 zero 1"
    infinite = "EDGE_SE3:QUAT 4 5 0 inf 0 0 0 0 1"
    for first, second, line, fragment in [(non_unit, not_a_number, 2, "not 1"),
                                          (not_a_number, non_unit, 2, "not a number"),
                                          (good, infinite, 3, "non-finite")]:
        with pytest.raises(G2oFormatError, match=fragment) as info:
            read_g2o(_write(tmp_path, "\n".join([good, first, second, malformed])))
        assert info.value.line == line


def test_planar_graph_reads_headings_about_z(tmp_path: Path) -> None:
    """``VERTEX_SE2`` is a body's pose in the world (world-to-node ``Rz(theta)^T``);
    ``EDGE_SE2`` measures ``T_i^-1 T_j``, so ``R_ij = Rz(dtheta) = R_i R_j^T``; the weight
    is the heading's information ``I33``."""
    theta = {3: 0.3, 7: -2.9, 9: 3.1}
    lines = [f"VERTEX_SE2 {k} 1.0 -2.0 {t!r}" for k, t in theta.items()]
    lines += [f"EDGE_SE2 3 7 0.5 0.1 {theta[7] - theta[3]!r} 10 0 0 10 0 40",
              f"EDGE_SE2 9 7 0 0 {theta[7] - theta[9] + 2 * np.pi!r}",
              "EDGE_SE3:QUAT 3 9 0 0 0 0 0 0 1"]
    g = read_g2o(_write(tmp_path, "\n".join(lines)))
    assert (g.num_vertices, g.num_edges, g.num_unsupported) == (3, 3, 0)
    assert g.graph.node_ids == [3, 7, 9]
    e = g.graph.edge_arrays()
    ids = g.graph.node_ids
    edges = {(ids[a], ids[b]): (R, w) for a, b, R, w in zip(e.i, e.j, e.R, e.weight,
                                                           strict=True)}
    assert sorted(edges) == [(3, 7), (3, 9), (7, 9)]
    assert [edges[k][1] for k in [(3, 7), (7, 9), (3, 9)]] == [40.0, 1.0, 1.0]
    for a, b in [(3, 7), (7, 9)]:
        Ri, Rj = g.vertex_rotations[a], g.vertex_rotations[b]
        np.testing.assert_allclose(edges[a, b][0], Ri @ Rj.T, atol=1e-12)
    c, s = np.cos(theta[3]), np.sin(theta[3])
    np.testing.assert_allclose(g.vertex_rotations[3], [[c, s, 0], [-s, c, 0], [0, 0, 1]],
                               atol=1e-15)


def test_unknown_tag_skipped_when_not_strict(tmp_path: Path) -> None:
    g = read_g2o(_write(tmp_path, FIXTURE + "\nBOGUS_TAG 1 2 3"), strict=False)
    assert g.num_unknown == 1 and g.skipped_tags["BOGUS_TAG"] == 1 and g.num_edges == 2


def test_vertex_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    R = random_rotations(50, rng)
    ids = [int(k) for k in rng.permutation(1000)[:50]]
    p = tmp_path / "out.g2o"
    write_g2o(p, ids, R)
    got_ids, got = read_g2o_vertices(p)
    assert got_ids == ids
    np.testing.assert_allclose(got, R, rtol=0, atol=1e-14)
    first = p.read_text().splitlines()[0].split()
    # Written quaternion is node-to-world (of R^T).
    np.testing.assert_allclose(quat_to_matrix([float(t) for t in first[5:9]]), R[0].T, atol=1e-14)


def test_graph_round_trip_with_edges(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    R = random_rotations(4, rng)
    i, j = np.array([0, 0, 1]), np.array([1, 3, 2])  # sorted by (i, j) like edge_arrays()
    edges = EdgeArrays(i, j, R[i] @ np.swapaxes(R[j], 1, 2), np.array([0.5, 2.0, 7.25]),
                       np.ones(3, np.int64))
    p = tmp_path / "graph.g2o"
    write_g2o(p, [10, 11, 12, 13], R, edges)
    g = read_g2o(p)
    e = g.graph.edge_arrays()
    assert g.graph.node_ids == [10, 11, 12, 13]
    assert e.i.tolist() == i.tolist() and e.j.tolist() == j.tolist()
    np.testing.assert_allclose(e.weight, edges.weight, rtol=1e-15)
    np.testing.assert_allclose(e.R, edges.R, atol=1e-14)


def test_write_rejects_non_integer_ids(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="integers"):
        write_g2o(tmp_path / "x.g2o", ["cam0"], np.eye(3)[None])


@pytest.mark.parametrize("name, n_nodes, n_edges", [
    ("tinyGrid3D", 9, 11), ("smallGrid3D", 125, 297)])
def test_shared_convention_on_odometry_edges(
    shared_dir: Path, name: str, n_nodes: int, n_edges: int
) -> None:
    g = read_g2o(shared_dir / "data" / "se_sync_3d" / f"{name}.g2o")
    assert (g.graph.num_nodes, g.num_edges, g.num_vertices) == (n_nodes, n_edges, n_nodes)
    assert g.graph.node_ids == list(range(n_nodes))
    e = g.graph.edge_arrays()
    Rv = np.stack([g.vertex_rotations[k] for k in range(n_nodes)])
    odo = e.j == e.i + 1
    assert odo.sum() == n_nodes - 1
    implied = Rv[e.i[odo]] @ np.swapaxes(Rv[e.j[odo]], 1, 2)
    err = np.degrees(geodesic_distance(implied, e.R[odo]))
    assert err.max() < 0.01
    # The transposed convention would not fit.
    err_t = np.degrees(geodesic_distance(np.swapaxes(implied, 1, 2), e.R[odo]))
    assert np.median(err_t) > 1.0
