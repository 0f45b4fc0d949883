"""The replay's one-line progress bar on a terminal (messages read so far)."""

from __future__ import annotations

import math
import time
from typing import TextIO


class ProgressBar:
    """``\\r[#####     ]  52% 10400/20000 msgs`` on a TTY, at most ~10 redraws a second.

    Plain text (carriage return and spaces, no terminal escapes); :meth:`clear` erases it
    before another line is printed.
    """

    def __init__(self, total: int | None, stream: TextIO, enabled: bool,
                 width: int = 30, min_interval: float = 0.1) -> None:
        self.total = total if total else None
        self.stream = stream
        self.enabled = enabled
        self.width = width
        self.min_interval = min_interval
        self.done = 0
        self.extra = ""
        self._last = -math.inf
        self._shown = False
        self._width_shown = 0

    def text(self) -> str:
        if self.total:
            frac = min(1.0, self.done / self.total)
            filled = int(round(frac * self.width))
            bar = "#" * filled + " " * (self.width - filled)
            text = f"[{bar}] {frac * 100:3.0f}% {self.done}/{self.total} msgs"
        else:
            text = f"{self.done} msgs"
        return f"{text}  {self.extra}".rstrip()

    def update(self, done: int, extra: str | None = None, force: bool = False) -> None:
        self.done = done
        if extra is not None:
            self.extra = extra
        if not self.enabled:
            return
        now = time.monotonic()
        if force or now - self._last >= self.min_interval:
            self._last = now
            text = self.text()
            self.stream.write("\r" + text + " " * max(0, self._width_shown - len(text)))
            self.stream.flush()
            self._width_shown = len(text)
            self._shown = True

    def clear(self) -> None:
        """Erase the bar (before printing a line); the next update redraws it."""
        if self.enabled and self._shown:
            self.stream.write("\r" + " " * self._width_shown + "\r")
            self.stream.flush()
            self._shown = False
            self._width_shown = 0
            self._last = -math.inf

    def finish(self) -> None:
        if self.enabled:
            self.update(self.done, force=True)
            self.stream.write("\n")
            self.stream.flush()
            self._shown = False


def isatty(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False
