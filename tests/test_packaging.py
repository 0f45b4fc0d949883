"""Packaging: what gets installed, and that every dependency has a way to be installed.

* ``msg_adapters/`` installs as ``rotavg_ros.msg_adapters`` and never as a top-level
  ``msg_adapters`` (a generic name in site-packages would clash with other packages).
* ``package.xml`` names only rosdep keys known to resolve on Ubuntu 24.04 + Jazzy
  (docs/install.md), and every third-party module that the installed code (package and launch
  file) imports is either declared there or pinned in ``requirements-colcon.txt`` (the pip
  step of a colcon workspace).

``scripts/check_colcon.sh`` (CI) checks the same layout in a real colcon install tree.
"""

from __future__ import annotations

import ast
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# Non-ROS rosdep keys checked against ros/rosdistro's rosdep/python.yaml (docs/install.md).
VERIFIED_KEYS = {"python3-numpy", "python3-scipy", "python3-pytest", "python3-hypothesis"}
# Python module -> rosdep key, where they differ.
MODULE_KEYS = {"numpy": "python3-numpy", "scipy": "python3-scipy"}
# Imported but neither declared nor pinned, and why that is fine.
EXEMPT = {
    "ruamel": "installed with rosbags (one of its own dependencies)",
    "benchmarks": "source checkout only; `rotavg bench` says so when it is missing",
}


def _package_xml() -> ET.Element:
    return ET.parse(REPO / "package.xml").getroot()


def _depends(kinds: tuple[str, ...]) -> set[str]:
    root = _package_xml()
    return {str(e.text).strip() for kind in kinds for e in root.iter(kind)}


def _colcon_pins() -> set[str]:
    lines = (REPO / "requirements-colcon.txt").read_text().splitlines()
    return {ln.split("==")[0].strip() for ln in lines if "==" in ln and not ln.startswith("#")}


def _third_party_imports() -> set[str]:
    stdlib = set(sys.stdlib_module_names) | {"__future__"}
    names: set[str] = set()
    files = [*(REPO / "rotavg_ros").rglob("*.py"), *(REPO / "msg_adapters").glob("*.py"),
             *(REPO / "launch").glob("*.py")]
    for path in files:
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names.update(a.name.split(".")[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return names - stdlib - {"rotavg_ros"}


def test_msg_adapters_installs_only_under_rotavg_ros(tmp_path: Path) -> None:
    """setuptools' build_py (what pip and colcon install from) lays out one top-level
    package, rotavg_ros, with msg_adapters inside it."""
    subprocess.run([sys.executable, "setup.py", "-q", "build_py", "--build-lib",
                    str(tmp_path / "lib")], cwd=REPO, check=True, capture_output=True)
    top = sorted(p.name for p in (tmp_path / "lib").iterdir())
    assert top == ["rotavg_ros"], top
    adapters = tmp_path / "lib" / "rotavg_ros" / "msg_adapters"
    assert {"__init__.py", "inputs.py", "outputs.py"} <= {p.name for p in adapters.iterdir()}


def test_package_xml_uses_only_resolvable_rosdep_keys() -> None:
    keys = _depends(("depend", "exec_depend", "build_depend", "test_depend"))
    non_ros = {k for k in keys if k.startswith("python")}
    assert non_ros <= VERIFIED_KEYS, non_ros - VERIFIED_KEYS
    assert not [k for k in keys if k.endswith("-pip")]
    comment = (REPO / "package.xml").read_text()
    for pinned in ("torch", "rosbags", "mcap"):  # said where they come from instead
        assert pinned in comment


def test_every_imported_dependency_is_declared_or_pinned() -> None:
    declared = _depends(("depend", "exec_depend"))
    pinned = _colcon_pins()
    missing = sorted(
        name for name in _third_party_imports()
        if MODULE_KEYS.get(name, name) not in declared and name not in pinned
        and name not in EXEMPT)
    assert not missing, (f"imported, but neither an exec_depend in package.xml nor pinned in "
                         f"requirements-colcon.txt: {missing}")


def test_venv_and_colcon_share_the_pins() -> None:
    """requirements.txt includes requirements-colcon.txt, so both installs get one version."""
    assert "-r requirements-colcon.txt" in (REPO / "requirements.txt").read_text().splitlines()
    assert _colcon_pins() == {"torch", "rosbags", "mcap"}
