"""A channel or schema id an MCAP file defines twice. Repeated as it was (a chunked file's
summary repeats every channel) it is nothing; defined again otherwise (another topic, another
type), the messages of that id cannot be told apart: `bag play` refuses them in one line
naming the id and both names, `bag reindex` keeps the first definition, leaves out the
messages after the second and says so. They were played (and rebuilt) as the first or the
last definition's, whichever the reader kept."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from mcap.data_stream import RecordBuilder
from mcap.reader import make_reader
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

from rcan_rtps.ros.bag import BagError, BagReader, reindex
from rcan_rtps.ros.serialization import serialize

pytestmark = pytest.mark.offline

STRING, INT32 = "std_msgs/msg/String", "std_msgs/msg/Int32"
MAGIC = b"\x89MCAP0\r\n"
STRING_SCHEMA = Schema(id=1, name=STRING, encoding="ros2msg", data=b"string data\n")
INT32_SCHEMA = Schema(id=1, name=INT32, encoding="ros2msg", data=b"int32 data\n")


def _channel(topic: str, schema_id: int = 1) -> Channel:
    return Channel(id=1, topic=topic, message_encoding="cdr", schema_id=schema_id,
                   metadata={})


def _message(i: int) -> Message:
    return Message(channel_id=1, sequence=i, log_time=10 + i, publish_time=10 + i,
                   data=serialize(STRING, {"data": f"m{i}"}))


def _bytes(records: list[McapRecord]) -> bytes:
    builder = RecordBuilder()
    for record in records:
        record.write(builder)
    return builder.end()


def _file(bag: Path, data: list[McapRecord], summary: list[McapRecord], *,
          chunked: bool) -> Path:
    """A closed MCAP file: `data` (in one chunk, indexed, when `chunked`), then `summary`."""
    head = MAGIC + _bytes([Header(profile="ros2", library="test")])
    if chunked:
        inner = _bytes(data)
        chunk = _bytes([Chunk(compression="", data=inner, message_start_time=10,
                              message_end_time=20, uncompressed_crc=0,
                              uncompressed_size=len(inner))])
        summary = [*summary, ChunkIndex(
            chunk_length=len(chunk), chunk_start_offset=len(head), compression="",
            compressed_size=len(inner), message_end_time=20, message_index_length=0,
            message_index_offsets={}, message_start_time=10, uncompressed_size=len(inner))]
        body = head + chunk
    else:
        body = head + _bytes(data)
    body += _bytes([DataEnd(data_section_crc=0)])
    messages = sum(isinstance(r, Message) for r in data)
    stats = Statistics(message_count=messages, schema_count=1, channel_count=1,
                       attachment_count=0, metadata_count=0, chunk_count=int(chunked),
                       message_start_time=10, message_end_time=20,
                       channel_message_counts={1: messages})
    tail = _bytes([*summary, stats])
    footer = _bytes([Footer(summary_start=len(body), summary_offset_start=0, summary_crc=0)])
    bag.mkdir()
    file = bag / "bag_0.mcap"
    file.write_bytes(body + tail + footer + MAGIC)
    return file


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rcan_rtps", *args], capture_output=True,
                          text=True, timeout=60)


@pytest.mark.parametrize("chunked", [True, False], ids=["indexed", "unindexed"])
def test_play_refuses_a_channel_id_defined_as_two_topics(tmp_path: Path, chunked: bool) -> None:
    data = [STRING_SCHEMA, _channel("/a"), _message(0), _message(1)]
    # the summary names the id twice: which topic are its messages of?
    file = _file(tmp_path / "bag", data, [STRING_SCHEMA, _channel("/a"), _channel("/b")],
                 chunked=chunked)
    with pytest.raises(BagError, match="channel id 1 is defined twice, as '/a' and as '/b'"):
        list(BagReader(file).messages())
    with pytest.raises(BagError, match="channel id 1"):
        list(BagReader(file).messages({"/b"}))
    done = _cli("bag", "play", str(file.parent))
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    (line,) = done.stderr.strip().splitlines()
    assert line.startswith("rcan-rtps: error: ") and "channel id 1 is defined twice, as " \
        "'/a' and as '/b'" in line and "not played" in line, line


def test_a_schema_id_defined_as_two_types_is_refused_too(tmp_path: Path) -> None:
    data = [STRING_SCHEMA, _channel("/a"), _message(0), INT32_SCHEMA, _message(1)]
    file = _file(tmp_path / "bag", data, [STRING_SCHEMA, _channel("/a")], chunked=False)
    with pytest.raises(BagError, match=f"schema id 1 is defined twice, as '{STRING}' and "
                                       f"as '{INT32}'"):
        list(BagReader(file).messages())
    (done,) = reindex(file.parent)  # the message before the second definition kept
    assert (done.messages, done.conflicted) == (1, 1)
    assert done.conflicts == [f"schema id 1 is defined twice, as '{STRING}' and as '{INT32}'"]


def test_reindex_keeps_the_first_definition_and_leaves_out_what_follows_the_second(
        tmp_path: Path) -> None:
    data = [STRING_SCHEMA, _channel("/a"), _message(0), _message(1), _channel("/b"),
            _message(2)]
    file = _file(tmp_path / "bag", data, [STRING_SCHEMA, _channel("/a")], chunked=True)
    done = _cli("bag", "reindex", str(file.parent))
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[0].endswith(
        ": 2 messages (channel id 1 is defined twice, as '/a' and as '/b': the first "
        "definition kept; left out 1 messages of a channel after its id was defined again "
        "(of which definition, none can tell))"), done.stdout
    with file.open("rb") as stream:
        got = [(c.topic, m.data) for _, c, m in make_reader(stream).iter_messages()]
    assert got == [("/a", _message(0).data), ("/a", _message(1).data)]
    from rosbags.highlevel import AnyReader

    with AnyReader([file.parent]) as reader:
        read = [(conn.topic, reader.deserialize(raw, conn.msgtype).data)
                for conn, _, raw in reader.messages()]
    assert read == [("/a", "m0"), ("/a", "m1")]
    assert [m.topic for m in BagReader(file).messages()] == ["/a", "/a"]  # played now


def test_a_definition_repeated_as_it_was_is_nothing(tmp_path: Path) -> None:
    data = [STRING_SCHEMA, _channel("/a"), _message(0), STRING_SCHEMA, _channel("/a"),
            _message(1)]
    file = _file(tmp_path / "bag", data, [STRING_SCHEMA, _channel("/a"), _channel("/a")],
                 chunked=True)
    assert [m.topic for m in BagReader(file).messages()] == ["/a", "/a"]
    (done,) = reindex(file.parent)
    assert (done.messages, done.conflicted, done.conflicts) == (2, 0, [])
