"""The package's exceptions: one base, so callers can tell bad input from a bug.

The command line maps :class:`RotavgError` to exit status 2 with a one-line message; any
other exception is a bug and keeps its traceback.
"""

from __future__ import annotations


class RotavgError(Exception):
    """Base of every error this package raises on purpose."""


class InputError(RotavgError, ValueError):
    """Unusable input: a g2o, 1DSfM, bag or graph file, or a bad argument or option.

    The message names the file (and line where known). Also a ``ValueError``, so callers
    that caught the bare ``ValueError`` of earlier versions keep working.
    """


class SolverError(RotavgError):
    """The solver cannot run as asked (for example an unavailable torch device)."""
