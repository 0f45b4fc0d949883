"""Start-up of the command line (issue 16): each command imports only what it needs.

Each case runs in a fresh interpreter, calls :func:`rotavg_ros.cli.main` and prints the
modules it loaded; ``rotavg solve`` on a g2o file must not load ROS, the bag readers or the
replay, and the help screens must not load torch.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
NOT_FOR_SOLVE = ("rclpy", "rosbags", "mcap", "rotavg_ros.replay", "rotavg_ros.ros",
                 "rotavg_ros.io.bag_", "rotavg_ros.io.rosbag2_mcap", "rotavg_ros.cli.replay")
CHILD = """\
import json, sys
from rotavg_ros.cli import main
try:
    status = main(sys.argv[1:])
except SystemExit as exc:
    status = exc.code
print(json.dumps({"status": status, "modules": sorted(sys.modules)}))
"""


def _loaded(argv: list[str]) -> tuple[object, list[str]]:
    """(exit status, sorted ``sys.modules``) after ``main(argv)`` in a fresh interpreter."""
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    proc = subprocess.run([sys.executable, "-c", CHILD, *argv], cwd=REPO_ROOT, env=env,
                          capture_output=True, text=True, timeout=120, check=True)
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    return report["status"], report["modules"]


def _hits(modules: list[str], prefixes: tuple[str, ...]) -> list[str]:
    return [m for m in modules if m.startswith(prefixes)]


def test_solve_on_g2o_loads_no_ros_bag_or_replay_module(tmp_path: Path) -> None:
    graph = tmp_path / "tiny.g2o"
    graph.write_text("EDGE_SE3:QUAT 0 1 0 0 0 0 0 0.0998 0.9950\n"
                     "EDGE_SE3:QUAT 1 2 0 0 0 0 0.0998 0 0.9950\n"
                     "EDGE_SE3:QUAT 0 2 0 0 0 0.0998 0 0 0.9950\n")
    out = tmp_path / "out.g2o"
    status, modules = _loaded(["solve", str(graph), "-o", str(out), "-q", "--depths", "2",
                               "--iterations", "50", "--threads", "1"])
    assert status == 0 and out.read_text().count("VERTEX_SE3:QUAT") == 3
    assert "torch" in modules  # the solver needs it: proves the solve really ran here
    assert not _hits(modules, NOT_FOR_SOLVE)


@pytest.mark.parametrize("argv", [["--help"], ["solve", "--help"], ["evaluate", "--help"]])
def test_help_loads_neither_torch_nor_the_replay(argv: list[str]) -> None:
    status, modules = _loaded(argv)
    assert status == 0
    assert not _hits(modules, ("torch", "scipy", *NOT_FOR_SOLVE))


def test_replay_help_still_lists_its_arguments(capsys: pytest.CaptureFixture[str]) -> None:
    from rotavg_ros.cli import main

    with pytest.raises(SystemExit):
        main(["replay", "--help"])
    assert "--solve-period" in capsys.readouterr().out


def test_top_level_help_lists_replay(capsys: pytest.CaptureFixture[str]) -> None:
    from rotavg_ros.cli import REPLAY_HELP, main

    with pytest.raises(SystemExit):
        main(["--help"])
    assert REPLAY_HELP in " ".join(capsys.readouterr().out.split())


BLAS_CHILD = "import os, rotavg_ros, numpy; print(os.environ.get('OPENBLAS_NUM_THREADS'))"


@pytest.mark.parametrize(("given", "expected"), [(None, "1"), ("2", "2")])
def test_importing_the_package_first_makes_blas_single_threaded_unless_set(
        given: str | None, expected: str) -> None:
    """Every rotavg process imports the package before numpy: OpenBLAS then runs one thread
    (a multi-threaded BLAS collapses when the CPU is shared); a user's own setting stays."""
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if given is not None:
        env["OPENBLAS_NUM_THREADS"] = given
    env["PYTHONPATH"] = str(REPO_ROOT)
    proc = subprocess.run([sys.executable, "-c", BLAS_CHILD], cwd=REPO_ROOT, env=env,
                          capture_output=True, text=True, timeout=120, check=True)
    assert proc.stdout.strip() == expected
