"""What the command line tells the user about their input: the ground-truth convention of
``rotavg evaluate``, a transposed ground truth, disconnected graphs (``solve`` and the
replay report), and a directory of loose .mcap files (``replay``)."""

from __future__ import annotations

import shutil
from itertools import combinations
from pathlib import Path

import numpy as np
import pytest
from ros_fixtures import spanning_tree_solve
from test_replay import chain_messages, ground_truth, replay, write_bag

from rotavg_ros.cli import main
from rotavg_ros.core.so3 import exp_map, matrix_to_quat, random_rotations
from rotavg_ros.errors import InputError
from rotavg_ros.replay import EXIT_INPUT, EXIT_OK

pytestmark = pytest.mark.usefixtures("single_torch_thread")
FAST_ARGS = ["--depths", "2", "--iterations", "300"]


def _write_g2o(path: Path, R: np.ndarray, groups: list[list[int]]) -> Path:
    """Complete graph inside each group of node ids (none between groups), R_ij = R_i R_j^T."""
    lines = []
    for group in groups:
        for a, b in combinations(group, 2):
            q = matrix_to_quat(R[a] @ R[b].T)
            lines.append(f"EDGE_SE3:QUAT {a} {b} 0 0 0 " + " ".join(repr(float(v)) for v in q))
    path.write_text("\n".join(lines) + "\n")
    return path


def _solved(tmp_path: Path, n: int = 12) -> tuple[np.ndarray, Path]:
    R = random_rotations(n, np.random.default_rng(1))
    g2o = _write_g2o(tmp_path / "graph.g2o", R, [list(range(n))])
    out = tmp_path / "out.g2o"
    assert main(["solve", str(g2o), "-o", str(out), "-q", *FAST_ARGS]) == 0
    return R, out


def test_evaluate_help_states_the_ground_truth_convention(
        capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["evaluate", "--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "world-to-node (x_node = R_i x_world)" in text
    assert "R_ij = R_i R_j^T" in text
    assert "node-to-world" in text and "transposed" in text


def test_evaluate_warns_once_when_the_ground_truth_is_transposed(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    R, out = _solved(tmp_path)
    Q = random_rotations(1, np.random.default_rng(2))[0]
    right, flipped = tmp_path / "right.npz", tmp_path / "flipped.npz"
    np.savez(right, R_ref=R @ Q)
    np.savez(flipped, R_ref=np.transpose(R @ Q, (0, 2, 1)))  # node-to-world by mistake
    capsys.readouterr()

    assert main(["evaluate", str(out), str(right)]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    fields = captured.out.split()
    assert float(fields[fields.index("mean") + 1]) < 0.01

    assert main(["evaluate", str(out), str(flipped)]) == 0
    captured = capsys.readouterr()
    warnings = [ln for ln in captured.err.splitlines() if "transposed" in ln]
    assert len(warnings) == 1 and len(captured.err.splitlines()) == 1
    assert warnings[0].startswith("rotavg: warning: ground truth looks transposed")
    assert "instead of" in warnings[0]
    fields = captured.out.split()
    assert float(fields[fields.index("mean") + 1]) > 10.0  # still scored as given


def test_evaluate_does_not_warn_when_neither_convention_fits_better(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Rotations near identity fit about as well either way: no warning."""
    rng = np.random.default_rng(3)
    small = np.stack([np.eye(3)] + [_small_rotation(rng, 0.02) for _ in range(7)])
    g2o = _write_g2o(tmp_path / "g.g2o", small, [list(range(8))])
    out = tmp_path / "o.g2o"
    assert main(["solve", str(g2o), "-o", str(out), "-q", *FAST_ARGS]) == 0
    ref = tmp_path / "ref.npz"
    np.savez(ref, R_ref=np.transpose(small, (0, 2, 1)))
    capsys.readouterr()
    assert main(["evaluate", str(out), str(ref)]) == 0
    assert "transposed" not in capsys.readouterr().err


def _small_rotation(rng: np.random.Generator, angle: float) -> np.ndarray:
    return np.asarray(exp_map(rng.normal(size=(1, 3)) * angle)[0])


def test_solve_warns_about_several_components(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    R = random_rotations(12, np.random.default_rng(4))
    g2o = _write_g2o(tmp_path / "two.g2o", R, [list(range(7)), list(range(7, 10)),
                                                 [10, 11]])
    out = tmp_path / "out.g2o"
    assert main(["solve", str(g2o), "-o", str(out), "-q", *FAST_ARGS]) == 0
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1, err  # --quiet keeps warnings
    assert err[0].startswith("rotavg: warning: the graph has 3 connected components "
                             "(sizes 7, 3, 2 nodes)")
    assert "its own gauge" in err[0]


def test_solve_of_a_connected_graph_does_not_warn(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _solved(tmp_path)
    assert "component" not in capsys.readouterr().err


def test_replay_report_warns_about_several_components(tmp_path: Path) -> None:
    gt = ground_truth(6, seed=5)
    names = list(gt)
    msgs = chain_messages({k: gt[k] for k in names[:3]}, [0.1, 0.2])
    msgs += chain_messages({k: gt[k] for k in names[3:]}, [0.3, 0.4])
    report = replay(write_bag(tmp_path / "bag", msgs))
    assert report.exit_code == EXIT_OK
    assert "final: 6 nodes, 2 component(s)" in report.text
    assert ("warning: the graph has 2 connected components (sizes 3, 3 nodes)"
            in report.text)
    connected = replay(write_bag(tmp_path / "one", chain_messages(gt, [0.1, 0.2, 0.3, 0.4,
                                                                       0.5])))
    assert "connected components" not in connected.text


def _loose_mcap_dir(tmp_path: Path) -> Path:
    """A directory with two .mcap files (two halves of a chain) and no metadata.yaml."""
    gt = ground_truth(6, seed=6)
    names = list(gt)
    loose = tmp_path / "loose"
    loose.mkdir()
    for part, keys in (("a", names[:4]), ("b", names[3:])):
        bag = write_bag(tmp_path / part, chain_messages({k: gt[k] for k in keys},
                                                        [0.1, 0.2, 0.3][:len(keys) - 1]))
        shutil.copy(next(bag.glob("*.mcap")), loose / f"{part}.mcap")
    return loose


def test_directory_of_several_mcap_files_is_refused_without_the_flag(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    loose = _loose_mcap_dir(tmp_path)
    with pytest.raises(InputError, match="--merge-mcap-files"):
        replay(loose)
    assert main(["replay", str(loose), "-q"]) == EXIT_INPUT
    err = capsys.readouterr().err
    assert "no metadata.yaml, and 2 .mcap files (a.mcap, b.mcap)" in err

    report = replay(loose, merge_mcap_files=True, solve_fn=spanning_tree_solve)
    assert report.exit_code == EXIT_OK
    assert "final: 6 nodes, 1 component(s)" in report.text
    assert any("read its 2 .mcap files as one bag" in p for p in report.problems)


def test_directory_with_one_mcap_file_needs_no_flag(tmp_path: Path) -> None:
    loose = _loose_mcap_dir(tmp_path)
    (loose / "b.mcap").unlink()
    report = replay(loose)
    assert report.exit_code == EXIT_OK and "final: 4 nodes" in report.text
