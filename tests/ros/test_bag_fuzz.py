"""Bags built record by record from hostile parts (red team 24): lengths of 2^63, chunks
claiming 500 MiB they do not hold (zstd and lz4 without a declared frame size), records of
length 0, chunk indexes and footers pointing backwards or anywhere, unknown opcodes, wrong
CRCs, then byte edits on top. `bag info`, `bag play`'s reading and `bag reindex` (its
salvage of damage in the middle included) must each end with a result or a BagError — never
another exception, a hang, memory in proportion to a claimed length rather than to the
file, or a write other than reindex's own file and metadata.yaml."""

from __future__ import annotations

import contextlib
import shutil
import signal
import tracemalloc
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from types import FrameType
from typing import Any

import lz4.frame
import pytest
import zstandard
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    MetadataIndex,
    Schema,
    Statistics,
)
from mcap.writer import CompressionType, Writer

from rcan_rtps.ros import bag as bag_module
from rcan_rtps.ros.bag import RECORD_HEAD, BagError, BagReader, reindex
from tests.ros.test_bag_hostile import MAGIC, STRING, _chunk, _mutated, _one_chunk_file, _record

pytestmark = pytest.mark.offline

CLAIM = 400 * 2**20  # what a chunk of a few hundred bytes claims to inflate to
# The most a read of a file of a few KiB may take: the records it holds, a summary, the
# libraries' own working memory; never a claimed length.
MEMORY_LIMIT = 32 * 2**20
HANG_LIMIT = 120  # s: a step still running then is taken for a loop that never ends


def _compressed(compression: str, data: bytes, *, sized: bool) -> bytes:
    """`data` compressed, its frame saying its size (`sized`) or not: without it, a reader
    has only the chunk's claim to size its output by."""
    if compression == "zstd":
        return zstandard.ZstdCompressor(write_content_size=sized).compress(data)
    if compression == "lz4":
        return lz4.frame.compress(data, store_size=sized)
    return data


def _one_message() -> bytes:
    return _record(Message(channel_id=1, sequence=0, log_time=1, publish_time=1,
                           data=b"\x00\x01\x00\x00" + b"x" * 12))


@contextlib.contextmanager
def _peak_memory() -> Iterator[list[int]]:
    """The peak of Python's allocations within (tracemalloc sees bytes objects and the
    buffers the compression libraries allocate through Python)."""
    peak: list[int] = []
    tracemalloc.start()
    try:
        yield peak
    finally:
        peak.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()


@pytest.mark.parametrize("compression,sized", [("zstd", False), ("zstd", True),
                                               ("lz4", False), ("lz4", True)])
@pytest.mark.parametrize("step", ["play", "reindex"])
def test_a_chunk_claiming_more_than_it_holds_costs_what_it_holds(
        tmp_path: Path, compression: str, sized: bool, step: str) -> None:
    """Inflated to its claim at once, a 500 B chunk claiming 400 MiB took 400 MiB: the
    mcap library's zstd read (play) and ours (reindex's salvage) allocate what they are
    asked for before the frame says how much it holds."""
    data = _compressed(compression, _one_message(), sized=sized)
    file = _one_chunk_file(tmp_path / "bag" / "bag_0.mcap", _chunk(compression, data, CLAIM))
    with _peak_memory() as peak, contextlib.suppress(BagError):
        if step == "play":
            list(BagReader(file.parent).messages())
        else:
            (done,) = reindex(file.parent)
            assert done.unreadable == 1 and "inflates to less than" in done.unreadable_why
    assert peak[0] < MEMORY_LIMIT, f"{peak[0] >> 20} MiB for a file of {file.stat().st_size} B"


def _nested_chunk() -> bytes:
    """A chunk record claiming CLAIM, to be put inside another chunk."""
    data = _compressed("zstd", _one_message(), sized=False)
    return _record(_chunk("zstd", data, CLAIM))


@pytest.mark.parametrize("step", ["info", "play", "reindex"])
def test_a_chunk_inside_a_chunk_is_damage_not_inflated_to_its_claim(tmp_path: Path,
                                                                   step: str) -> None:
    """MCAP has no chunk in a chunk; the mcap library's parse of a chunk's records inflated
    one found there to what it claims (400 MiB for a file of 700 B), and played it."""
    inner = _nested_chunk()
    file = _one_chunk_file(tmp_path / "bag" / "bag_0.mcap", _chunk("", inner, len(inner)))
    with _peak_memory() as peak:
        if step == "info":
            (line,) = BagReader(file.parent).damage().chunks
            assert line.endswith(": damaged inside a chunk (a chunk in it)"), line
        elif step == "play":
            with pytest.raises(BagError, match="a chunk in it"):
                list(BagReader(file.parent).messages())
        else:
            (done,) = reindex(file.parent)
            assert (done.messages, done.unreadable) == (0, 1), done
    assert peak[0] < MEMORY_LIMIT, f"{peak[0] >> 20} MiB"


@pytest.mark.parametrize("step", ["info", "damage", "play"])
def test_a_footer_pointing_at_a_chunk_is_refused_not_inflated(tmp_path: Path,
                                                              step: str) -> None:
    """A footer whose summary starts at a chunk of the data section: the mcap library read
    that chunk as part of the summary, inflated to its claim (400 MiB for 500 B)."""
    data = _compressed("zstd", _one_message(), sized=False)
    file = _one_chunk_file(tmp_path / "bag" / "bag_0.mcap", _chunk("zstd", data, CLAIM))
    whole = file.read_bytes()
    chunk_at = whole.index(_record(_chunk("zstd", data, CLAIM)))
    footer = _record(Footer(summary_start=chunk_at, summary_offset_start=0, summary_crc=0))
    file.write_bytes(whole[:-len(footer) - len(MAGIC)] + footer + MAGIC)
    reader = BagReader(file.parent)
    with _peak_memory() as peak, pytest.raises(
            BagError, match=f"its summary section holds a chunk \\(at byte {chunk_at}\\)"):
        if step == "info":
            reader.summary()
        elif step == "damage":
            reader.damage()
        else:
            list(reader.messages())
    assert peak[0] < MEMORY_LIMIT, f"{peak[0] >> 20} MiB"


def test_a_metadata_index_pointing_at_a_chunk_is_refused_not_inflated(tmp_path: Path) -> None:
    """`bag info` reads the metadata records (rosbag2's, for the distro) the summary indexes:
    the mcap library parsed whatever an index pointed at, a chunk inflated to its claim."""
    data = _compressed("zstd", _one_message(), sized=False)
    file = _one_chunk_file(tmp_path / "bag" / "bag_0.mcap", _chunk("zstd", data, CLAIM))
    whole = file.read_bytes()
    chunk_at = whole.index(_record(_chunk("zstd", data, CLAIM)))
    index = _record(MetadataIndex(offset=chunk_at, length=100, name="rosbag2"))
    tail = len(_record(Footer(summary_start=0, summary_offset_start=0, summary_crc=0))) \
        + len(MAGIC)
    file.write_bytes(whole[:-tail] + index + whole[-tail:])
    with _peak_memory() as peak, pytest.raises(BagError) as refused:
        BagReader(file.parent).summary()
    assert peak[0] < MEMORY_LIMIT, f"{peak[0] >> 20} MiB"
    assert "a metadata index points at no metadata record" in str(refused.value)


def test_play_says_a_chunk_claiming_more_than_it_holds_is_damaged(tmp_path: Path) -> None:
    """The library's zstd read played such a chunk as if its claim were true."""
    data = _compressed("zstd", _one_message(), sized=False)
    file = _one_chunk_file(tmp_path / "bag" / "bag_0.mcap", _chunk("zstd", data, 1000))
    with pytest.raises(BagError, match="inflates to less than the 1000 B it claims"):
        list(BagReader(file.parent).messages())


# -- hostile files, record by record -------------------------------------------------
_IDS = st.integers(0, 3)
_TIMES = st.sampled_from([0, 1, 5, 2**63 - 1, 2**64 - 1])
_LENGTHS = st.sampled_from([0, 1, 8, 2**31, CLAIM, 2**63, 2**64 - 1])
_SCHEMA = st.builds(Schema, id=_IDS, name=st.sampled_from([STRING, "x/msg/Y", ""]),
                    encoding=st.just("ros2msg"), data=st.binary(max_size=16))
_CHANNEL = st.builds(Channel, id=_IDS, topic=st.sampled_from(["/a", "/b", ""]),
                     message_encoding=st.just("cdr"), schema_id=_IDS,
                     metadata=st.sampled_from([{}, {"offered_qos_profiles": "- {depth: 3}"}]))
_MESSAGE = st.builds(Message, channel_id=_IDS, sequence=st.integers(0, 3), log_time=_TIMES,
                     publish_time=_TIMES, data=st.binary(max_size=24))
_INNER = st.lists(st.one_of(_SCHEMA, _CHANNEL, _MESSAGE), max_size=5)


@st.composite
def _chunks(draw: st.DrawFn) -> bytes:
    """A chunk of real records, its claimed size and CRC true or not."""
    inner = b"".join(_record(r) for r in draw(_INNER)) + draw(st.sampled_from(
        [b"", RECORD_HEAD.pack(0x05, 2**63), RECORD_HEAD.pack(0x05, 0), _nested_chunk()]))
    compression = draw(st.sampled_from(["", "zstd", "lz4"]))
    data = _compressed(compression, inner, sized=draw(st.booleans()))
    claimed = draw(st.sampled_from([len(inner), len(inner) + 1, max(0, len(inner) - 1),
                                    CLAIM, 2**63]))
    crc = draw(st.sampled_from([zlib.crc32(inner), 0, zlib.crc32(inner) ^ 1]))
    return _record(Chunk(compression=compression, data=data, message_start_time=draw(_TIMES),
                         message_end_time=draw(_TIMES), uncompressed_crc=crc,
                         uncompressed_size=claimed))


_RAW_HEAD = st.builds(lambda op, length, tail: RECORD_HEAD.pack(op, length) + tail,
                      st.integers(0, 0x11), _LENGTHS, st.binary(max_size=12))
_DATA = st.lists(st.one_of(_SCHEMA.map(_record), _CHANNEL.map(_record),
                           _MESSAGE.map(_record), _chunks(), _RAW_HEAD,
                           st.builds(MessageIndex, channel_id=_IDS,
                                     records=st.lists(st.tuples(_TIMES, _LENGTHS),
                                                      max_size=2)).map(_record)),
                 max_size=8)


@st.composite
def _hostile_files(draw: st.DrawFn) -> bytes:
    """Magic, header, data records (one of them a chunk claiming CLAIM, which a reader
    that trusts the claim allocates), DataEnd, a summary whose chunk and metadata indexes
    and footer point where hypothesis likes (that chunk, a record's start, backwards, past
    the end), the magic; then a few byte edits."""
    head = MAGIC + _record(Header(profile="ros2", library="fuzz"))
    records = draw(_DATA)
    bomb = draw(st.integers(0, len(records)))
    records.insert(bomb, _record(_chunk("zstd", _compressed(
        "zstd", _one_message(), sized=False), CLAIM)))
    starts, at = [], len(head)
    for record in records:
        starts.append(at)
        at += len(record)
    body = head + b"".join(records) + _record(DataEnd(data_section_crc=0))
    offsets = st.one_of(st.just(starts[bomb]),
                        st.sampled_from([*starts, 0, 1, len(body), 2**63]))
    summary = [*draw(st.lists(st.one_of(_SCHEMA, _CHANNEL), max_size=3)),
               *draw(st.lists(st.builds(
                   ChunkIndex, chunk_length=_LENGTHS, chunk_start_offset=offsets,
                   compression=st.sampled_from(["", "zstd", "lz4", "bz2"]),
                   compressed_size=_LENGTHS, message_end_time=_TIMES,
                   message_index_length=_LENGTHS, message_index_offsets=st.just({}),
                   message_start_time=_TIMES, uncompressed_size=_LENGTHS), max_size=3)),
               *draw(st.lists(st.builds(MetadataIndex, offset=offsets, length=_LENGTHS,
                                        name=st.just("rosbag2")), max_size=2)),
               Statistics(message_count=1, schema_count=1, channel_count=1,
                          attachment_count=0, metadata_count=0, chunk_count=1,
                          message_start_time=1, message_end_time=2,
                          channel_message_counts={1: 1})]
    tail = b"".join(_record(r) for r in summary)
    summary_start = draw(st.one_of(st.sampled_from([len(body), 0, 1, 2**63]), offsets))
    footer = _record(Footer(summary_start=summary_start, summary_offset_start=0,
                            summary_crc=0))
    whole = body + tail + footer + MAGIC
    edits = draw(st.lists(st.tuples(st.sampled_from(["set", "word", "cut", "insert"]),
                                    st.floats(0, 1), st.binary(min_size=1, max_size=8)),
                          max_size=2))
    return _mutated(whole, edits) if edits else whole


class _Hung(Exception):
    pass


def _on_alarm(signum: int, frame: FrameType | None) -> None:
    raise _Hung("a bag step ran past the hang limit: a loop that never ends")


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.parent.rglob("*")) if p.is_file()}


def _within_limits(step: Callable[[], Any], bag: Path, writes: set[str]) -> None:
    """`step` ends in a result or a BagError, within MEMORY_LIMIT (the file is small),
    having changed no file but `writes` (names in the bag folder)."""
    before = _snapshot(bag)
    previous = signal.signal(signal.SIGALRM, _on_alarm)
    signal.alarm(HANG_LIMIT)
    try:
        with _peak_memory() as peak, contextlib.suppress(BagError):
            step()
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    assert peak[0] < MEMORY_LIMIT, f"{peak[0] >> 20} MiB"
    after = _snapshot(bag)
    changed = {n for n in before.keys() | after.keys() if before.get(n) != after.get(n)}
    assert changed <= writes, changed


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture,
                                 HealthCheck.too_slow])
@given(data=_hostile_files())
def test_a_hostile_file_is_read_within_limits_or_refused(tmp_path: Path, data: bytes) -> None:
    bag = tmp_path / "fuzz"
    shutil.rmtree(bag, ignore_errors=True)
    bag.mkdir()
    (bag / "fuzz_0.mcap").write_bytes(data)
    file = bag / "fuzz_0.mcap"
    _within_limits(lambda: BagReader(bag).summary(), bag, set())
    _within_limits(lambda: BagReader(bag).damage(), bag, set())
    _within_limits(lambda: list(BagReader(file).messages()), bag, set())
    _within_limits(lambda: list(BagReader(bag).messages({"/a"})), bag, set())
    _within_limits(lambda: reindex(bag), bag, {"fuzz_0.mcap", "metadata.yaml"})
    _within_limits(lambda: list(BagReader(bag).messages()), bag, set())


def test_a_chunk_indexed_many_times_is_played_once(tmp_path: Path) -> None:
    """A summary may index one chunk any number of times: each index was read as a chunk of
    its own, the chunk's messages played once per index and all held at once (they are due
    together), so 1 MiB of summary multiplied one chunk's memory ten thousand times."""
    messages = [Message(channel_id=1, sequence=i, log_time=10 + i, publish_time=10 + i,
                        data=b"\x00\x01\x00\x00" + bytes(200)) for i in range(1000)]
    inner = b"".join(_record(m) for m in messages)
    schema = Schema(id=1, name=STRING, encoding="ros2msg", data=b"string data\n")
    channel = Channel(id=1, topic="/a", message_encoding="cdr", schema_id=1, metadata={})
    head = MAGIC + _record(Header(profile="ros2", library="test")) + _record(schema) \
        + _record(channel)
    chunk = _record(Chunk(compression="", data=inner, message_start_time=10,
                          message_end_time=1009, uncompressed_crc=zlib.crc32(inner),
                          uncompressed_size=len(inner)))
    body = head + chunk + _record(DataEnd(data_section_crc=0))
    index = ChunkIndex(chunk_length=len(chunk), chunk_start_offset=len(head), compression="",
                       compressed_size=len(inner), message_end_time=1009,
                       message_index_length=0, message_index_offsets={},
                       message_start_time=10, uncompressed_size=len(inner))
    summary = _record(schema) + _record(channel) + _record(index) * 200 + _record(Statistics(
        message_count=1000, schema_count=1, channel_count=1, attachment_count=0,
        metadata_count=0, chunk_count=1, message_start_time=10, message_end_time=1009,
        channel_message_counts={1: 1000}))
    footer = _record(Footer(summary_start=len(body), summary_offset_start=0, summary_crc=0))
    file = tmp_path / "bag_0.mcap"
    file.write_bytes(body + summary + footer + MAGIC)
    with _peak_memory() as peak:
        played = sum(1 for _ in BagReader(file).messages())
    assert played == 1000
    assert peak[0] < MEMORY_LIMIT, f"{peak[0] >> 20} MiB"


def _zstd_chunks_file(file: Path, *, overlapping: bool) -> Path:
    """8 zstd chunks of 1 MiB of messages each (zeros: a few KiB compressed), each over the
    same 16 ns (`overlapping`), or one after the other as a recorder writes them."""
    with file.open("wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD, chunk_size=2**20)
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema(STRING, "ros2msg", b"string data\n")
        channel = writer.register_channel("/a", "cdr", schema, {})
        for i in range(8 * 16):
            when = i % 16 if overlapping else i  # (each chunk: 16 messages)
            writer.add_message(channel, log_time=when, publish_time=when,
                               data=b"\x00\x01\x00\x00" + bytes(2**16))
        writer.finish()
    return file


def test_chunks_overlapping_in_time_are_held_within_a_limit(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Play puts overlapping chunks' messages in time order, holding them until due: chunks
    that all start at once were all held (zstd bombs: GiBs from a file of KiBs)."""
    monkeypatch.setattr(bag_module, "HELD_LIMIT", 4 * 2**20)  # 8 chunks of 1 MiB
    apart = _zstd_chunks_file(tmp_path / "apart.mcap", overlapping=False)
    assert sum(1 for _ in BagReader(apart).messages()) == 128  # a chunk at a time
    together = _zstd_chunks_file(tmp_path / "together.mcap", overlapping=True)
    assert together.stat().st_size < 2**20 // 4
    with pytest.raises(BagError, match="chunks overlapping in time that hold more than 4 "
                                       "MiB of messages at once"):
        list(BagReader(together).messages())
