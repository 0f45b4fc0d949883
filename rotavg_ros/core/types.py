"""Array type aliases shared by every layer (defined once here)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

ProgressFn = Callable[[str], None]
"""Receives one progress line at a time."""
