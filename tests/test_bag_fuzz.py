"""Fuzzing the bag reader (issue #5, item 4): truncated and bit-flipped copies of a committed
sample bag, a bounded and deterministic set of cases.

Two bags, both built from ``bags/smallgrid3d_odom`` (``/ground_truth`` TransformStamped and
``/odom_edges`` Odometry) in ``tmp_path``:

* ``sample``: a copy of the committed rosbag2 directory: one zstd chunk, written by rosbags
  (chunk CRC 0: damage inside the compressed data is not caught by a checksum);
* ``chunked``: a lone ``.mcap`` with the same schemas and the first 40 ground-truth and 60
  odometry messages, written by ``test_replay.write_mcap`` in small uncompressed chunks
  with CRCs, so that truncation and damage leave whole chunks before them.

For every case (a truncation at byte ``k``, or 1-3 bits flipped inside one region: magic,
header, chunk header, chunk records, message index, data end, summary records, summary
offsets, footer, end magic):

* ``open_bag`` + ``read`` + ``decode`` either work or raise the module's own ``BagError``
  (naming the bag; only when the damage precedes every complete chunk) / ``DecodeError``;
* the messages of every chunk that lies wholly before the first damaged byte are read (for a
  truncation exactly those: a chunk cut short cannot be read); damage confined to the
  summary or footer loses nothing; a bag with CRCs delivers only authentic messages;
* fewer messages than the bag holds comes with a problem in ``BagSource.problems``;
* ``rotavg replay`` (``run_replay`` in-process, and the CLI ``main`` for unreadable bags)
  ends without a traceback, uses every recovered edge and reports the problems.

Targeted single-bit cases in the summary (a Channel id, a ChunkIndex end time, a field name
of a stored definition) keep the bugs these fuzz cases found from coming back. A hypothesis
test adds random truncations combined with random bit flips (bounded examples,
derandomized) on the reader alone.
"""

from __future__ import annotations

import shutil
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from test_replay import replay, write_mcap

from rotavg_ros import cli
from rotavg_ros.errors import InputError
from rotavg_ros.io.bag_reader import BagError, DecodeError, open_bag
from rotavg_ros.replay import EXIT_INPUT, EXIT_NOTHING_USABLE, EXIT_OK

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "bags" / "smallgrid3d_odom"
EDGES = "/odom_edges"
CHUNKED_ODOM = 60  # odometry messages in the chunked bag
CHUNKED_GT = 40  # ground-truth messages in the chunked bag

pytestmark = pytest.mark.skipif(not (SAMPLE / "metadata.yaml").is_file(),
                                reason="bags/smallgrid3d_odom not generated")


# ---------------------------------------------------------------------- bag layout
@dataclass
class Layout:
    """One pristine bag: where its records lie and what its chunks hold."""

    bag: Path
    """what is opened: the rosbag2 directory or the lone .mcap"""
    mcap: Path
    data: bytes
    spans: list[tuple[str, int, int]]
    """(region, start, end) in file order; chunks are split into header and records"""
    chunks: list[tuple[int, int]]
    """(end offset, messages) per chunk"""
    messages: Counter[tuple[int, bytes]]
    """(log time, data) of every message"""
    crcs: bool

    @property
    def total(self) -> int:
        return sum(n for _, n in self.chunks)

    def complete_before(self, k: int) -> int:
        """Messages in the chunks that lie wholly before byte ``k``."""
        return sum(n for end, n in self.chunks if end <= k)

    def region(self, name: str) -> list[tuple[int, int]]:
        return [(a, b) for kind, a, b in self.spans if kind == name]

    def data_end(self) -> int:
        return self.region("data end")[0][1]


SUMMARY_KINDS = {Schema: "summary schema", Channel: "summary channel"}


def layout(bag: Path, crcs: bool) -> Layout:
    mcap = bag if bag.suffix == ".mcap" else next(bag.glob("*.mcap"))
    data = mcap.read_bytes()
    spans: list[tuple[str, int, int]] = [("magic", 0, 8)]
    chunks: list[tuple[int, int]] = []
    messages: Counter[tuple[int, bytes]] = Counter()
    after_data = False
    with open(mcap, "rb") as fh:
        start = 8
        for rec in StreamReader(fh, emit_chunks=True).records:
            end = fh.tell()
            kind = type(rec).__name__
            if isinstance(rec, Chunk):
                inner = [r for r in breakup_chunk(rec) if isinstance(r, Message)]
                messages.update((m.log_time, bytes(m.data)) for m in inner)
                chunks.append((end, len(inner)))
                head = start + 49 + len(rec.compression)  # opcode .. records length
                spans += [("chunk header", start, head), ("chunk records", head, end)]
            else:
                name = {"Header": "header", "MessageIndex": "message index",
                        "DataEnd": "data end", "SummaryOffset": "summary offsets",
                        "Footer": "footer"}.get(kind, "summary" if after_data else "metadata")
                if after_data and type(rec) in SUMMARY_KINDS:
                    name = SUMMARY_KINDS[type(rec)]
                elif kind in ("ChunkIndex", "Statistics"):
                    name = f"summary {kind.lower()}"
                spans.append((name, start, end))
                after_data = after_data or kind == "DataEnd"
            start = end
    spans.append(("end magic", len(data) - 8, len(data)))
    return Layout(bag, mcap, data, spans, chunks, messages, crcs)


# ---------------------------------------------------------------------- the two bags
@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Layout]:
    root = tmp_path_factory.mktemp("fuzz")
    sample = root / "sample"
    shutil.copytree(SAMPLE, sample)
    schemas: dict[int, Schema] = {}
    channels: dict[int, tuple[str, str]] = {}
    records: list[tuple[str, int, str, bytes]] = []
    with open(next(sample.glob("*.mcap")), "rb") as fh:
        for rec in StreamReader(fh).records:
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                channels[rec.id] = (rec.topic, schemas[rec.schema_id].name)
            elif isinstance(rec, Message):
                topic, typ = channels[rec.channel_id]
                records.append((topic, rec.log_time, typ, bytes(rec.data)))
    texts = {s.name: s.data.decode() for s in schemas.values()}
    odom = [r for r in records if r[0] == EDGES][:CHUNKED_ODOM]
    truth = [r for r in records if r[0] != EDGES][:CHUNKED_GT]
    subset = sorted(truth + odom, key=lambda r: r[1])
    chunked = write_mcap(root / "chunked.mcap", subset, chunk_size=1536, schemas=texts)
    out = {"sample": layout(sample, crcs=False), "chunked": layout(chunked, crcs=True)}
    assert len(out["chunked"].chunks) >= 20 and out["chunked"].total == len(subset)
    assert len(out["sample"].chunks) == 1 and out["sample"].total == 422
    return out


def damaged(lay: Layout, tmp_path: Path, data: bytes) -> Path:
    """A copy of ``lay``'s bag in ``tmp_path`` whose .mcap holds ``data``."""
    if lay.bag.is_dir():
        bag = tmp_path / lay.bag.name
        shutil.copytree(lay.bag, bag)
        (bag / lay.mcap.name).write_bytes(data)
        return bag
    bag = tmp_path / lay.mcap.name
    bag.write_bytes(data)
    return bag


# ---------------------------------------------------------------------- the checks
@dataclass
class Outcome:
    error: BagError | None = None
    read: Counter[str] | None = None
    problems: list[str] | None = None


def read_all(lay: Layout, bag: Path, bound: int) -> Outcome:
    """open_bag + read + decode with the reader's own properties asserted."""
    try:
        source = open_bag(bag)
    except BagError as exc:
        assert str(bag) in str(exc), exc
        assert bound == 0, f"{exc} although {bound} messages lie before the damage"
        return Outcome(error=exc)
    with source:
        records = list(source.read(list(source.topics)))
        for rec in records:
            try:
                source.decode(rec)
            except DecodeError as exc:
                assert str(exc).strip() and "\n" not in str(exc)
        problems = list(source.problems)
    n = len(records)
    assert n >= bound, (n, bound, problems)
    if n < lay.total:
        assert problems, f"{lay.total - n} messages lost without a problem"
    if lay.crcs:  # every chunk is checksummed: nothing but the bag's own messages
        got = Counter((r.log_time_ns, r.data) for r in records)
        assert not got - lay.messages, "messages that are not in the bag"
    return Outcome(read=Counter(r.topic for r in records), problems=problems)


def check_replay(lay: Layout, bag: Path, outcome: Outcome) -> None:
    """``rotavg replay`` ends normally, uses every recovered edge and shows the problems."""
    if outcome.error is not None:
        with pytest.raises(InputError, match="no MCAP magic|not a rosbag2"):
            replay(bag)
        return
    assert outcome.read is not None and outcome.problems is not None
    report = replay(bag)
    text = report.text  # type: ignore[attr-defined]
    assert "Traceback" not in text and f"replay summary for {bag}" in text
    for topic, stats in report.topics.items():
        if stats.role != "ignored":  # replay reads topic by topic, so rosbags may skip a
            # damaged chunk that holds none of the topic: at least as many as read above
            assert stats.read >= outcome.read[topic], (topic, text)
    edges = report.topics.get(EDGES)
    if lay.crcs and edges is not None and edges.role == "edges":
        # authentic odometry is valid: only a damaged schema makes it undecodable
        assert edges.used + edges.rejected["undecodable_message"] == edges.read, text
    expected = EXIT_OK if report.edges_used else EXIT_NOTHING_USABLE
    assert report.exit_code == expected, text
    if outcome.problems:
        assert "problems:" in text
        for problem in outcome.problems:  # details differ: replay reads topic by topic
            assert " ".join(problem.split()[:3]) in text, (problem, text)


def run_case(lay: Layout, tmp_path: Path, data: bytes, bound: int) -> Outcome:
    bag = damaged(lay, tmp_path, data)
    outcome = read_all(lay, bag, bound)
    check_replay(lay, bag, outcome)
    return outcome


# ---------------------------------------------------------------------- truncation
def truncation_points(lay: Layout, rng: np.random.Generator, count: int) -> list[int]:
    """Region boundaries (just before, at) and random points, ``count`` distinct ones."""
    size = len(lay.data)
    ends = [end for end, _ in lay.chunks]
    firsts = lay.region("chunk records")[0]
    points = {0, 5, 8, 20, firsts[0] + 5, (firsts[0] + firsts[1]) // 2,
              ends[0] - 1, ends[0], ends[len(ends) // 2] - 1, ends[len(ends) // 2],
              ends[-1] - 1, ends[-1], lay.data_end() - 3, lay.data_end() + 5,
              (lay.data_end() + size) // 2, size - 30, size - 8, size - 1}
    points = {p for p in points if 0 <= p < size}
    while len(points) < count:
        points.add(int(rng.integers(0, size)))
    return sorted(points)[:count] if len(points) > count else sorted(points)


TRUNCATIONS = [("chunked", i) for i in range(24)] + [("sample", i) for i in range(6)]


@pytest.mark.parametrize(("which", "index"), TRUNCATIONS,
                         ids=[f"{w}-{i}" for w, i in TRUNCATIONS])
def test_truncated_bag(bags: dict[str, Layout], tmp_path: Path, which: str,
                       index: int) -> None:
    """Truncated at byte k: exactly the chunks that end by k are read (a chunk cut short is
    lost, nothing before it is), the replay uses them and says what was lost."""
    lay = bags[which]
    if which == "chunked":
        points = truncation_points(lay, np.random.default_rng(2025), 24)
    else:  # one big zstd chunk: magic, header, inside the chunk, after it, summary
        size, end = len(lay.data), lay.chunks[0][0]
        points = [4, 30, end // 3, end - 1, end + 10, size - 20]
    k = points[index]
    expected = lay.complete_before(k)
    outcome = run_case(lay, tmp_path, lay.data[:k], expected)
    if outcome.error is None:
        assert outcome.read is not None and sum(outcome.read.values()) == expected
        assert outcome.problems and any("stopped at byte" in p for p in outcome.problems)
        assert any(lay.mcap.name in p for p in outcome.problems)
        if expected == lay.total:  # only the index was cut: every message is there
            assert outcome.read[EDGES] == (CHUNKED_ODOM if which == "chunked" else 297)


def test_truncating_the_last_tenth_keeps_the_data(bags: dict[str, Layout],
                                                  tmp_path: Path) -> None:
    """Cutting 10% (the summary and part of the last chunks) keeps >= 80% of the
    messages of the chunked bag; the sample's 10% is all index, so it keeps them all."""
    for which, share in (("chunked", 0.8), ("sample", 1.0)):
        lay = bags[which]
        k = int(len(lay.data) * 0.9)
        sub = tmp_path / which
        sub.mkdir()
        outcome = run_case(lay, sub, lay.data[:k], lay.complete_before(k))
        assert outcome.read is not None
        assert sum(outcome.read.values()) >= share * lay.total


# ---------------------------------------------------------------------- bit flips
FLIP_REGIONS = {
    "chunked": ["magic", "header", "header", "chunk header", "chunk header", "chunk header",
                "chunk records", "chunk records", "chunk records", "chunk records",
                "chunk records", "message index", "message index", "data end",
                "summary schema", "summary schema", "summary channel", "summary channel",
                "summary chunkindex", "summary chunkindex", "summary statistics",
                "summary offsets", "footer", "footer", "end magic"],
    "sample": ["chunk header", "chunk records", "chunk records", "chunk records",
               "summary channel", "summary statistics", "footer"],
}
FLIPS = [(w, i) for w, regions in FLIP_REGIONS.items() for i in range(len(regions))]


def flipped(lay: Layout, region: str, rng: np.random.Generator) -> tuple[bytes, int]:
    """1-3 random bits flipped inside one random span of ``region``; the first byte hit."""
    spans = lay.region(region)
    a, b = spans[int(rng.integers(len(spans)))]
    data = bytearray(lay.data)
    positions = rng.choice(np.arange(a, b), size=min(int(rng.integers(1, 4)), b - a),
                           replace=False)
    for pos in positions:
        data[pos] ^= 1 << int(rng.integers(8))
    return bytes(data), int(positions.min())


@pytest.mark.parametrize(("which", "index"), FLIPS,
                         ids=[f"{w}-{FLIP_REGIONS[w][i].replace(' ', '_')}-{i}"
                              for w, i in FLIPS])
def test_bit_flipped_bag(bags: dict[str, Layout], tmp_path: Path, which: str,
                         index: int) -> None:
    """Bits flipped in one region: the chunks before the first flipped byte are read, damage
    to the summary or footer loses nothing, and the replay reports what it met."""
    lay = bags[which]
    region = FLIP_REGIONS[which][index]
    data, first = flipped(lay, region, np.random.default_rng([7, len(which), index]))
    assert data != lay.data
    outcome = run_case(lay, tmp_path, data, lay.complete_before(first))
    if outcome.error is not None:
        assert region == "magic"
    elif first >= lay.data_end():  # only the index is damaged: the data is all there
        assert outcome.read is not None
        assert sum(outcome.read.values()) == lay.total, (region, outcome.problems)


# ---------------------------------------------------------------------- found by fuzzing
def targeted_flip(lay: Layout, what: str) -> tuple[bytes, int]:
    """One bit that the random cases above rarely hit, each once a bug of the reader:

    * ``channel id``: a summary Channel's id: rosbags found no message for it and the topic
      vanished without a problem (now: the index is inconsistent, read record by record);
    * ``chunk end time``: a ChunkIndex's end time below its start: rosbags skipped the
      chunk's messages silently (now: fewer than indexed, the rest read record by record);
    * ``schema field``: ``child_frame_id`` in the summary's TransformStamped definition: the
      ground truth decoded without it and the replay crashed (AttributeError).
    """
    data = bytearray(lay.data)
    if what == "channel id":
        start = lay.region("summary channel")[0][0]
        pos = start + 9  # opcode, record length, then the id (little endian)
        data[pos] ^= 0x01
    elif what == "chunk end time":
        indexes = lay.region("summary chunkindex")
        start = indexes[len(indexes) // 2][0]
        begin, end = (int.from_bytes(data[start + o:start + o + 8], "little")
                      for o in (9, 17))
        bit = next(b for b in range(64) if end >> b & 1 and 1 << b > end - begin)
        pos = start + 17 + bit // 8
        data[pos] ^= 1 << (bit % 8)
    else:
        a, b = next(span for span in lay.region("summary schema")
                    if b"TransformStamped" in lay.data[span[0]:span[1]])
        pos = lay.data.index(b"child_frame_id", a, b)
        data[pos] ^= 0x01  # 'c' -> 'b'
    return bytes(data), pos


TARGETED = [(w, what) for w in ("chunked", "sample")
            for what in ("channel id", "chunk end time", "schema field")]


@pytest.mark.parametrize(("which", "what"), TARGETED,
                         ids=[f"{w}-{what.replace(' ', '_')}" for w, what in TARGETED])
def test_damaged_summary_loses_nothing(bags: dict[str, Layout], tmp_path: Path, which: str,
                                       what: str) -> None:
    lay = bags[which]
    data, pos = targeted_flip(lay, what)
    assert pos >= lay.data_end()
    outcome = run_case(lay, tmp_path, data, lay.total)
    assert outcome.read is not None and sum(outcome.read.values()) == lay.total


# ---------------------------------------------------------------------- hypothesis
@settings(max_examples=25, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(draw=st.data())
def test_random_truncation_and_flips(bags: dict[str, Layout], tmp_path: Path,
                                     draw: st.DataObject) -> None:
    """Any truncation combined with up to three bit flips, on the reader alone."""
    lay = bags["chunked"]
    size = len(lay.data)
    cut = draw.draw(st.integers(0, size), label="cut")
    flips = draw.draw(st.lists(st.tuples(st.integers(0, size - 1), st.integers(0, 7)),
                               max_size=3), label="flips")
    data = bytearray(lay.data)
    for pos, bit in flips:
        data[pos] ^= 1 << bit
    first = min([cut, *(pos for pos, _ in flips)])
    bag = tmp_path / "hyp.mcap"
    bag.write_bytes(bytes(data[:cut]))
    read_all(lay, bag, lay.complete_before(first))


# ---------------------------------------------------------------------- CLI
def test_cli_reports_an_unreadable_bag_without_traceback(
        bags: dict[str, Layout], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A flipped magic: exit 2 and a one-line error naming the file, no traceback."""
    lay = bags["sample"]
    data = bytearray(lay.data)
    data[1] ^= 0x10
    bag = damaged(lay, tmp_path, bytes(data))
    assert cli.main(["replay", str(bag), "--quiet"]) == EXIT_INPUT
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err + captured.out
    (line,) = captured.err.strip().splitlines()
    assert line.startswith("rotavg replay: error:") and str(bag) in line
    assert "no MCAP magic" in line
