from __future__ import annotations

from pathlib import Path
from typing import cast

import numpy as np
import pytest

from rotavg_ros.core.so3 import geodesic_distance, random_rotations
from rotavg_ros.io.onedsfm import (
    DatasetFormatError,
    read_1dsfm_egs,
    read_1dsfm_npz,
    read_rotations_npz,
)


def _ellis(shared_dir: Path) -> Path:
    return shared_dir / "data" / "1dsfm" / "Ellis_Island" / "Ellis_Island.npz"


def test_ellis_gt_only_sizes_and_convention(shared_dir: Path) -> None:
    ds = read_1dsfm_npz(_ellis(shared_dir), gt_only=True)
    g = ds.graph
    assert ds.name == "Ellis_Island"
    assert g.num_nodes == 227 and g.edge_arrays().num_edges == 20010
    ids = cast(list[int], g.node_ids)  # 1DSfM node ids are the npz indices
    assert sorted(ds.gt) == sorted(ids)
    e = g.edge_arrays()
    gt = np.stack([ds.gt[k] for k in ids])
    implied = gt[e.i] @ np.swapaxes(gt[e.j], 1, 2)  # R_i R_j^T
    med = np.median(np.degrees(geodesic_distance(e.R, implied)))
    assert 2.7 < med < 3.1
    med_t = np.median(np.degrees(geodesic_distance(np.swapaxes(e.R, 1, 2), implied)))
    assert med_t > 10.0


def test_ellis_full_graph(shared_dir: Path) -> None:
    ds = read_1dsfm_npz(_ellis(shared_dir))
    assert ds.graph.num_nodes == 247 and ds.graph.edge_arrays().num_edges == 20297
    assert len(ds.gt) == 227
    assert ds.graph.node_ids == list(range(247))  # dense index == camera index


def test_madrid_egs(shared_dir: Path) -> None:
    folder = shared_dir / "data" / "1dsfm" / "Madrid_Metropolis"
    ds = read_1dsfm_egs(folder / "EGs.txt")
    assert ds.name == "Madrid_Metropolis" and ds.gt == {}
    assert ds.graph.num_nodes == 394 and ds.graph.edge_arrays().num_edges == 23784
    cc = set(int(x) for x in (folder / "cc.txt").read_text().split())
    assert set(ds.graph.node_ids) == cc
    # Same rotations as the npz copy, up to the SO(3) projection.
    npz = read_1dsfm_npz(folder / "Madrid_Metropolis.npz")
    np.testing.assert_allclose(npz.graph.edge_arrays().R, ds.graph.edge_arrays().R, atol=1e-12)


@pytest.mark.parametrize("line, fragment", [
    ("1 2 1 0 0 0 1 0 0 0 1 0 0", "expected 14 fields"),
    ("1 2 1 0 0 0 1 0 0 0 x 0 0 1", "not a number"),
    ("1 2 1 0 0 0 1 0 0 0 inf 0 0 1", "non-finite"),
    ("3 3 1 0 0 0 1 0 0 0 1 0 0 1", "self-loop"),
    ("1 2 1 0 0 0 1 0 0 0 1.01 0 0 1", "not a rotation"),
    ("1 2 -1 0 0 0 1 0 0 0 1 0 0 1", "not a rotation"),
])
def test_malformed_egs_line(tmp_path: Path, line: str, fragment: str) -> None:
    p = tmp_path / "EGs.txt"
    p.write_text("0 1 1 0 0 0 1 0 0 0 1 0 0 1\n" + line + "\n")
    with pytest.raises(DatasetFormatError, match=fragment) as info:
        read_1dsfm_egs(p)
    assert f"{p}:2:" in str(info.value)


def test_egs_projects_small_errors(tmp_path: Path) -> None:
    p = tmp_path / "EGs.txt"
    p.write_text("0 1 1.0001 0 0 0 1 0 0 0 1 0 0 1\n")
    R = read_1dsfm_egs(p).graph.edge_arrays().R[0]
    np.testing.assert_allclose(R, np.eye(3), atol=1e-15)


def test_npz_bad_rotation_names_key_and_row(tmp_path: Path) -> None:
    R = random_rotations(3, np.random.default_rng(0))
    R[2] *= 2.0
    p = tmp_path / "bad.npz"
    np.savez(p, edges=np.array([[0, 1], [1, 2], [0, 2]]), R_rel=R)
    with pytest.raises(DatasetFormatError, match=r"bad\.npz: R_rel\[2\]"):
        read_1dsfm_npz(p)


def test_read_rotations_npz(tmp_path: Path, shared_dir: Path) -> None:
    ref = read_rotations_npz(shared_dir / "reference" / "se_sync_3d" / "smallGrid3D.npz")
    assert sorted(ref) == list(range(125))
    gt = read_rotations_npz(_ellis(shared_dir))
    assert len(gt) == 227
    R = random_rotations(3, np.random.default_rng(1))
    R[1] = 0.0
    p = tmp_path / "gt.npz"
    np.savez(p, R_gt=R)
    got = read_rotations_npz(p)
    assert sorted(got) == [0, 2]
    np.testing.assert_allclose(got[2], R[2], atol=1e-15)
