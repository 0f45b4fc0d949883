"""Read rosbag2 MCAP bags robustly, without ROS: rosbags first, record by record if that fails.

:func:`open_bag` accepts a rosbag2 directory (``metadata.yaml`` + ``.mcap`` files) or a lone
``.mcap`` file and returns a :class:`BagSource`:

* Normally it is read with ``rosbags.rosbag2.Reader`` (indexed, messages in log-time order).
* If rosbags cannot open it (truncated file: no footer/summary, broken ``metadata.yaml``, an
  MCAP whose profile is not ``ros2``, ...), every ``.mcap`` file is read with the ``mcap``
  library's non-seeking :class:`~mcap.stream_reader.StreamReader`, record by record, with CRC
  checks, stopping at the first bad record; what was read before it is used (sorted by log
  time). The same happens if rosbags' index is inconsistent (its topics hold fewer messages
  than its total: a damaged summary), and if rosbags fails in the middle of the bag or
  delivers fewer messages of a topic than indexed: the stream reader then delivers what
  rosbags had not delivered.
* Messages are decoded with a rosbags typestore: the Jazzy store plus the message definitions
  stored in the bag (types unknown to Jazzy are registered; a topic whose stored definition
  differs from Jazzy's gets its own store built from the bag's definition).

Nothing here raises for bad content except :class:`BagError` (nothing readable at all);
problems are collected in :attr:`BagSource.problems` as one-line texts for the report.
"""

from __future__ import annotations

import contextlib
from collections import Counter
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rosbags.interfaces import MessageDefinitionFormat
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from rotavg_ros.errors import InputError

MAX_RECORD_BYTES = 1 << 30
MCAP_MAGIC = b"\x89MCAP0\r\n"


class BagError(InputError):
    """The path is not a readable bag (nothing at all could be read)."""


class DecodeError(Exception):
    """One message could not be deserialised."""


@dataclass(frozen=True)
class BagRecord:
    """One serialised message: topic, type, log time (ns) and CDR bytes."""

    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes


@dataclass
class BagSource:
    """An opened bag; iterate with :meth:`read`, decode with :meth:`decode`."""

    path: Path
    reader: str
    """``rosbags`` or ``mcap stream reader`` (the fallback)."""
    topics: dict[str, str]
    """topic -> message type (the first one seen if a topic has several)."""
    counts: dict[str, int]
    """Messages per topic according to the bag's index (fallback: as read)."""
    declared: dict[str, int]
    """Messages per topic the bag claims to hold (index or ``metadata.yaml``; fallback
    without a readable ``metadata.yaml``: as read)."""
    start_ns: int | None
    problems: list[str] = field(default_factory=list)
    _stores: dict[str, Typestore] = field(default_factory=dict, repr=False)
    _store: Typestore | None = field(default=None, repr=False)
    _rosbags: Reader | None = field(default=None, repr=False)
    _files: list[Path] = field(default_factory=list, repr=False)
    _records: list[BagRecord] | None = field(default=None, repr=False)

    @property
    def message_count(self) -> int:
        return int(sum(self.counts.values()))

    def count(self, topics: Collection[str]) -> int:
        return int(sum(self.counts.get(t, 0) for t in topics))

    # ------------------------------------------------------------------ reading
    def read(self, topics: Collection[str]) -> Iterator[BagRecord]:
        """Records of ``topics`` in log-time order (ties: bag order); never raises for a
        damaged bag, it records the problem and stops.

        With rosbags, if it fails in the middle or delivers fewer messages of a topic than
        the index declares (a damaged chunk without CRC, a damaged summary), the files are
        also read record by record and the records rosbags did not deliver follow, late and
        in their own log-time order."""
        wanted = set(topics)
        if self._records is not None:
            yield from (r for r in self._records if r.topic in wanted)
            return
        assert self._rosbags is not None
        connections = [c for c in self._rosbags.connections if c.topic in wanted]
        last_time: int | None = None
        delivered: Counter[tuple[str, int, int]] = Counter()
        per_topic: Counter[str] = Counter()
        try:
            if connections:
                for conn, t, data in self._rosbags.messages(connections=connections):
                    raw = bytes(data)
                    last_time = t
                    delivered[(conn.topic, int(t), hash(raw))] += 1
                    per_topic[conn.topic] += 1
                    yield BagRecord(conn.topic, conn.msgtype, int(t), raw)
        except Exception as exc:  # noqa: BLE001 - a damaged bag: report and fall back
            where = "" if last_time is None else f" after bag time {last_time / 1e9:.3f} s"
            self.problems.append(
                f"rosbags stopped reading{where}: {_describe(exc)}; reading the rest record "
                f"by record with the mcap stream reader")
        else:
            short = {t: n for t in sorted(wanted)
                     if per_topic[t] < (n := self.counts.get(t, 0))}
            if not short:
                return
            self.problems.append(
                "rosbags delivered fewer messages than the index declares ("
                + ", ".join(f"{t}: {per_topic[t]} of {n}" for t, n in short.items())
                + "); reading the bag record by record with the mcap stream reader for the "
                "missing ones")
        extra = 0
        for rec in _scan_files(self._files, self.problems).records:
            if rec.topic not in wanted:
                continue
            key = (rec.topic, rec.log_time_ns, hash(rec.data))
            if delivered[key] > 0:
                delivered[key] -= 1
                continue
            extra += 1
            yield rec
        self.problems.append(f"the mcap stream reader found {extra} message(s) of "
                             f"{', '.join(sorted(wanted))} that rosbags had not delivered")

    # ------------------------------------------------------------------ decoding
    def decode(self, record: BagRecord) -> Any:
        """Deserialise ``record`` (raises :class:`DecodeError` with a one-line reason)."""
        store = self._stores.get(record.topic, self._store)
        assert store is not None
        if record.msgtype not in store.types:
            raise DecodeError(f"unknown message type {record.msgtype!r} (no definition in the "
                              "bag or in the Jazzy typestore)")
        try:
            return store.deserialize_cdr(record.data, record.msgtype)
        except Exception as exc:  # noqa: BLE001 - any failure is a malformed message
            raise DecodeError(_describe(exc)) from None

    def close(self) -> None:
        if self._rosbags is not None:
            with contextlib.suppress(Exception):
                self._rosbags.close()
            self._rosbags = None

    def __enter__(self) -> BagSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _describe(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or "no details"  # one line
    return f"{type(exc).__name__}: {text}"[:300]


def _register(store: Typestore, stores: dict[str, Typestore], topic: str, msgtype: str,
              msgdef_format: Any, msgdef: str, problems: list[str]) -> None:
    """Register the types of one stored definition (own store for a topic on conflict)."""
    if not msgdef.strip():
        return
    try:
        if msgdef_format == MessageDefinitionFormat.IDL:
            types = get_types_from_idl(msgdef)
        else:
            types = get_types_from_msg(msgdef, msgtype)
    except Exception as exc:  # noqa: BLE001
        if msgtype not in store.types:
            problems.append(f"{topic}: cannot parse the stored definition of {msgtype} "
                            f"({_describe(exc)})")
        return
    try:
        store.register(types)
    except Exception:  # noqa: BLE001 - differs from Jazzy's definition: use the bag's
        own = get_typestore(Stores.EMPTY)
        try:
            own.register(types)
        except Exception as exc:  # noqa: BLE001
            problems.append(f"{topic}: cannot use the stored definition of {msgtype} "
                            f"({_describe(exc)})")
            return
        stores[topic] = own
        problems.append(f"{topic}: the bag's definition of {msgtype} differs from Jazzy's; "
                        "decoding with the bag's")


def _metadata(path: Path) -> dict[str, Any]:
    """``rosbag2_bagfile_information`` of a bag directory, or {} if absent/unreadable."""
    meta = path / "metadata.yaml"
    if not path.is_dir() or not meta.is_file():
        return {}
    try:
        from ruamel.yaml import YAML

        info = YAML(typ="safe").load(meta.read_text())["rosbag2_bagfile_information"]
        return info if isinstance(info, dict) else {}
    except Exception:  # noqa: BLE001
        return {}


def _metadata_counts(path: Path) -> dict[str, int]:
    try:
        return {str(t["topic_metadata"]["name"]): int(t["message_count"])
                for t in _metadata(path).get("topics_with_message_count", [])}
    except Exception:  # noqa: BLE001
        return {}


def _storage_files(path: Path) -> list[Path]:
    """The ``.mcap`` files of a bag directory (per ``metadata.yaml`` if readable) or file."""
    if path.is_file():
        return [path]
    files: list[Path] = []
    try:
        files = [path / Path(str(p)).name
                 for p in _metadata(path).get("relative_file_paths", [])]
        files = [f for f in files if f.is_file() and f.suffix == ".mcap"]
    except Exception:  # noqa: BLE001 - fall back to the directory listing
        files = []
    return files or sorted(path.glob("*.mcap"))


def _loose_mcap_files(path: Path) -> list[Path]:
    """The ``.mcap`` files of a directory without ``metadata.yaml`` (else [])."""
    if not path.is_dir() or (path / "metadata.yaml").exists():
        return []
    return sorted(f for f in path.glob("*.mcap") if f.is_file())


@dataclass
class _Scan:
    topics: dict[str, str] = field(default_factory=dict)
    schemas: dict[str, tuple[str, str, bytes]] = field(default_factory=dict)
    """topic -> (type name, schema encoding, schema data)"""
    records: list[BagRecord] = field(default_factory=list)


def _scan_files(files: list[Path], problems: list[str]) -> _Scan:
    """Stream-read every file, stopping at the first bad record of each; records come back
    sorted by log time (stable: ties keep file order)."""
    from mcap.exceptions import EndOfFile
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    scan = _Scan()
    for file in files:
        schemas: dict[int, Any] = {}
        channels: dict[int, tuple[str, str]] = {}
        before = len(scan.records)
        with open(file, "rb") as fh:
            reader = StreamReader(fh, validate_crcs=True, record_size_limit=MAX_RECORD_BYTES)
            try:
                for rec in reader.records:
                    if isinstance(rec, Message):
                        if rec.channel_id in channels:
                            topic, msgtype = channels[rec.channel_id]
                            scan.records.append(
                                BagRecord(topic, msgtype, rec.log_time, bytes(rec.data)))
                    elif isinstance(rec, Schema):
                        schemas[rec.id] = rec
                    elif isinstance(rec, Channel):
                        schema = schemas.get(rec.schema_id)
                        msgtype = schema.name if schema is not None else ""
                        if rec.message_encoding != "cdr":
                            problems.append(f"{rec.topic}: message encoding "
                                            f"{rec.message_encoding!r} is not CDR; skipped")
                            continue
                        channels[rec.id] = (rec.topic, msgtype)
                        scan.topics.setdefault(rec.topic, msgtype)
                        if schema is not None:
                            scan.schemas.setdefault(
                                rec.topic, (schema.name, schema.encoding, bytes(schema.data)))
            except Exception as exc:  # noqa: BLE001 - stop at the first bad record
                size = file.stat().st_size
                what = ("the file ends inside a record (truncated)"
                        if isinstance(exc, EndOfFile) else _describe(exc))
                problems.append(
                    f"{file.name}: stopped at byte {min(fh.tell(), size)} of {size}: {what}; "
                    f"{len(scan.records) - before} message(s) before it were read, the rest "
                    "of the file is lost")
    scan.records.sort(key=lambda r: r.log_time_ns)
    return scan


def _has_mcap_magic(file: Path) -> bool:
    try:
        with open(file, "rb") as fh:
            return fh.read(8) == MCAP_MAGIC
    except OSError:
        return False


def _rosbags_source(path: Path, reader: Reader, store: Typestore,
                    stores: dict[str, Typestore], problems: list[str]) -> BagSource:
    topics: dict[str, str] = {}
    counts: dict[str, int] = {}
    for conn in reader.connections:
        topics.setdefault(conn.topic, conn.msgtype)
        counts[conn.topic] = counts.get(conn.topic, 0) + int(conn.msgcount)
        if conn.msgtype != topics[conn.topic]:
            problems.append(f"{conn.topic}: several message types ({topics[conn.topic]}, "
                            f"{conn.msgtype}); using {topics[conn.topic]}")
        _register(store, stores, conn.topic, conn.msgtype, conn.msgdef.format,
                  conn.msgdef.data, problems)
    start = reader.start_time if reader.message_count else None
    return BagSource(path, "rosbags", topics, counts, dict(counts), start, problems,
                     stores, store, reader, _storage_files(path))


def open_bag(path: str | Path, merge_mcap_files: bool = False) -> BagSource:
    """Open a rosbag2 directory or a lone ``.mcap`` (see the module docstring).

    A directory without ``metadata.yaml`` that holds several ``.mcap`` files is refused
    (they may be unrelated recordings) unless ``merge_mcap_files``: then they are read as
    one bag, in log-time order.
    """
    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such file or directory")
    loose = _loose_mcap_files(path)
    if len(loose) > 1 and not merge_mcap_files:
        names = ", ".join(f.name for f in loose[:5]) + (", ..." if len(loose) > 5 else "")
        raise BagError(
            f"{path}: no metadata.yaml, and {len(loose)} .mcap files ({names}) that may be "
            "separate recordings; replay one file, or pass --merge-mcap-files to read them "
            "all as one bag")
    store = get_typestore(Stores.ROS2_JAZZY)
    stores: dict[str, Typestore] = {}
    problems: list[str] = []
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # noqa: BLE001 - fall back to the stream reader
        reason = _describe(exc)
    else:
        indexed = sum(int(conn.msgcount) for conn in reader.connections)
        if indexed < reader.message_count:  # e.g. a damaged Channel record in the summary
            reason = (f"its index is inconsistent: its topics hold {indexed} of its "
                      f"{reader.message_count} messages")
            with contextlib.suppress(Exception):
                reader.close()
        else:
            return _rosbags_source(path, reader, store, stores, problems)

    files = _storage_files(path)
    if not files:
        raise BagError(f"{path}: not a rosbag2 bag ({reason}) and no .mcap file to read")
    if not any(_has_mcap_magic(f) for f in files):
        names = ", ".join(f.name for f in files)
        raise BagError(f"{path}: not an MCAP bag ({reason}; {names}: no MCAP magic)")
    problems.append(f"rosbags could not open the bag ({reason}); reading it record by "
                    "record with the mcap stream reader")
    if len(loose) > 1:
        problems.append(f"no metadata.yaml: read its {len(loose)} .mcap files as one bag "
                        "(--merge-mcap-files)")
    scan = _scan_files(files, problems)
    for topic, (name, encoding, data) in scan.schemas.items():
        if encoding in ("ros2msg", "ros2idl"):
            fmt = (MessageDefinitionFormat.IDL if encoding == "ros2idl"
                   else MessageDefinitionFormat.MSG)
            _register(store, stores, topic, name, fmt, data.decode("utf-8", "replace"),
                      problems)
    counts = {topic: 0 for topic in scan.topics}
    for rec in scan.records:
        counts[rec.topic] += 1
    start = scan.records[0].log_time_ns if scan.records else None
    declared = {**counts, **_metadata_counts(path)}
    return BagSource(path, "mcap stream reader", scan.topics, counts, declared, start,
                     problems, stores, store, None, files, scan.records)
