"""The parameter table is the one source: config/rotavg.yaml, the solver defaults and the
replay's flags agree with it (no ROS needed)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml  # type: ignore[import-untyped]  # PyYAML (with rclpy); no stubs in the venv

from rotavg_ros.app.parameters import (
    PARAMETER_DEFAULTS,
    PARAMETER_TABLE,
    FloatRange,
    IntRange,
    main,
    parameters_yaml,
    settings_from_parameters,
    yaml_value,
)
from rotavg_ros.cli import build_parser
from rotavg_ros.cli.replay import NODE_FLAGS
from rotavg_ros.core.options import SolverOptions

REPO = Path(__file__).resolve().parents[1]
SHIPPED = REPO / "config" / "rotavg.yaml"


def _ros_parameters(text: str) -> dict[str, object]:
    doc = yaml.safe_load(text)
    assert list(doc) == ["/**/rotavg_node"]
    params = doc["/**/rotavg_node"]["ros__parameters"]
    assert isinstance(params, dict)
    return params


def test_shipped_params_file_matches_the_table() -> None:
    """Fails when config/rotavg.yaml and the table disagree; regenerate the file with
    ``python -m rotavg_ros.app.parameters --write config/rotavg.yaml``."""
    shipped = _ros_parameters(SHIPPED.read_text())
    assert list(shipped) == [spec.name for spec in PARAMETER_TABLE]
    for spec in PARAMETER_TABLE:
        value = shipped[spec.name]
        assert value == spec.default, spec.name
        assert type(value) is spec.type, spec.name  # 1.0 stays a double, 0 an integer
    assert SHIPPED.read_text() == parameters_yaml(), (
        "config/rotavg.yaml is stale: python -m rotavg_ros.app.parameters --write "
        "config/rotavg.yaml")


def test_generator_writes_and_prints_the_file(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "rotavg.yaml"
    assert main(["--write", str(out)]) == 0
    assert out.read_text() == parameters_yaml()
    assert main(["--yaml"]) == 0
    assert capsys.readouterr().out == parameters_yaml()
    for spec in PARAMETER_TABLE:  # every description is in the file, as a comment
        assert spec.description.split()[0] in parameters_yaml()


@pytest.mark.parametrize("value", [0.0, 1.0, 1e-12, 2.5e20, 0.001, 3, True, False, "", "world",
                                   "true", "a b", "cuda:0", [2, 4]])
def test_yaml_values_read_back_with_their_type(value: object) -> None:
    back = yaml.safe_load(f"x: {yaml_value(value)}")["x"]
    assert back == value and type(back) is type(value)


def test_solver_defaults_come_from_solver_options() -> None:
    s = SolverOptions()
    assert PARAMETER_DEFAULTS["mode"] == s.mode
    assert PARAMETER_DEFAULTS["depths"] == list(s.dense.depths)
    assert PARAMETER_DEFAULTS["iterations"] == s.dense.iterations
    assert PARAMETER_DEFAULTS["sigma"] == s.filter.sigma
    assert PARAMETER_DEFAULTS["seed"] == s.runtime.seed
    assert PARAMETER_DEFAULTS["device"] == s.runtime.device
    assert PARAMETER_DEFAULTS["threads"] == 0 and s.runtime.threads is None
    assert settings_from_parameters({}).solver == s


def test_table_rows_are_consistent() -> None:
    for spec in PARAMETER_TABLE:
        assert spec.description.endswith("."), spec.name
        if isinstance(spec.range, FloatRange):
            assert spec.type is float and spec.range.low <= spec.default <= spec.range.high
        elif isinstance(spec.range, IntRange):
            assert spec.type is int and spec.range.low <= spec.default <= spec.range.high
        if spec.choices:
            assert spec.default in spec.choices


def test_replay_flags_default_to_the_table() -> None:
    args = build_parser().parse_args(["replay", "bag"])
    for name in NODE_FLAGS:
        want = None if name == "reference_variance" else PARAMETER_DEFAULTS[name]
        assert getattr(args, name) == want, name
