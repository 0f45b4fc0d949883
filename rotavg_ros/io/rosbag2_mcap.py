"""Write a rosbag2 bag (metadata version 9, as ROS 2 Jazzy writes it) with the mcap library.

rosbags' writer leaves the MCAP CRCs at zero, names ``ros_distro: rosbags`` and stores no
topic type hash in the channels. This writer keeps everything a Jazzy ``ros2 bag`` reads:

* the ``.mcap`` (profile ``ros2``, zstd chunks) carries chunk CRCs, the data-section CRC and
  the summary CRC;
* every channel's metadata holds ``offered_qos_profiles`` (a YAML string, policy names as in
  metadata version 9) and ``topic_type_hash`` (RIHS01), as rosbag2's MCAP plugin writes them;
* a ``rosbag2`` metadata record holds ``serialized_metadata`` (the bag's metadata as YAML)
  and ``ROS_DISTRO``, and ``metadata.yaml`` holds the same metadata, so the bag reads the
  same as a directory or as a lone ``.mcap``.

Messages are given already serialised (CDR); definitions and hashes come from a rosbags
typestore. ``ros2 bag play`` offers each topic the recorded reliability and durability, so a
topic recorded ``transient_local`` is replayed latched.
"""

from __future__ import annotations

from dataclasses import dataclass
from io import StringIO
from pathlib import Path
from typing import IO, Any

from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.typesys.store import Typestore
from ruamel.yaml import YAML

ROS_DISTRO = "jazzy"
METADATA_VERSION = 9
# RMW_DURATION_INFINITE, as rosbag2 records an unset deadline / lifespan / lease duration.
INFINITE = {"sec": 9223372036, "nsec": 854775807}


@dataclass(frozen=True)
class OfferedQos:
    """One publisher's offered QoS as rosbag2 records it (version 9: policy names).

    A recording sees what DDS discovery reports: reliability, durability and liveliness;
    history and depth are not part of it (``unknown``, 0), and playback uses its own.
    """

    reliability: str = "reliable"
    durability: str = "volatile"
    history: str = "unknown"
    depth: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {
            "history": self.history, "depth": self.depth,
            "reliability": self.reliability, "durability": self.durability,
            "deadline": dict(INFINITE), "lifespan": dict(INFINITE),
            "liveliness": "automatic", "liveliness_lease_duration": dict(INFINITE),
            "avoid_ros_namespace_conventions": False,
        }


def dump_yaml(data: Any) -> str:
    """Block-style YAML (ruamel, as rosbags writes its metadata)."""
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    out = StringIO()
    yaml.dump(data, out)
    return out.getvalue()


def qos_yaml(profiles: list[OfferedQos]) -> str:
    """``offered_qos_profiles`` of an MCAP channel: the profile list as a YAML string."""
    return dump_yaml([p.as_dict() for p in profiles]).strip()


@dataclass
class _Topic:
    name: str
    msgtype: str
    type_hash: str
    qos: list[OfferedQos]
    channel_id: int
    count: int = 0


class Rosbag2McapWriter:
    """A rosbag2 directory ``path`` holding ``metadata.yaml`` and ``<name>_0.mcap``."""

    def __init__(self, path: Path, typestore: Typestore, *, ros_distro: str = ROS_DISTRO,
                 chunk_size: int = 1 << 20) -> None:
        path.mkdir(parents=True)
        self.path = path
        self.file = path / f"{path.name}_0.mcap"
        self.typestore = typestore
        self.ros_distro = ros_distro
        self._fh: IO[bytes] = open(self.file, "wb")  # noqa: SIM115 - closed in close()
        self._mcap = McapWriter(self._fh, chunk_size=chunk_size,
                                compression=CompressionType.ZSTD, enable_crcs=True,
                                enable_data_crcs=True)
        self._mcap.start(profile="ros2", library="rotavg_ros (mcap python)")
        self._schemas: dict[str, int] = {}
        self._topics: dict[int, _Topic] = {}
        self._t_min: int | None = None
        self._t_max = 0

    def add_topic(self, topic: str, msgtype: str, qos: list[OfferedQos]) -> int:
        """Register ``topic`` (CDR) with its offered QoS; returns the id to :meth:`write`."""
        if msgtype not in self._schemas:
            msgdef, _ = self.typestore.generate_msgdef(msgtype, ros_version=2)
            encoding = "ros2idl" if msgdef.startswith("=" * 80 + "\nIDL: ") else "ros2msg"
            self._schemas[msgtype] = self._mcap.register_schema(
                msgtype, encoding, msgdef.encode())
        type_hash = self.typestore.hash_rihs01(msgtype)
        channel_id = self._mcap.register_channel(
            topic, "cdr", self._schemas[msgtype],
            {"offered_qos_profiles": qos_yaml(qos), "topic_type_hash": type_hash})
        self._topics[channel_id] = _Topic(topic, msgtype, type_hash, list(qos), channel_id)
        return channel_id

    def write(self, channel_id: int, time_ns: int, data: bytes) -> None:
        """One serialised message, logged and published at ``time_ns``."""
        topic = self._topics[channel_id]
        self._mcap.add_message(channel_id, log_time=time_ns, data=data,
                               publish_time=time_ns, sequence=topic.count)
        topic.count += 1
        self._t_min = time_ns if self._t_min is None else min(self._t_min, time_ns)
        self._t_max = max(self._t_max, time_ns)

    def metadata(self) -> dict[str, Any]:
        """The bag's ``rosbag2_bagfile_information`` (what metadata.yaml holds)."""
        start = self._t_min or 0
        duration = self._t_max - start if self._t_min is not None else 0
        count = sum(t.count for t in self._topics.values())
        return {
            "version": METADATA_VERSION,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": count,
            "topics_with_message_count": [
                {"topic_metadata": {
                    "name": t.name, "type": t.msgtype, "serialization_format": "cdr",
                    "offered_qos_profiles": [q.as_dict() for q in t.qos],
                    "type_description_hash": t.type_hash},
                 "message_count": t.count}
                for t in self._topics.values()],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [self.file.name],
            "files": [{"path": self.file.name,
                       "starting_time": {"nanoseconds_since_epoch": start},
                       "duration": {"nanoseconds": duration},
                       "message_count": count}],
            "custom_data": None,
            "ros_distro": self.ros_distro,
        }

    def close(self) -> None:
        """Write the ``rosbag2`` metadata record, the summary and ``metadata.yaml``."""
        info = self.metadata()
        self._mcap.add_metadata("rosbag2", {"serialized_metadata": dump_yaml(info),
                                            "ROS_DISTRO": self.ros_distro})
        self._mcap.finish()
        self._fh.close()
        tmp = self.path / "metadata.yaml.tmp"
        tmp.write_text(dump_yaml({"rosbag2_bagfile_information": info}), encoding="utf-8")
        tmp.replace(self.path / "metadata.yaml")
