"""Solve results out: what the node publishes, built once over a message factory.

Conventions: the solver returns world-to-node rotations ``R_i``; outputs carry the
node-to-world rotation ``R_i^T`` (``header.frame_id = world_frame``, ``child_frame_id = i``).
"""

from __future__ import annotations

import math
from enum import IntEnum
from typing import Any

import numpy as np

from rotavg_ros.core.so3 import matrix_to_quat
from rotavg_ros.core.types import FloatArray, IntArray


class Level(IntEnum):
    """``diagnostic_msgs/DiagnosticStatus`` levels as ints (the message field is a byte).

    Re-exported by ``rotavg_ros.ros.messages``.
    """

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3



def node_to_world_quaternions(rotations: FloatArray) -> FloatArray:
    """``(N, 4)`` quaternions (x, y, z, w) of ``R_i^T`` for world-to-node ``rotations``."""
    R = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    return matrix_to_quat(np.swapaxes(R, 1, 2))


def grid_layout(component: IntArray, spacing: float = 1.0) -> FloatArray:
    """``(N, 3)`` marker positions: each component on its own square grid in the z=0 plane.

    Component 0 (the anchor's) starts at the origin; the next components follow along +x with
    a gap of two ``spacing``. Inside a component, nodes keep their index order row by row.
    """
    comp = np.asarray(component, dtype=np.int64).reshape(-1)
    pos = np.zeros((comp.size, 3))
    x0 = 0.0
    for label in np.unique(comp):
        idx = np.flatnonzero(comp == label)
        cols = max(1, math.ceil(math.sqrt(idx.size)))
        k = np.arange(idx.size)
        pos[idx, 0] = x0 + (k % cols) * spacing
        pos[idx, 1] = -(k // cols) * spacing
        x0 += (cols + 1) * spacing
    return pos


def format_diagnostic_value(value: Any) -> str:
    """Floats with 6 significant digits, booleans ``true``/``false``, lists comma-separated."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(format_diagnostic_value(v) for v in value)
    return str(value)
