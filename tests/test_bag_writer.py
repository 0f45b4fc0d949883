"""The replay's output bags as ROS tools read them: CRCs, Jazzy metadata, offered QoS.

Read back with the mcap library and mcap-ros2-support (independent of rosbags, which wrote
nothing here but the CDR bytes), with rosbags' rosbag2 reader, and compared with the QoS the
live ``rotavg_node`` offers.
"""

from __future__ import annotations

import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Chunk, DataEnd, Footer, Header
from mcap.stream_reader import CRCValidationError, StreamReader
from mcap_ros2.decoder import DecoderFactory
from rosbags.interfaces import ConnectionExtRosbag2
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from rotavg_ros.msg_adapters.outputs import orientation_markers
from ruamel.yaml import YAML

from rotavg_ros.io.bag_messages import MessageFactory
from rotavg_ros.io.bag_writer import OutputBag, output_topics

NODE = "rotavg_node"
LATCHED_TOPICS = {f"/{NODE}/orientations", f"/{NODE}/markers"}
T0 = 1_700_000_000_000_000_000


def _yaml(text: str) -> Any:
    return YAML(typ="safe").load(text)


def write_output_bag(path: Path, n_msgs: int = 300) -> Path:
    """An output bag with every topic; enough orientations for several zstd chunks."""
    factory = MessageFactory()
    bag = OutputBag(path, NODE, factory, chunk_size=4096)  # several chunks
    rng = np.random.default_rng(0)
    for k in range(n_msgs):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        bag.write("orientations", factory.transform("world", f"n{k}", q, T0 + k), T0 + k)
    tf = factory.tf_message([factory.transform("world", "n0", (0, 0, 0, 1), T0)])
    bag.write("tf", tf, T0 + n_msgs)
    header = factory.header("world", T0)
    bag.write("diagnostics", factory.diagnostic_array(header, [
        factory.diagnostic_status(0, "rotavg", "ok", "", [("solves", "1")])]), T0 + n_msgs)
    markers = orientation_markers(factory, ["n0", "n1"], np.stack([np.eye(3)] * 2),
                                  np.zeros(2, dtype=np.int64), ["n0"], "world", T0)
    bag.write("markers", markers, T0 + n_msgs)
    bag.close()
    return path


@pytest.fixture(scope="module")
def out_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_output_bag(tmp_path_factory.mktemp("bag") / "out")


def _mcap_file(bag: Path) -> Path:
    (file,) = bag.glob("*.mcap")
    return file


def test_chunk_data_and_summary_crcs_are_written_and_valid(out_bag: Path) -> None:
    with open(_mcap_file(out_bag), "rb") as fh:
        records = list(StreamReader(fh, validate_crcs=True, emit_chunks=True).records)
    chunks = [r for r in records if isinstance(r, Chunk)]
    assert len(chunks) >= 3
    for chunk in chunks:
        assert chunk.compression == "zstd"
        assert chunk.uncompressed_crc != 0
    (data_end,) = [r for r in records if isinstance(r, DataEnd)]
    (footer,) = [r for r in records if isinstance(r, Footer)]
    assert data_end.data_section_crc != 0 and footer.summary_crc != 0
    (header,) = [r for r in records if isinstance(r, Header)]
    assert header.profile == "ros2"


def _read_all(data: bytes, tmp_path: Path) -> int:
    path = tmp_path / "copy.mcap"
    path.write_bytes(data)
    with open(path, "rb") as fh:
        return sum(1 for _ in StreamReader(fh, validate_crcs=True).records)


def test_a_corrupted_byte_is_rejected_by_the_crcs(out_bag: Path, tmp_path: Path) -> None:
    """The intact file validates; a changed chunk CRC field, or one changed byte outside the
    chunks (the metadata record), fails validation."""
    data = _mcap_file(out_bag).read_bytes()
    assert _read_all(data, tmp_path) > 300
    with open(_mcap_file(out_bag), "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    start = summary.chunk_indexes[1].chunk_start_offset
    # Chunk: opcode(1) length(8) start(8) end(8) uncompressed_size(8), then uncompressed_crc
    crc_at = start + 1 + 8 + 8 + 8 + 8
    bad_chunk = bytearray(data)
    bad_chunk[crc_at] ^= 0x01
    with pytest.raises(CRCValidationError):
        _read_all(bytes(bad_chunk), tmp_path)
    at = data.index(b"ros_distro: jazzy")
    bad_data = bytearray(data)
    bad_data[at] = ord("R")
    with pytest.raises(CRCValidationError):
        _read_all(bytes(bad_data), tmp_path)


def test_metadata_yaml_is_jazzy_v9_with_offered_qos(out_bag: Path) -> None:
    info = _yaml((out_bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["version"] == 9 and info["ros_distro"] == "jazzy"
    assert info["storage_identifier"] == "mcap"
    assert info["relative_file_paths"] == [_mcap_file(out_bag).name]
    topics = {t["topic_metadata"]["name"]: t for t in info["topics_with_message_count"]}
    assert set(topics) == {t for t, _, _ in output_topics(NODE).values()}
    assert topics[f"/{NODE}/orientations"]["message_count"] == 300
    assert info["message_count"] == 303
    store = get_typestore(Stores.ROS2_JAZZY)
    for name, t in topics.items():
        meta = t["topic_metadata"]
        (qos,) = meta["offered_qos_profiles"]
        assert qos["reliability"] == "reliable"
        assert qos["durability"] == ("transient_local" if name in LATCHED_TOPICS
                                     else "volatile")
        assert qos["deadline"] == {"sec": 9223372036, "nsec": 854775807}
        assert meta["type_description_hash"] == store.hash_rihs01(meta["type"])


def test_mcap_carries_the_rosbag2_record_and_channel_qos(out_bag: Path) -> None:
    """What rosbag2's MCAP plugin reads from a lone .mcap: the ``rosbag2`` metadata record
    (serialized_metadata, ROS_DISTRO) and each channel's offered_qos_profiles string."""
    with open(_mcap_file(out_bag), "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        (meta,) = [m for m in reader.iter_metadata() if m.name == "rosbag2"]
        summary = reader.get_summary()
    assert meta.metadata["ROS_DISTRO"] == "jazzy"
    serialized = _yaml(meta.metadata["serialized_metadata"])
    assert serialized["ros_distro"] == "jazzy" and serialized["version"] == 9
    assert serialized["message_count"] == 303
    assert summary is not None
    store = get_typestore(Stores.ROS2_JAZZY)
    seen = set()
    for channel in summary.channels.values():
        schema = summary.schemas[channel.schema_id]
        assert channel.message_encoding == "cdr" and schema.encoding == "ros2msg"
        qos_text = channel.metadata["offered_qos_profiles"]
        assert isinstance(qos_text, str)
        (qos,) = _yaml(qos_text)
        assert qos["durability"] == ("transient_local" if channel.topic in LATCHED_TOPICS
                                     else "volatile")
        assert channel.metadata["topic_type_hash"] == store.hash_rihs01(schema.name)
        seen.add(channel.topic)
    assert LATCHED_TOPICS <= seen and len(seen) == 4


def test_messages_decode_with_mcap_ros2_and_rosbags_reads_the_qos(out_bag: Path) -> None:
    with open(_mcap_file(out_bag), "rb") as fh:
        reader = make_reader(fh, validate_crcs=True, decoder_factories=[DecoderFactory()])
        decoded = [(c.topic, m.log_time, msg) for _, c, m, msg in reader.iter_decoded_messages()]
    orient = [(t, msg) for topic, t, msg in decoded if topic == f"/{NODE}/orientations"]
    assert len(orient) == 300
    assert [msg.child_frame_id for _, msg in orient[:3]] == ["n0", "n1", "n2"]
    q = orient[0][1].transform.rotation
    assert abs(np.linalg.norm([q.x, q.y, q.z, q.w]) - 1.0) < 1e-12
    (markers,) = [msg for topic, _, msg in decoded if topic == f"/{NODE}/markers"]
    assert len(markers.markers) >= 2

    with Reader(out_bag) as bag:
        assert bag.message_count == 303
        durability = {c.topic: c.ext.offered_qos_profiles[0].durability.name
                      for c in bag.connections if isinstance(c.ext, ConnectionExtRosbag2)}
    assert durability == {t: ("TRANSIENT_LOCAL" if t in LATCHED_TOPICS else "VOLATILE")
                          for t, _, _ in output_topics(NODE).values()}


def test_bag_qos_matches_what_the_node_offers() -> None:
    """The live node's publishers offer the reliability and durability the bag records."""
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
    from ros_fixtures import RosHarness, wait_until

    from rotavg_ros.ros.node import RotavgNode

    with RosHarness() as h:
        node = h.add(RotavgNode(context=h.context, namespace=h.namespace))
        h.start()
        ns = h.namespace
        checked = 0
        for key, (topic, _, qos) in output_topics(NODE).items():
            if key == "tf":
                continue  # the node publishes no /tf (the replay adds it for RViz)
            live = topic if topic == "/diagnostics" else ns + topic
            def offered(t: str = live) -> bool:
                return bool(node.get_publishers_info_by_topic(t))

            assert wait_until(offered, 5.0)
            (info,) = [i for i in node.get_publishers_info_by_topic(live)
                       if i.node_name == NODE and i.node_namespace == ns]
            profile = info.qos_profile
            assert profile.reliability == ReliabilityPolicy.RELIABLE
            want = (DurabilityPolicy.TRANSIENT_LOCAL if qos.durability == "transient_local"
                    else DurabilityPolicy.VOLATILE)
            assert profile.durability == want, (topic, profile.durability)
            checked += 1
    assert checked == 3


def test_zlib_crc_of_a_chunk_matches_its_content(out_bag: Path) -> None:
    """The chunk CRC is the CRC-32 of the decompressed records (the MCAP definition)."""
    import zstandard

    with open(_mcap_file(out_bag), "rb") as fh:
        records = list(StreamReader(fh, emit_chunks=True).records)
    chunk = next(r for r in records if isinstance(r, Chunk))
    raw = zstandard.ZstdDecompressor().decompress(chunk.data,
                                                  max_output_size=chunk.uncompressed_size)
    assert zlib.crc32(raw) == chunk.uncompressed_crc
