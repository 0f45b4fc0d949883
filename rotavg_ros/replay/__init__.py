"""Offline replay: a recorded rosbag2 bag through the node's own pipeline, without ROS.

The engine (:mod:`.engine`) feeds the bag's edge messages, in log-time order, through the
same adapters, accumulator, solve session and diagnostics as ``rotavg_node``, and writes what
the node would publish to an output bag. :mod:`.report` is what it did; :mod:`.config` what
it was asked. The command line is ``rotavg replay`` (:mod:`rotavg_ros.cli.replay`).
"""

from rotavg_ros.replay.config import (
    EXIT_INPUT,
    EXIT_NOTHING_USABLE,
    EXIT_OK,
    EXIT_SOLVE_FAILED,
    ExitStatus,
    ReplayConfig,
)
from rotavg_ros.replay.engine import Replayer, run_replay
from rotavg_ros.replay.report import ReplayReport, TopicRole

__all__ = [
    "EXIT_INPUT",
    "EXIT_NOTHING_USABLE",
    "EXIT_OK",
    "EXIT_SOLVE_FAILED",
    "ExitStatus",
    "ReplayConfig",
    "ReplayReport",
    "Replayer",
    "TopicRole",
    "run_replay",
]
