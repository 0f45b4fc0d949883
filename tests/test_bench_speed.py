"""The whole-process speed benchmark (``benchmarks.bench_speed``): its table and a quick run."""

from __future__ import annotations

import importlib.util

import pytest

from benchmarks import bench_speed
from benchmarks.bench_speed import PYCOLMAP, Row, format_table, ratio


def _row(method: str, walls: list[float], failure: str | None = None) -> Row:
    return Row("g", 10, 20, method, walls, 1.25, 0.5, failure)


def test_median_and_ratio_to_the_reference_method() -> None:
    ours = _row("rotavg (default)", [3.0, 9.0, 4.0])
    ref = _row(PYCOLMAP, [2.0, 1.0, 50.0])
    assert ours.median_wall == 4.0 and ref.median_wall == 2.0
    assert ratio(ours, ref) == 2.0
    assert ratio(ours, None) is None
    failed = _row("rotavg (default)", [1.0], failure="exit 2: boom")
    assert failed.median_wall is None and ratio(failed, ref) is None


def test_table_rows_ratios_and_failures() -> None:
    rows = [_row("rotavg (default)", [3.0, 9.0, 4.0]), _row(PYCOLMAP, [2.0, 1.0, 50.0]),
            _row("rotavg --profile paper", [7.0], failure="timed out after 5 s")]
    lines = format_table(rows).splitlines()
    assert len(lines) == 2 + 3 and lines[0].startswith("| graph | N | E | method |")
    assert lines[2] == "| g | 10 | 20 | rotavg (default) | 4.00 | 3 | 2.00 | 1.250 | 0.500 |"
    assert lines[3] == f"| g | 10 | 20 | {PYCOLMAP} | 2.00 | 3 | 1.00 | 1.250 | 0.500 |"
    assert "failed: timed out after 5 s" in lines[4] and lines[4].endswith("| – | – | – |")


def test_missing_shared_data_skips_with_a_message(monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    import benchmarks.datasets

    monkeypatch.setattr(benchmarks.datasets, "find_shared_dir", lambda: None)
    assert bench_speed.main(["--graphs", "ellis", "--methods", "rotavg (default)"]) == 0
    out, err = capsys.readouterr()
    assert "shared data not found" in err and "skipping ellis" in err and out == ""


@pytest.mark.skipif(importlib.util.find_spec("pycolmap") is None,
                    reason="pycolmap not installed (requirements-bench.txt)")
def test_quick_run_on_a_tiny_generated_graph(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench_speed.main(["--graphs", "tiny", "--quick", "--timeout", "300"]) == 0
    rows = [line.split(" | ") for line in capsys.readouterr().out.splitlines()
            if line.startswith("| tiny |")]
    assert [r[3] for r in rows] == list(bench_speed.METHODS)
    for r in rows:
        assert r[1:3] == ["60", "388"] and r[5] == "1"
        assert float(r[4]) > 0 and float(r[8].rstrip(" |")) < 2.0  # median error, degrees
    assert rows[-1][6] == "1.00"


def test_help_prints_and_exits_zero(capsys: pytest.CaptureFixture[str]) -> None:
    """The graph names hold '%' (argparse's format character): --help must still print."""
    with pytest.raises(SystemExit) as exc:
        bench_speed.parse_args(["--help"])
    assert exc.value.code == 0
    assert "ellis+15%" in capsys.readouterr().out
