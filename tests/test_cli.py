"""Command line: ``rotavg solve`` / ``rotavg evaluate`` and their error handling."""

from __future__ import annotations

import os
import subprocess
import sys
from itertools import combinations
from pathlib import Path

import numpy as np
import pytest

from rotavg_ros.cli import main
from rotavg_ros.core.so3 import geodesic_distance, matrix_to_quat, quat_to_matrix, random_rotations

pytestmark = pytest.mark.usefixtures("single_torch_thread")


REPO_ROOT = Path(__file__).resolve().parents[1]
FAST_ARGS = ["--depths", "2", "--iterations", "300"]
N = 12


def _truth() -> np.ndarray:
    """World-to-node rotations with R_0 = I, so the solver's gauge equals the truth's."""
    R = random_rotations(N, np.random.default_rng(0))
    return np.einsum("kab,cb->kac", R, R[0])


def _write_g2o(path: Path, R: np.ndarray) -> Path:
    """Complete graph; edge quaternion = R_i R_j^T (g2o: T_i^-1 T_j with body-to-world)."""
    lines = []
    for a, b in combinations(range(R.shape[0]), 2):
        q = matrix_to_quat(R[a] @ R[b].T)
        lines.append(f"EDGE_SE3:QUAT {a} {b} 0 0 0 " + " ".join(repr(float(v)) for v in q))
    path.write_text("\n".join(lines) + "\n")
    return path


def _read_vertices(path: Path) -> dict[int, np.ndarray]:
    out: dict[int, np.ndarray] = {}
    for line in path.read_text().splitlines():
        tok = line.split()
        if tok and tok[0] == "VERTEX_SE3:QUAT":
            assert len(tok) == 9
            vid = int(tok[1])
            assert vid not in out
            assert [float(t) for t in tok[2:5]] == [0.0, 0.0, 0.0]
            out[vid] = np.array([float(t) for t in tok[5:9]])  # qx qy qz qw
    return out


def test_solve_writes_node_to_world_quaternions(tmp_path: Path, capsys) -> None:
    R = _truth()
    g2o = _write_g2o(tmp_path / "graph.g2o", R)
    out = tmp_path / "out.g2o"
    assert main(["solve", str(g2o), "-o", str(out), *FAST_ARGS]) == 0
    stdout = capsys.readouterr().out
    assert "solved 12 nodes, 66 edges" in stdout and str(out) in stdout
    quats = _read_vertices(out)
    assert sorted(quats) == list(range(N))  # one vertex per node
    for vid, q in quats.items():
        assert q[3] >= 0
        M = quat_to_matrix(q)
        # Node-to-world: the vertex quaternion's matrix is R_i^T (not R_i).
        assert np.degrees(geodesic_distance(M, R[vid].T)) < 0.01
    # And not the transpose (the test would be vacuous for symmetric rotations).
    assert max(np.degrees(geodesic_distance(quat_to_matrix(quats[k]), R[k]))
               for k in range(1, N)) > 1.0


def test_solve_quiet_prints_nothing(tmp_path: Path, capsys) -> None:
    g2o = _write_g2o(tmp_path / "graph.g2o", _truth())
    out = tmp_path / "out.g2o"
    assert main(["solve", str(g2o), "--output", str(out), "--quiet", *FAST_ARGS]) == 0
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == ""  # no progress lines either
    assert len(_read_vertices(out)) == N


def test_solve_progress_goes_to_stderr(tmp_path: Path, capsys) -> None:
    g2o = _write_g2o(tmp_path / "graph.g2o", _truth())
    assert main(["solve", str(g2o), "-o", str(tmp_path / "o.g2o"), *FAST_ARGS]) == 0
    captured = capsys.readouterr()
    assert "[rotavg]" in captured.err and "[rotavg]" not in captured.out


def test_evaluate_prints_mean_and_median(tmp_path: Path, capsys) -> None:
    R = _truth()
    g2o = _write_g2o(tmp_path / "graph.g2o", R)
    out = tmp_path / "out.g2o"
    assert main(["solve", str(g2o), "-o", str(out), "-q", *FAST_ARGS]) == 0
    Q = random_rotations(1, np.random.default_rng(5))[0]
    ref = tmp_path / "ref.npz"
    np.savez(ref, R_ref=R @ Q)  # another gauge: evaluate must align it away
    capsys.readouterr()
    assert main(["evaluate", str(out), str(ref)]) == 0
    text = capsys.readouterr().out
    assert "nodes 12" in text and "mean" in text and "median" in text
    fields = text.split()
    mean = float(fields[fields.index("mean") + 1])
    median = float(fields[fields.index("median") + 1])
    assert 0.0 <= median <= mean < 0.01


def test_solve_and_evaluate_1dsfm_npz(tmp_path: Path, capsys) -> None:
    n = 10
    rng = np.random.default_rng(3)
    R = random_rotations(n, rng)
    pairs = np.array(list(combinations(range(n), 2)), dtype=np.int64)
    R_rel = np.einsum("eab,ecb->eac", R[pairs[:, 0]], R[pairs[:, 1]])
    has_gt = np.ones(n, bool)
    has_gt[4] = False  # camera 4 has no GT: dropped with --gt-only
    ds = tmp_path / "scene.npz"
    np.savez(ds, edges=pairs, R_rel=R_rel, R_gt=R, has_gt=has_gt)
    out = tmp_path / "scene_out.g2o"
    assert main(["solve", str(ds), "-o", str(out), "--gt-only", "-q", *FAST_ARGS]) == 0
    quats = _read_vertices(out)
    assert sorted(quats) == [k for k in range(n) if k != 4]
    capsys.readouterr()
    assert main(["evaluate", str(out), str(ds)]) == 0
    text = capsys.readouterr().out
    assert "nodes 9" in text
    fields = text.split()
    assert float(fields[fields.index("mean") + 1]) < 0.01


def test_module_entry_point_subprocess(tmp_path: Path) -> None:
    g2o = _write_g2o(tmp_path / "graph.g2o", _truth())
    out = tmp_path / "out.g2o"
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    proc = subprocess.run(
        [sys.executable, "-m", "rotavg_ros", "solve", str(g2o), "-o", str(out), "--quiet",
         "--threads", "1", *FAST_ARGS],
        cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == ""
    quats = _read_vertices(out)
    R = _truth()
    assert sorted(quats) == list(range(N))
    assert all(np.degrees(geodesic_distance(quat_to_matrix(q), R[k].T)) < 0.01
               for k, q in quats.items())
    # The entry ends with os._exit: what the command printed still arrives, through a
    # pipe, and a refused input still exits with status 2 and its message.
    loud = subprocess.run(
        [sys.executable, "-m", "rotavg_ros", "solve", str(g2o), "-o", str(out),
         "--threads", "1", *FAST_ARGS],
        cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=120,
    )
    assert loud.returncode == 0, loud.stderr
    assert loud.stdout.startswith(f"solved {N} nodes") and loud.stdout.endswith("\n")
    bad = subprocess.run(
        [sys.executable, "-m", "rotavg_ros", "solve", str(tmp_path / "missing.g2o"),
         "-o", str(out)], cwd=REPO_ROOT, env=env, capture_output=True, text=True,
        timeout=120,
    )
    assert bad.returncode == 2 and "rotavg: error:" in bad.stderr


# ---------------------------------------------------------------------- errors
def test_unknown_extension_exit_2(tmp_path: Path, capsys) -> None:
    src = tmp_path / "graph.csv"
    src.write_text("0,1\n")
    out = tmp_path / "out.g2o"
    assert main(["solve", str(src), "-o", str(out)]) == 2
    captured = capsys.readouterr()
    assert str(src) in captured.err and "unknown input format" in captured.err
    assert captured.out == ""
    assert not out.exists()


def test_missing_file_exit_2(tmp_path: Path, capsys) -> None:
    src = tmp_path / "nope.g2o"
    assert main(["solve", str(src), "-o", str(tmp_path / "o.g2o")]) == 2
    assert f"{src}: no such file" in capsys.readouterr().err


def test_malformed_g2o_line_names_file_and_line(tmp_path: Path, capsys) -> None:
    src = tmp_path / "bad.g2o"
    src.write_text(
        "# header\n"
        "EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1\n"
        "EDGE_SE3:QUAT 1 2 0 0 0 0 0 zero 1\n"  # line 3: not a number
    )
    out = tmp_path / "out.g2o"
    assert main(["solve", str(src), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{src}:3:" in err
    assert err.startswith("rotavg: error:")
    assert not out.exists()


def test_g2o_nan_and_wrong_field_count(tmp_path: Path, capsys) -> None:
    src = tmp_path / "nan.g2o"
    src.write_text("EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1\n\nEDGE_SE3:QUAT 1 2 0 0 0 nan 0 0 1\n")
    assert main(["solve", str(src), "-o", str(tmp_path / "o.g2o")]) == 2
    assert f"{src}:3:" in capsys.readouterr().err
    src2 = tmp_path / "short.g2o"
    src2.write_text("EDGE_SE3:QUAT 0 1 0 0 0 0 0 1\n")
    assert main(["solve", str(src2), "-o", str(tmp_path / "o.g2o")]) == 2
    assert f"{src2}:1:" in capsys.readouterr().err


def test_nan_in_egs_file_exit_2_with_line(tmp_path: Path, capsys) -> None:
    folder = tmp_path / "Scene"
    folder.mkdir()
    src = folder / "EGs.txt"
    eye = "1 0 0 0 1 0 0 0 1"
    src.write_text(
        f"0 1 {eye} 0 0 1\n"
        f"1 2 {eye} 0 0 1\n"
        f"2 3 1 0 0 0 nan 0 0 0 1 0 0 1\n"  # line 3
    )
    out = tmp_path / "out.g2o"
    assert main(["solve", str(src), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{src}:3:" in err
    assert not out.exists()


def test_evaluate_bad_ground_truth_extension(tmp_path: Path, capsys) -> None:
    est = tmp_path / "est.g2o"
    est.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n")
    gt = tmp_path / "gt.txt"
    gt.write_text("x\n")
    assert main(["evaluate", str(est), str(gt)]) == 2
    assert str(gt) in capsys.readouterr().err


def test_bad_depths_argument(tmp_path: Path, capsys) -> None:
    g2o = _write_g2o(tmp_path / "graph.g2o", _truth()[:4])
    assert main(["solve", str(g2o), "-o", str(tmp_path / "o.g2o"), "--depths", "2,x"]) == 2
    assert "--depths" in capsys.readouterr().err
    assert main(["solve", str(g2o), "-o", str(tmp_path / "o.g2o"), "--depths", "3"]) == 2


def test_usage_error_exits_2() -> None:
    with pytest.raises(SystemExit) as exc:
        main(["solve"])  # missing input and --output
    assert exc.value.code == 2


@pytest.mark.parametrize(("flag", "value", "name"), [
    ("--iterations", "0", "iterations"),
    ("--iterations", "-5", "iterations"),
    ("--lr", "-1", "lr"),
    ("--lr", "nan", "lr"),
    ("--sigma", "nan", "sigma"),
    ("--sigma", "-1", "sigma"),
    ("--hidden-width", "0", "hidden_width"),
    ("--threads", "-1", "threads"),
    ("--tolerance", "-1", "tolerance"),
    ("--device", "gpu", "device"),
    ("--depths", "", "depths"),
])
def test_invalid_solver_option_exit_2_before_reading(
    tmp_path: Path, capsys, flag: str, value: str, name: str
) -> None:
    # The input does not exist: the option is rejected before the input is read.
    out = tmp_path / "o.g2o"
    assert main(["solve", str(tmp_path / "nope.g2o"), "-o", str(out), flag, value]) == 2
    err = capsys.readouterr().err
    assert err.startswith("rotavg: error: invalid solver option: ") and name in err, err
    assert not out.exists()


def test_missing_output_directory_exit_2_before_solving(tmp_path: Path, capsys) -> None:
    g2o = _write_g2o(tmp_path / "graph.g2o", _truth()[:4])
    out = tmp_path / "no_such_dir" / "o.g2o"
    assert main(["solve", str(g2o), "-o", str(out), *FAST_ARGS]) == 2
    err = capsys.readouterr().err
    assert "output directory" in err and "solved" not in err


@pytest.mark.parametrize("content", [b"", b"PK\x03\x04 truncated", b"not an archive\n"])
def test_unreadable_npz_exit_2_names_the_file(tmp_path: Path, capsys, content: bytes) -> None:
    bad = tmp_path / "bad.npz"
    bad.write_bytes(content)
    assert main(["solve", str(bad), "-o", str(tmp_path / "o.g2o")]) == 2
    assert f"{bad}:" in capsys.readouterr().err
    est = tmp_path / "est.g2o"
    est.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n")
    assert main(["evaluate", str(est), str(bad)]) == 2
    assert f"{bad}:" in capsys.readouterr().err


def test_truncated_real_npz_exit_2(tmp_path: Path, capsys) -> None:
    R = _truth()
    good = tmp_path / "good.npz"
    e = np.array([(a, b) for a, b in combinations(range(N), 2)])
    np.savez_compressed(good, edges=e, R_rel=np.einsum("eab,ecb->eac", R[e[:, 0]], R[e[:, 1]]))
    cut = tmp_path / "cut.npz"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    assert main(["solve", str(cut), "-o", str(tmp_path / "o.g2o")]) == 2
    assert f"{cut}:" in capsys.readouterr().err


def test_non_unit_quaternion_in_g2o_exit_2_with_line(tmp_path: Path, capsys) -> None:
    src = tmp_path / "q.g2o"
    src.write_text("EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 1 2 0 0 0 0.3 0.3 0.3 0.3\n")
    assert main(["solve", str(src), "-o", str(tmp_path / "o.g2o")]) == 2
    err = capsys.readouterr().err
    assert f"{src}:2:" in err and "norm" in err


def test_solve_reads_a_planar_pose_graph(tmp_path: Path, capsys) -> None:
    """A 2D g2o file (``VERTEX_SE2`` / ``EDGE_SE2``): a robot's headings along 60 poses,
    odometry at 0.5 deg and six loop closures. The answer is the headings, about z."""
    rng = np.random.default_rng(1)
    theta = np.cumsum(rng.uniform(-0.4, 0.4, 60))
    pairs = [(k, k + 1) for k in range(59)] + [(0, 30), (5, 40), (10, 50), (20, 59),
                                               (15, 45), (25, 55)]
    lines = [f"VERTEX_SE2 {k} 0 0 0" for k in range(60)]  # an initial guess, unused
    for a, b in pairs:
        d = float(theta[b] - theta[a] + np.radians(0.5) * rng.normal())
        lines.append(f"EDGE_SE2 {a} {b} 1 0 {d!r} 100 0 0 100 0 1000")
    src = tmp_path / "planar.g2o"
    src.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out.g2o"
    assert main(["solve", str(src), "-o", str(out), "-q", *FAST_ARGS]) == 0
    assert "warning" not in capsys.readouterr().err
    q = _read_vertices(out)
    assert sorted(q) == list(range(60))
    R = np.stack([quat_to_matrix(q[k]).T for k in range(60)])  # world-to-node
    c, s = np.cos(theta), np.sin(theta)
    truth = np.stack([np.array([[ck, sk, 0], [-sk, ck, 0], [0, 0, 1]])
                      for ck, sk in zip(c, s, strict=True)])
    # Gauge: both with node 0 at the identity.
    aligned = np.einsum("kab,cb->kac", R, R[0])
    expected = np.einsum("kab,cb->kac", truth, truth[0])
    assert np.degrees(geodesic_distance(aligned, expected)).max() < 2.0
    np.testing.assert_allclose(aligned[:, 2, 2], 1.0, atol=1e-6)  # about z


def test_skipped_g2o_tags_are_reported(tmp_path: Path, capsys) -> None:
    g2o = _write_g2o(tmp_path / "graph.g2o", _truth()[:5])
    lines = g2o.read_text().splitlines()
    lines[3] = "EDGE_SE2_XY 1 2 0 0 1 0 1"
    g2o.write_text("\n".join(lines) + "\n")
    out = tmp_path / "o.g2o"
    assert main(["solve", str(g2o), "-o", str(out), "-q", *FAST_ARGS]) == 0
    err = capsys.readouterr().err
    assert "rotavg: warning:" in err and "EDGE_SE2_XY x1" in err
    only = tmp_path / "xy.g2o"
    only.write_text("EDGE_SE2_XY 1 2 0 0 1 0 1\n")
    assert main(["solve", str(only), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "no EDGE_SE3:QUAT or EDGE_SE2 edges" in err and "EDGE_SE2_XY x1" in err


def test_evaluate_warns_when_ids_only_partly_overlap(tmp_path: Path, capsys) -> None:
    R = _truth()
    gt = tmp_path / "ref.npz"
    np.savez(gt, R_ref=R)
    est = tmp_path / "est.g2o"
    est.write_text("".join(
        f"VERTEX_SE3:QUAT {k} 0 0 0 " + " ".join(repr(float(v)) for v in matrix_to_quat(R[k].T))
        + "\n" for k in range(5)))
    assert main(["evaluate", str(est), str(gt)]) == 0
    captured = capsys.readouterr()
    assert "nodes 5" in captured.out
    assert "7 ground-truth node(s) have no estimate" in captured.err


def test_evaluate_binary_estimate_names_the_file(tmp_path: Path, capsys) -> None:
    est = tmp_path / "est.g2o"
    est.write_bytes(b"VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n\xff\xfe\x00")
    gt = tmp_path / "ref.npz"
    np.savez(gt, R_ref=_truth())
    assert main(["evaluate", str(est), str(gt)]) == 2
    assert f"{est}:2:" in capsys.readouterr().err
