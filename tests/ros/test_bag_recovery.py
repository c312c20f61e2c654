"""Bags that survive their recorder: flushed while recording, read by a sequential reader
when the recorder died, rebuilt by `reindex`, and explained (not a traceback) when damaged.
The recorder's death is simulated by copying the files of a writer that is still open; the
SIGKILL of a real recorder is in tests/interop/test_cli_bag.py."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from mcap.exceptions import EndOfFile
from mcap.reader import NonSeekingReader, make_reader

from rcan_rtps.ros.bag import METADATA_FILE, BagError, BagReader, BagWriter, reindex
from rcan_rtps.ros.serialization import serialize
from rcan_rtps.ros.typesys.store import TypeStore

pytestmark = pytest.mark.offline

STRING = "std_msgs/msg/String"
FLUSH = 0.05  # s: the writer's flush period here, short so the test does not wait long


def _metadata(bag: Path) -> dict:  # type: ignore[type-arg]
    return yaml.safe_load((bag / METADATA_FILE).read_text())["rosbag2_bagfile_information"]


def _wait_for_count(bag: Path, count: int, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if (bag / METADATA_FILE).is_file() and _metadata(bag)["message_count"] == count:
            return
        time.sleep(FLUSH / 2)
    raise AssertionError(f"metadata.yaml never counted {count} messages")


def _sequential_messages(file: Path) -> list[bytes]:
    """What mcap's non-seeking reader reads before the file ends (it has no summary)."""
    got: list[bytes] = []
    with file.open("rb") as stream:
        try:
            # in file order: sorting by time would read to the end first, then fail
            for _, _, message in NonSeekingReader(stream).iter_messages(log_time_order=False):
                got.append(message.data)
        except EndOfFile:
            pass
    return got


@pytest.fixture
def open_writer(tmp_path: Path) -> Iterator[tuple[BagWriter, list[bytes]]]:
    writer = BagWriter(tmp_path / "live", TypeStore(distro="jazzy"), flush_period=FLUSH)
    writer.add_topic("/chatter", STRING, [])
    sent = [serialize(STRING, {"data": f"hello {i}"}) for i in range(3)]
    for i, data in enumerate(sent):
        writer.write("/chatter", 1_000_000_000 + i, data)
    try:
        yield writer, sent
    finally:
        writer.close()


def _crashed_copy(writer: BagWriter, sent: list[bytes], where: Path) -> Path:
    """The bag as a recorder killed now would leave it (the writer stays open)."""
    _wait_for_count(writer.directory, len(sent))
    shutil.copytree(writer.directory, where)
    return where


def test_metadata_and_header_are_on_disk_from_the_start(tmp_path: Path) -> None:
    writer = BagWriter(tmp_path / "fresh", TypeStore(distro="jazzy"), flush_period=60)
    try:
        assert (tmp_path / "fresh" / METADATA_FILE).is_file()
        assert _metadata(tmp_path / "fresh")["message_count"] == 0
        assert (tmp_path / "fresh" / "fresh_0.mcap").stat().st_size > 0
    finally:
        writer.close()


def test_a_killed_recorders_bag_reads_sequentially(
        open_writer: tuple[BagWriter, list[bytes]], tmp_path: Path) -> None:
    writer, sent = open_writer
    crashed = _crashed_copy(writer, sent, tmp_path / "crashed")
    assert _sequential_messages(crashed / "live_0.mcap") == sent
    meta = _metadata(crashed)
    assert meta["topics_with_message_count"][0]["message_count"] == 3
    assert not list(crashed.glob(".*.tmp"))  # replaced, not left beside it


def test_info_on_the_killed_bag_says_to_reindex(
        open_writer: tuple[BagWriter, list[bytes]], tmp_path: Path) -> None:
    crashed = _crashed_copy(*open_writer, tmp_path / "crashed")
    with pytest.raises(BagError, match="bag reindex"):
        BagReader(crashed).summary()


def test_reindex_makes_a_complete_bag_rosbags_reads(
        open_writer: tuple[BagWriter, list[bytes]], tmp_path: Path) -> None:
    writer, sent = open_writer
    crashed = _crashed_copy(writer, sent, tmp_path / "crashed")
    (done,) = reindex(crashed)
    assert (done.messages, done.dropped_bytes) == (3, 0)

    summary = BagReader(crashed).summary()
    assert summary.message_count == 3 and summary.topics[0].type == STRING
    with (crashed / "live_0.mcap").open("rb") as stream:
        assert make_reader(stream).get_summary() is not None

    from rosbags.highlevel import AnyReader  # rosbags needs the summary and metadata.yaml

    with AnyReader([crashed]) as reader:
        got = [reader.deserialize(raw, conn.msgtype).data
               for conn, _, raw in reader.messages()]
    assert got == ["hello 0", "hello 1", "hello 2"]


def test_reindex_leaves_out_a_torn_last_record(
        open_writer: tuple[BagWriter, list[bytes]], tmp_path: Path) -> None:
    writer, sent = open_writer
    crashed = _crashed_copy(writer, sent, tmp_path / "crashed")
    # one more chunk, cut in the middle of its write
    writer.write("/chatter", 2_000_000_000, serialize(STRING, {"data": "late"}))
    _wait_for_count(writer.directory, 4)
    whole = (writer.directory / "live_0.mcap").read_bytes()
    kept = (crashed / "live_0.mcap").stat().st_size
    (crashed / "live_0.mcap").write_bytes(whole[:kept + (len(whole) - kept) // 2])
    (done,) = reindex(crashed)
    assert done.messages == 3 and done.dropped_bytes > 0
    assert BagReader(crashed).summary().message_count == 3


def test_reindex_of_a_complete_bag_leaves_nothing_out(tmp_path: Path) -> None:
    # a recorder stopped with Ctrl-C closes its file: the closing magic is no torn record
    file = _complete_bag(tmp_path / "whole")
    (done,) = reindex(tmp_path / "whole")
    assert (done.messages, done.dropped_bytes) == (50, 0)
    (again,) = reindex(tmp_path / "whole")
    assert (again.messages, again.dropped_bytes) == (50, 0)
    with file.open("rb") as stream:
        assert make_reader(stream).get_summary() is not None


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rcan_rtps", *args], capture_output=True,
                          text=True, timeout=60)


def _complete_bag(where: Path) -> Path:
    writer = BagWriter(where, TypeStore(distro="jazzy"), flush_period=60)
    writer.add_topic("/chatter", STRING, [])
    for i in range(50):
        writer.write("/chatter", 1_000_000_000 + i, serialize(STRING, {"data": "x" * 100}))
    writer.close()
    return where / f"{where.name}_0.mcap"


@pytest.mark.parametrize("damage", ["empty", "not_mcap", "truncated", "torn_summary"])
@pytest.mark.parametrize("verb", ["info", "play"])
def test_info_and_play_explain_a_damaged_file(tmp_path: Path, verb: str, damage: str) -> None:
    file = _complete_bag(tmp_path / "bag")
    data = file.read_bytes()
    file.write_bytes({"empty": b"", "not_mcap": b"PK\x03\x04 a zip, say" * 10,
                      "truncated": data[: len(data) // 2],
                      "torn_summary": data[:-20]}[damage])
    done = _cli("bag", verb, str(file))
    assert done.returncode == 1, done.stdout
    assert "Traceback" not in done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rcan-rtps: error: "), done.stderr
    assert str(file) in lines[0]
    if damage in ("truncated", "torn_summary"):
        assert "bag reindex" in lines[0]


def test_reindex_needs_a_bag_folder(tmp_path: Path) -> None:
    done = _cli("bag", "reindex", str(tmp_path / "nothing"))
    assert done.returncode == 1 and "is not a bag folder" in done.stderr
    assert "Traceback" not in done.stderr
