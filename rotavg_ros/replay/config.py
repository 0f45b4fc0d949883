"""What a replay is asked to do: the bag, the node's settings, outputs, and exit statuses."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path

from rotavg_ros.app.parameters import NODE_NAME, Settings
from rotavg_ros.io.bag_messages import TF_MESSAGE, TRANSFORM_STAMPED

ODOMETRY = "nav_msgs/msg/Odometry"
EDGE_TYPES = (TRANSFORM_STAMPED, ODOMETRY, TF_MESSAGE)
DEFAULT_GT_TOPIC = "/ground_truth"
NOT_BY_DEFAULT = ("/tf", "/tf_static")
UNDECODABLE = "undecodable_message"
EMPTY_TF = "empty_tf_message"



class ExitStatus(IntEnum):
    """Exit status of ``rotavg replay``."""

    OK = 0
    NOTHING_USABLE = 1
    """No edge was accepted from the bag."""
    INPUT = 2
    """Unusable input (no such bag, not a bag, bad arguments)."""
    SOLVE_FAILED = 3
    """The last solve failed."""


EXIT_OK = ExitStatus.OK
EXIT_NOTHING_USABLE = ExitStatus.NOTHING_USABLE
EXIT_INPUT = ExitStatus.INPUT
EXIT_SOLVE_FAILED = ExitStatus.SOLVE_FAILED


@dataclass
class ReplayConfig:
    """Everything ``rotavg replay`` needs besides the solver function."""

    bag: Path
    settings: Settings
    repeat_policy: str = "merge"
    solve_period: float | None = None
    """Seconds of bag time between timer ticks; None = solve once at the end."""
    output: Path | None = None
    overwrite: bool = False
    output_g2o: Path | None = None
    gt_topic: str = DEFAULT_GT_TOPIC
    edge_topics: list[str] | None = None
    merge_mcap_files: bool = False
    """A directory without metadata.yaml and with several .mcap files: read them as one bag
    (refused otherwise)."""
    node_name: str = NODE_NAME
    quiet: bool = False
    progress: bool | None = None
    """Show the progress bar: None = when stderr is a TTY and not quiet."""
