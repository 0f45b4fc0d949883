"""Shared pytest fixtures: the read-only benchmark data folder ``shared/``."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:  # the package is not installed in the venv
    sys.path.insert(0, str(REPO_ROOT))


def find_shared_dir() -> Path | None:
    """``<repo>/../shared`` if it has ``data/``, else ``$ROTAVG_SHARED``, else None."""
    candidates = [REPO_ROOT.parent / "shared"]
    if os.environ.get("ROTAVG_SHARED"):
        candidates.append(Path(os.environ["ROTAVG_SHARED"]))
    return next((c for c in candidates if (c / "data").is_dir()), None)


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    found = find_shared_dir()
    if found is None:
        pytest.skip("shared benchmark data not found: expected ../shared next to the repo "
                    "or a folder in $ROTAVG_SHARED containing data/")
    return found


@pytest.fixture
def single_torch_thread() -> Iterator[None]:
    """One torch thread: solver tests use tiny problems, and two spinning OpenMP threads on a
    shared 2-core machine are several times slower than one. Restored afterwards."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
