"""Bags a stranger could hand a user: each gets a one-line error (BagError, on the command
line `rcan-rtps: error: …`, exit 1) or is read as far as it can be, never a traceback, a hang
or gigabytes of memory. The files are made here: the mcap library's records written by hand
where a valid writer would refuse (red team 22)."""

from __future__ import annotations

import contextlib
import os
import shutil
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import lz4.frame
import pytest
import yaml
import zstandard
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.data_stream import RecordBuilder
from mcap.exceptions import EndOfFile
from mcap.reader import NonSeekingReader
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    Schema,
    Statistics,
)
from mcap.writer import CompressionType, Writer

from rcan_rtps.ros.bag import (
    METADATA_FILE,
    METADATA_LIMIT,
    BagError,
    BagReader,
    BagWriter,
    parse_offered_qos,
    reindex,
)
from rcan_rtps.ros.serialization import serialize
from rcan_rtps.ros.typesys.store import TypeStore

pytestmark = pytest.mark.offline

STRING = "std_msgs/msg/String"
MAGIC = b"\x89MCAP0\r\n"
# Nine lines standing for 9^9 strings: whoever walks the structure never finishes.
ALIAS_BOMB = "a: &a [x,x,x,x,x,x,x,x,x]\n" + "".join(
    f"{b}: &{b} [{', '.join([f'*{a}'] * 9)}]\n"
    for a, b in zip("abcdefghi", "bcdefghij", strict=True))


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    """The command line, given 60 s: a hang fails the test (TimeoutExpired), not the run."""
    return subprocess.run([sys.executable, "-m", "rcan_rtps", *args], capture_output=True,
                          text=True, timeout=60)


def _one_line_error(done: subprocess.CompletedProcess[str]) -> str:
    assert done.returncode == 1, (done.stdout, done.stderr)
    assert "Traceback" not in done.stderr, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rcan-rtps: error: "), done.stderr
    return lines[0]


def _valid_bag(where: Path, count: int = 20) -> Path:
    writer = BagWriter(where, TypeStore(distro="jazzy"), flush_period=60)
    writer.add_topic("/chatter", STRING, [])
    for i in range(count):
        writer.write("/chatter", 1_000_000_000 + i, serialize(STRING, {"data": f"m{i}"}))
    writer.close()
    return where / f"{where.name}_0.mcap"


def _record(record: McapRecord) -> bytes:
    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


def _one_chunk_file(path: Path, chunk: Chunk, *, indexed: bool = True) -> Path:
    """An MCAP file with one channel and one chunk (as given), its summary's chunk index
    pointing at the chunk when `indexed`."""
    schema = Schema(id=1, name=STRING, encoding="ros2msg", data=b"string data\n")
    channel = Channel(id=1, topic="/chatter", message_encoding="cdr", schema_id=1, metadata={})
    head = MAGIC + _record(Header(profile="ros2", library="test")) + _record(schema) \
        + _record(channel)
    body = _record(chunk)
    data = head + body + _record(DataEnd(data_section_crc=0))
    summary = _record(schema) + _record(channel) + _record(Statistics(
        attachment_count=0, channel_count=1, channel_message_counts={1: 1}, chunk_count=1,
        message_count=1, message_end_time=2, message_start_time=1, metadata_count=0,
        schema_count=1))
    if indexed:
        summary += _record(ChunkIndex(
            chunk_length=len(body), chunk_start_offset=len(head),
            compression=chunk.compression, compressed_size=len(chunk.data),
            message_end_time=2, message_index_length=0,
            message_index_offsets={1: len(head) + len(body)}, message_start_time=1,
            uncompressed_size=chunk.uncompressed_size))
    footer = _record(Footer(summary_start=len(data), summary_offset_start=0, summary_crc=0))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data + summary + footer + MAGIC)
    return path


def _chunk(compression: str, data: bytes, claimed: int) -> Chunk:
    return Chunk(compression=compression, data=data, message_start_time=1,
                 message_end_time=2, uncompressed_crc=0, uncompressed_size=claimed)


# -- files that are no files ------------------------------------------------------
@pytest.mark.parametrize("kind", ["fifo", "dev_zero"])
def test_a_fifo_or_device_in_a_bag_folder_is_refused_not_waited_on(tmp_path: Path,
                                                                     kind: str) -> None:
    bag = tmp_path / "bag"
    bag.mkdir()
    if kind == "fifo":  # opened for reading, it blocks until a writer comes: forever
        os.mkfifo(bag / "bag_0.mcap")
    else:
        (bag / "bag_0.mcap").symlink_to("/dev/zero")
    for verb in ("info", "reindex", "play"):
        line = _one_line_error(_cli("bag", verb, str(bag)))
        assert "is not a regular file" in line


def test_a_fifo_for_metadata_yaml_is_refused_not_waited_on(tmp_path: Path) -> None:
    file = _valid_bag(tmp_path / "bag")
    (file.parent / METADATA_FILE).unlink()
    os.mkfifo(file.parent / METADATA_FILE)
    assert "is not a regular file" in _one_line_error(_cli("bag", "info", str(file.parent)))


# -- metadata.yaml ------------------------------------------------------------------
HOSTILE_METADATA = {
    # str() of the distro walked the billion strings
    "alias_bomb_distro": textwrap.indent(ALIAS_BOMB, "  ") + "  ros_distro: *j\n",
    "alias_bomb_files": textwrap.indent(ALIAS_BOMB, "  ") + "  relative_file_paths: *j\n",
    "files_a_number": "  relative_file_paths: 5\n",
    "files_numbers": "  relative_file_paths: [1, 2]\n",
    "nested_too_deep": "  custom_data: " + "[" * 5000 + "]" * 5000 + "\n",
    # parsing YAML in Python takes about a second a MiB: refused before it starts
    "too_large": "  custom_data: " + "x" * (METADATA_LIMIT + 10) + "\n",
}


@pytest.mark.parametrize("name", sorted(HOSTILE_METADATA))
def test_a_hostile_metadata_yaml_gets_a_one_line_error(tmp_path: Path, name: str) -> None:
    file = _valid_bag(tmp_path / "bag")
    (file.parent / METADATA_FILE).write_text(
        "rosbag2_bagfile_information:\n" + HOSTILE_METADATA[name])
    line = _one_line_error(_cli("bag", "info", str(file.parent)))
    assert "is not a bag's metadata.yaml" in line


def test_reindex_writes_a_hostile_metadata_yaml_anew(tmp_path: Path) -> None:
    file = _valid_bag(tmp_path / "bag")
    meta = file.parent / METADATA_FILE
    meta.write_text("rosbag2_bagfile_information:\n" + HOSTILE_METADATA["alias_bomb_distro"])
    (done,) = reindex(file.parent)  # the old file only told the distro: left aside
    assert done.messages == 20
    info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
    assert info["message_count"] == 20 and info["ros_distro"] == "unknown"


# -- a channel's QoS ----------------------------------------------------------------
@pytest.mark.parametrize("text", [
    "[: : :", "5", "[a, b]", "\x03", "- {depth: abc, deadline: [1, 2], lifespan: {sec: x}}",
    "- {deadline: {sec: -5, nsec: 0}, depth: 99999999999999999999}",
    "- " + textwrap.indent(ALIAS_BOMB, "  ").lstrip(),
])
def test_a_channel_qos_that_is_no_qos_counts_as_unknown(tmp_path: Path, text: str) -> None:
    profiles = parse_offered_qos(text)  # no exception
    assert all(p.depth == 10 and p.deadline_s is None for p in profiles)
    file = tmp_path / "bag_0.mcap"
    with file.open("wb") as stream:
        writer = Writer(stream, compression=CompressionType.NONE)
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema(STRING, "ros2msg", b"string data\n")
        writer.register_channel("/chatter", "cdr", schema, {"offered_qos_profiles": text})
        writer.finish()
    (topic,) = BagReader(file).summary().topics
    assert topic.name == "/chatter"


# -- chunks: bombs and lies --------------------------------------------------------
def test_a_chunk_claiming_a_terabyte_is_refused(tmp_path: Path) -> None:
    small = zstandard.ZstdCompressor().compress(b"\0" * 100)
    file = _one_chunk_file(tmp_path / "bag" / "bag_0.mcap", _chunk("zstd", small, 2**40))
    with pytest.raises(BagError, match="over the 512 MiB"):
        list(BagReader(file).messages())
    # reindex leaves it out, says why, and keeps the rest (here: nothing)
    (rebuilt,) = reindex(file.parent)
    assert (rebuilt.messages, rebuilt.unreadable) == (0, 1)
    assert "over the 512 MiB" in rebuilt.unreadable_why


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
@pytest.mark.parametrize("indexed", [True, False])
def test_a_chunk_inflating_past_its_claim_is_refused(tmp_path: Path, compression: str,
                                                    indexed: bool) -> None:
    # 4 MiB of zeros (records the reader skips) in a chunk claiming 1000 B: the library
    # inflates an LZ4 chunk without limit, to whatever its frame holds
    zeros = b"\0" * (4 * 2**20)
    data = zstandard.ZstdCompressor(write_content_size=False).compress(zeros) \
        if compression == "zstd" else lz4.frame.compress(zeros)
    file = _one_chunk_file(tmp_path / "bag" / "bag_0.mcap", _chunk(compression, data, 1000),
                           indexed=indexed)
    # (zstd through the index: the library's own decompress, bounded by the claim, says so)
    with pytest.raises(BagError, match=r"inflates to more than the 1000 B|decompression error"):
        list(BagReader(file).messages())
    (rebuilt,) = reindex(file.parent)  # left out, bounded, said why
    assert (rebuilt.messages, rebuilt.unreadable) == (0, 1)
    assert "inflates to more than the 1000 B it claims" in rebuilt.unreadable_why


def test_a_cut_lz4_frame_is_damaged(tmp_path: Path) -> None:
    # the frame's end mark cut off: it inflates to the size claimed, but is no whole frame
    # (the library's decompress, called by `play` after the check, raised RuntimeError)
    frame = lz4.frame.compress(b"\0" * 1000, content_checksum=False)[:-4]
    file = _one_chunk_file(tmp_path / "bag" / "bag_0.mcap", _chunk("lz4", frame, 1000))
    with pytest.raises(BagError, match="LZ4 frame is cut short"):
        list(BagReader(file).messages())


def test_a_chunk_with_an_unknown_compression_is_refused(tmp_path: Path) -> None:
    file = _one_chunk_file(tmp_path / "bag" / "bag_0.mcap", _chunk("brotli", b"x" * 10, 10))
    with pytest.raises(BagError, match="not one MCAP names"):
        list(BagReader(file).messages())


def test_a_length_field_past_the_end_costs_no_allocation(tmp_path: Path) -> None:
    # a chunk in the summary section whose data claims 2^62 bytes, in a record of 60: the
    # library asked the file for 2^62 bytes (MemoryError), now for what the file holds
    fields = struct.pack("<QQQI", 1, 2, 10, 0) + struct.pack("<I", 0) \
        + struct.pack("<Q", 2**62) + b"\0" * 16
    data = MAGIC + _record(Header(profile="ros2", library="test")) \
        + _record(DataEnd(data_section_crc=0))
    summary = struct.pack("<BQ", 0x06, len(fields)) + fields
    footer = _record(Footer(summary_start=len(data), summary_offset_start=0, summary_crc=0))
    file = tmp_path / "long.mcap"
    file.write_bytes(data + summary + footer + MAGIC)
    with pytest.raises(BagError, match="damaged"):
        BagReader(file).summary()


def test_a_file_shorter_than_a_footer_is_cut_short(tmp_path: Path) -> None:
    file = tmp_path / "short.mcap"
    file.write_bytes(MAGIC + _record(Header(profile="ros2", library="test")))
    with pytest.raises(BagError, match="damaged or cut short"):
        BagReader(file).summary()
    with pytest.raises(BagError, match="damaged or cut short"):
        list(BagReader(file).messages())


def test_no_topics_wanted_reads_no_messages(tmp_path: Path) -> None:
    # `play` of a bag none of whose topics it can publish (unknown types, not CDR) asks for
    # no topics: the library read that as all, and play failed on the first (KeyError)
    file = _valid_bag(tmp_path / "bag")
    assert list(BagReader(file).messages(set())) == []
    assert len(list(BagReader(file).messages())) == 20


def test_reindex_says_what_it_could_not_carry_over(tmp_path: Path) -> None:
    # channel 1 defined twice (another topic and schema the second time) and a message of a
    # channel never defined: reindex kept the first definition and dropped the message,
    # saying nothing of either; the message after the second definition (of /a or /b?) went
    # to /a
    string = serialize(STRING, {"data": "hi"})
    records = [
        Schema(id=1, name=STRING, encoding="ros2msg", data=b"string data\n"),
        Schema(id=2, name="std_msgs/msg/Int32", encoding="ros2msg", data=b"int32 data\n"),
        Channel(id=1, topic="/a", message_encoding="cdr", schema_id=1, metadata={}),
        Message(channel_id=1, sequence=0, log_time=1, publish_time=1, data=string),
        Channel(id=1, topic="/b", message_encoding="cdr", schema_id=2, metadata={}),
        Message(channel_id=1, sequence=1, log_time=2, publish_time=2, data=string),
        Message(channel_id=7, sequence=0, log_time=3, publish_time=3, data=string),
    ]
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "bag_0.mcap").write_bytes(
        MAGIC + _record(Header(profile="ros2", library="test"))
        + b"".join(_record(r) for r in records) + _record(DataEnd(data_section_crc=0))
        + _record(Footer(summary_start=0, summary_offset_start=0, summary_crc=0)) + MAGIC)
    done = _cli("bag", "reindex", str(bag))
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[0] == (
        f"Reindexed '{bag / 'bag_0.mcap'}': 1 messages (left out 1 messages of a channel "
        "the file never defines; channel id 1 is defined twice, as '/a' and as '/b': the "
        "first definition kept; left out 1 messages of a channel after its id was defined "
        "again (of which definition, none can tell))")


# -- byte mutation ----------------------------------------------------------------
@pytest.fixture(scope="module")
def seed_files(tmp_path_factory: pytest.TempPathFactory) -> list[bytes]:
    """A recorder's bag, a killed recorder's, and zstd and lz4 chunked files."""
    where = tmp_path_factory.mktemp("seeds")
    whole = _valid_bag(where / "whole", count=12).read_bytes()
    seeds = [whole, whole[: len(whole) * 2 // 3]]
    for compression in (CompressionType.ZSTD, CompressionType.LZ4):
        path = where / f"{compression.name}.mcap"
        with path.open("wb") as stream:
            writer = Writer(stream, compression=compression, chunk_size=200)
            writer.start(profile="ros2", library="test")
            schema = writer.register_schema(STRING, "ros2msg", b"string data\n")
            channel = writer.register_channel("/a", "cdr", schema,
                                              {"offered_qos_profiles": "- {depth: 3}"})
            for i in range(12):
                writer.add_message(channel, log_time=i, publish_time=i,
                                   data=serialize(STRING, {"data": "y" * i}))
            writer.finish()
        seeds.append(path.read_bytes())
    return seeds


_EDIT = st.tuples(st.sampled_from(["set", "word", "cut", "insert", "delete"]),
                  st.floats(0, 1), st.binary(min_size=1, max_size=8))


def _mutated(seed: bytes, edits: list[tuple[str, float, bytes]]) -> bytes:
    data = bytearray(seed)
    for kind, where, value in edits:
        at = int(where * len(data))
        if kind == "set" and at < len(data):
            data[at] = value[0]
        elif kind == "word":  # a length or offset field made huge, zero or random
            data[at:at + 8] = (value * 8)[:8]
        elif kind == "cut":
            del data[at:]
        elif kind == "insert":
            data[at:at] = value
        else:
            del data[at:at + len(value) * 16]
    return bytes(data)


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(which=st.integers(0, 3), edits=st.lists(_EDIT, min_size=1, max_size=4))
def test_a_mutated_bag_reads_or_says_it_is_damaged(
        seed_files: list[bytes], tmp_path: Path, which: int,
        edits: list[tuple[str, float, bytes]]) -> None:
    bag = tmp_path / "fuzz"
    shutil.rmtree(bag, ignore_errors=True)
    bag.mkdir()
    (bag / "fuzz_0.mcap").write_bytes(_mutated(seed_files[which], edits))
    for step in (lambda: BagReader(bag).summary(), lambda: list(BagReader(bag).messages()),
                 lambda: reindex(bag), lambda: list(BagReader(bag).messages())):
        with contextlib.suppress(BagError):  # anything else fails the test
            step()


# -- the writer: a full disk, a concurrent reindex ------------------------------------
_FULL_DISK_RECORDER = """
import resource, sys
from pathlib import Path
from rcan_rtps.ros.bag import BagError, BagWriter
from rcan_rtps.ros.serialization import serialize
from rcan_rtps.ros.typesys.store import TypeStore
resource.setrlimit(resource.RLIMIT_FSIZE, (300_000, 300_000))  # the disk is full at 300 kB
writer = BagWriter(Path(sys.argv[1]), TypeStore(distro="jazzy"), flush_period=60)
writer.add_topic("/chatter", "std_msgs/msg/String", [])
for i in range(2000):
    writer.write("/chatter", 10**9 + i, serialize("std_msgs/msg/String", {"data": "x" * 500}))
    if i % 50 == 49:
        writer.flush()
print("failed:", writer.failed)
try:
    writer.close()
except BagError as exc:
    print(exc)
"""


def test_a_full_disk_stops_the_writer_and_leaves_what_it_wrote_readable(
        tmp_path: Path) -> None:
    bag = tmp_path / "full"
    done = subprocess.run([sys.executable, "-c", _FULL_DISK_RECORDER, str(bag)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    failed, said = done.stdout.strip().splitlines()
    assert failed == "failed: True"
    assert said.startswith(f"could not write bag '{bag}' (File too large): recording stopped")
    kept = int(said.split("the ")[1].split(" messages")[0])
    assert kept > 0
    # what metadata.yaml counts is what the file holds, for mcap's sequential reader ...
    info = yaml.safe_load((bag / METADATA_FILE).read_text())["rosbag2_bagfile_information"]
    assert info["message_count"] == kept
    read = 0
    with (bag / "full_0.mcap").open("rb") as stream:
        try:
            for _ in NonSeekingReader(stream).iter_messages(log_time_order=False):
                read += 1
        except EndOfFile:  # the torn write at its end
            pass
    assert read == kept
    # ... and for rosbags after reindex, which also keeps the whole messages of the chunk
    # the failed write cut short (an uncompressed chunk's records lie in the file as written)
    (rebuilt,) = reindex(bag)
    assert rebuilt.messages >= kept
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        assert sum(1 for _ in reader.messages()) == rebuilt.messages


def test_reindex_refuses_a_bag_being_recorded(tmp_path: Path) -> None:
    # Replaced under it, the recorder went on writing to the old file: all it wrote after
    # was lost (100 of 200 messages here).
    writer = BagWriter(tmp_path / "live", TypeStore(distro="jazzy"), flush_period=60)
    writer.add_topic("/chatter", STRING, [])
    for i in range(100):
        writer.write("/chatter", 1_000_000_000 + i, serialize(STRING, {"data": "a"}))
    writer.flush()
    with pytest.raises(BagError, match="is being recorded"):
        reindex(tmp_path / "live")
    for i in range(100):
        writer.write("/chatter", 2_000_000_000 + i, serialize(STRING, {"data": "b"}))
    writer.close()
    assert BagReader(tmp_path / "live").summary().message_count == 200
    (done,) = reindex(tmp_path / "live")  # once the recording ended
    assert done.messages == 200
