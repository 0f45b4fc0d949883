"""The solver's threads: independent work side by side, with the same results."""

from __future__ import annotations

import contextvars
import threading

import pytest

from rotavg_ros.core.threads import PARALLEL_MIN_EDGES, map_in_threads, verify_workers

_LABEL: contextvars.ContextVar[str] = contextvars.ContextVar("_LABEL", default="unset")


def test_map_in_threads_keeps_order_and_context_and_raises() -> None:
    token = _LABEL.set("caller's")
    try:
        seen: list[tuple[int, str, int]] = []

        def work(x: int) -> int:
            seen.append((x, _LABEL.get(), threading.get_ident()))
            return x * x

        assert map_in_threads(work, range(6), workers=3) == [0, 1, 4, 9, 16, 25]
        assert {label for _, label, _ in seen} == {"caller's"}
        assert any(ident != threading.get_ident() for _, _, ident in seen)
        seen.clear()
        assert map_in_threads(work, [7], workers=3) == [49]  # one item: the caller's thread
        assert seen[0][2] == threading.get_ident()
    finally:
        _LABEL.reset(token)

    def fail(x: int) -> int:
        if x == 2:
            raise FloatingPointError("diverged")
        return x

    with pytest.raises(FloatingPointError, match="diverged"):
        map_in_threads(fail, range(4), workers=2)


def test_verify_workers_by_graph_size() -> None:
    assert verify_workers(PARALLEL_MIN_EDGES - 1, None) == 1
    assert verify_workers(PARALLEL_MIN_EDGES - 1, 4) == 1
    assert verify_workers(PARALLEL_MIN_EDGES, 3) == 3
    assert verify_workers(PARALLEL_MIN_EDGES, None) >= 1
