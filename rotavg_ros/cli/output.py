"""How the command line talks: progress lines and warnings on stderr."""

from __future__ import annotations

import sys


def say(text: str) -> None:
    """A progress line: ``[rotavg] text``."""
    print(f"[rotavg] {text}", file=sys.stderr, flush=True)


def warn(text: str) -> None:
    """A warning: ``rotavg: warning: text``."""
    print(f"rotavg: warning: {text}", file=sys.stderr, flush=True)
