"""rosbag2 MCAP writer for the node's outputs (Jazzy metadata, CRCs, offered QoS per topic).

The bag holds what ``rotavg_node`` publishes, with the QoS it offers, so that ``ros2 bag
play`` republishes ``~/orientations`` and ``~/markers`` transient-local (latched) as the node
does; ``/tf`` (for RViz / Foxglove; the node itself publishes no ``/tf``) and
``/diagnostics`` are volatile. Writing: :mod:`rotavg_ros.io.rosbag2_mcap`; serialisation:
:mod:`rotavg_ros.io.bag_messages` (rosbags, Jazzy typestore).
"""

from __future__ import annotations

import shutil
from collections import Counter
from pathlib import Path
from typing import Any

from rotavg_ros.errors import InputError
from rotavg_ros.io.bag_messages import (
    DIAGNOSTIC_ARRAY,
    MARKER_ARRAY,
    TF_MESSAGE,
    TRANSFORM_STAMPED,
    MessageFactory,
)
from rotavg_ros.io.rosbag2_mcap import OfferedQos, Rosbag2McapWriter

LATCHED = OfferedQos(reliability="reliable", durability="transient_local")
VOLATILE = OfferedQos(reliability="reliable", durability="volatile")


def output_topics(node_name: str) -> dict[str, tuple[str, str, OfferedQos]]:
    """key -> (topic, type, offered QoS) of the outputs, as ``rotavg_node`` offers them."""
    return {
        "orientations": (f"/{node_name}/orientations", TRANSFORM_STAMPED, LATCHED),
        "tf": ("/tf", TF_MESSAGE, VOLATILE),
        "markers": (f"/{node_name}/markers", MARKER_ARRAY, LATCHED),
        "diagnostics": ("/diagnostics", DIAGNOSTIC_ARRAY, VOLATILE),
    }


class OutputBag:
    """rosbag2 MCAP bag of the node's outputs (see the module docstring)."""

    def __init__(self, path: Path, node_name: str, factory: MessageFactory,
                 overwrite: bool = False, chunk_size: int = 1 << 20) -> None:
        if path.exists():
            if not overwrite:
                raise InputError(f"{path} exists; pass --overwrite to replace it")
            if not (path / "metadata.yaml").is_file():
                raise InputError(f"{path} exists and is not a rosbag2 bag; not replacing it")
            shutil.rmtree(path)
        self.factory = factory
        self.writer = Rosbag2McapWriter(path, factory.typestore, chunk_size=chunk_size)
        self.conns = {key: self.writer.add_topic(topic, msgtype, [qos])
                      for key, (topic, msgtype, qos) in output_topics(node_name).items()}
        self.counts: Counter[str] = Counter()

    def write(self, key: str, msg: Any, time_ns: int) -> None:
        self.writer.write(self.conns[key], int(time_ns), self.factory.serialize(msg))
        self.counts[key] += 1

    def close(self) -> None:
        self.writer.close()
