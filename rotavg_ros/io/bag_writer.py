"""rosbag2 MCAP writer for the node's outputs (rosbags' writer, Jazzy typestore, zstd)."""

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


class OutputBag:
    """rosbag2 MCAP writer for the node's outputs (rosbags, Jazzy typestore)."""

    def __init__(self, path: Path, node_name: str, factory: MessageFactory,
                 overwrite: bool = False) -> None:
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

        if path.exists():
            if not overwrite:
                raise InputError(f"{path} exists; pass --overwrite to replace it")
            if not (path / "metadata.yaml").is_file():
                raise InputError(f"{path} exists and is not a rosbag2 bag; not replacing it")
            shutil.rmtree(path)
        self.factory = factory
        self.writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        self.writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self.writer.open()
        store = factory.typestore
        self.conns = {
            "orientations": self.writer.add_connection(
                f"/{node_name}/orientations", TRANSFORM_STAMPED, typestore=store),
            "tf": self.writer.add_connection("/tf", TF_MESSAGE, typestore=store),
            "markers": self.writer.add_connection(
                f"/{node_name}/markers", MARKER_ARRAY, typestore=store),
            "diagnostics": self.writer.add_connection(
                "/diagnostics", DIAGNOSTIC_ARRAY, typestore=store),
        }
        self.counts: Counter[str] = Counter()

    def write(self, key: str, msg: Any, time_ns: int) -> None:
        self.writer.write(self.conns[key], int(time_ns), self.factory.serialize(msg))
        self.counts[key] += 1

    def close(self) -> None:
        self.writer.close()
