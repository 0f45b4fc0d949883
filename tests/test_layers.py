"""The package's layers: imports point down, never up, and the core stays ROS-free.

Reads every module's imports with ``ast`` (module level and inside functions alike), so a
lazy import that reaches up a layer or into ROS fails here too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# Rank of each layer: a module may import its own layer or lower ranks only.
RANKS = {
    "errors": 0,
    "core": 1,
    "msg_adapters": 2,  # message conversion: needs core only
    "io": 3,
    "app": 3,  # ROS-free application layer shared by the node and the replay
    "ros": 4,
    "replay": 4,
    "cli": 5,
}
# Third-party modules a layer must not import (top-level names).
FORBIDDEN = {
    "core": {"rclpy", "rosbags", "mcap", "builtin_interfaces", "geometry_msgs", "nav_msgs",
             "std_msgs", "tf2_msgs", "visualization_msgs", "diagnostic_msgs", "std_srvs",
             "rcl_interfaces"},
    "msg_adapters": {"rclpy", "rosbags", "mcap"},
    "io": {"rclpy"},
    "app": {"rclpy", "rosbags", "mcap", "geometry_msgs", "nav_msgs", "visualization_msgs",
            "diagnostic_msgs"},
    "replay": {"rclpy"},
    "cli": {"rclpy"},
}


def _modules() -> dict[str, Path]:
    """``rotavg_ros.<...>`` module name -> file, with msg_adapters/ mapped as installed."""
    out: dict[str, Path] = {}
    for path in sorted((REPO / "rotavg_ros").rglob("*.py")):
        parts = path.relative_to(REPO).with_suffix("").parts
        out[".".join(p for p in parts if p != "__init__")] = path
    for path in sorted((REPO / "msg_adapters").glob("*.py")):
        name = "rotavg_ros.msg_adapters" + ("" if path.stem == "__init__" else f".{path.stem}")
        out[name] = path
    return out


def _layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in RANKS else None


def _imports(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


MODULES = _modules()


def test_every_module_is_in_a_layer() -> None:
    loose = [m for m in MODULES if _layer(m) is None
             and m not in ("rotavg_ros", "rotavg_ros.__main__")]
    assert not loose, f"modules outside the layer folders: {loose}"


@pytest.mark.parametrize("module", sorted(m for m in MODULES if _layer(m)))
def test_imports_point_down(module: str) -> None:
    layer = _layer(module)
    assert layer is not None
    bad = []
    for name in _imports(MODULES[module]):
        top = name.split(".")[0]
        if top in FORBIDDEN.get(layer, set()):
            bad.append(f"{name} (not allowed in {layer}/)")
        if top == "msg_adapters":
            bad.append(f"{name} (import it as rotavg_ros.msg_adapters)")
        target = _layer(name) if top == "rotavg_ros" else None
        if target is not None and target != layer and RANKS[target] >= RANKS[layer]:
            bad.append(f"{name} ({target}/ is not below {layer}/)")
    assert not bad, f"{module} imports: {bad}"


def test_no_import_cycles_between_modules() -> None:
    graph = {m: {n for n in _imports(p) if n in MODULES and n != m}
             for m, p in MODULES.items()}
    # A package's __init__ re-exporting its own modules is not a cycle of the design.
    for m in graph:
        graph[m] = {n for n in graph[m] if not (m.startswith(n + ".") or n.startswith(m + "."))}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                cycle = stack[stack.index(n):] + [n]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if n not in state:
                visit(n)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_the_checker_catches_an_upward_import(tmp_path: Path) -> None:
    """The rule above is not vacuous: core importing app is flagged."""
    bad = tmp_path / "bad.py"
    bad.write_text("from rotavg_ros.app.session import solve_snapshot\nimport rclpy\n")
    names = _imports(bad)
    assert "rotavg_ros.app.session" in names and "rclpy" in names
    assert RANKS[_layer("rotavg_ros.app.session") or ""] >= RANKS["core"]
