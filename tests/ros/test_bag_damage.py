"""What `bag info` sees beyond a bag's summary: chunks whose CRC does not match (a flipped
byte the summary cannot show), and a summary whose schemas or channels are not the data
section's. Such a summary is refused by `bag play` as damaged and left behind by `bag
reindex`, which keeps the data section's (its first) definition."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from rcan_rtps.cli import bag_cmd
from rcan_rtps.ros.bag import BagError, BagReader, reindex
from rcan_rtps.ros.serialization import serialize
from tests.ros.test_bag_definitions import STRING_SCHEMA, _channel, _file, _message
from tests.ros.test_bag_hostile import STRING, _valid_bag

pytestmark = pytest.mark.offline


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rcan_rtps", *args], capture_output=True,
                          text=True, timeout=60)


def _chunked_bag(folder: Path, compression: CompressionType) -> Path:
    """A bare MCAP file of 30 messages in several chunks (of about 200 B each)."""
    folder.mkdir()
    file = folder / "many_0.mcap"
    with file.open("wb") as stream:
        writer = Writer(stream, compression=compression, chunk_size=200)
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema(STRING, "ros2msg", b"string data\n")
        channel = writer.register_channel("/a", "cdr", schema, {})
        for i in range(30):
            writer.add_message(channel, log_time=i, publish_time=i,
                               data=serialize(STRING, {"data": f"message number {i:02}"}))
        writer.finish()
    return file


def _chunk_offsets(file: Path) -> list[int]:
    with file.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    return sorted(index.chunk_start_offset for index in summary.chunk_indexes)


def _flip(file: Path, at: int) -> None:
    data = bytearray(file.read_bytes())
    data[at] ^= 0x20
    file.write_bytes(bytes(data))


def test_a_sound_bag_shows_no_damage(tmp_path: Path) -> None:
    file = _chunked_bag(tmp_path / "many", CompressionType.ZSTD)
    assert len(_chunk_offsets(file)) > 3
    damage = BagReader(file).damage()
    assert (damage.chunks, damage.conflicts) == ([], [])
    done = _cli("bag", "info", str(file))
    assert done.returncode == 0, done.stderr
    assert "Damaged" not in done.stdout and "Conflicts" not in done.stdout


def test_info_names_the_one_chunk_whose_crc_does_not_match(tmp_path: Path) -> None:
    """A byte flipped inside a message's text: the chunk still parses, its CRC tells."""
    file = _chunked_bag(tmp_path / "many", CompressionType.NONE)
    offsets = _chunk_offsets(file)
    at = file.read_bytes().index(b"message number 17")
    damaged = max(o for o in offsets if o < at)
    _flip(file, at + 3)
    assert BagReader(file).damage().chunks == [
        f"many_0.mcap at byte {damaged}: a chunk's CRC does not match"]
    done = _cli("bag", "info", str(file))
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert "Damaged chunks:    1" in lines, done.stdout
    assert f"                   many_0.mcap at byte {damaged}: a chunk's CRC does not match" \
        in lines, done.stdout
    assert "Messages:          30" in lines  # the summary's, as before


def test_info_names_a_compressed_chunk_that_does_not_inflate(tmp_path: Path) -> None:
    file = _chunked_bag(tmp_path / "many", CompressionType.LZ4)
    damaged = _chunk_offsets(file)[2]
    _flip(file, damaged + 60)  # inside the LZ4 frame
    (line,) = BagReader(file).damage().chunks
    assert line.startswith(f"many_0.mcap at byte {damaged}: "), line


def test_a_recorder_s_one_chunk_is_checked_too(tmp_path: Path) -> None:
    """rosbag2's layout (ours): one chunk, its CRC set, checked."""
    file = _valid_bag(tmp_path / "bag")
    assert BagReader(file.parent).damage().chunks == []
    _flip(file, file.read_bytes().index(b"m13"))
    (line,) = BagReader(file.parent).damage().chunks
    assert line.endswith("a chunk's CRC does not match"), line


# -- a summary whose definitions are not the data section's -------------------------
@pytest.mark.parametrize("chunked", [True, False], ids=["indexed", "unindexed"])
def test_a_summary_that_contradicts_the_data_section_is_damage(tmp_path: Path,
                                                                chunked: bool) -> None:
    data = [STRING_SCHEMA, _channel("/a"), _message(0), _message(1)]
    # the summary says channel 1 is /b: the data section's messages are /a's
    file = _file(tmp_path / "bag", data, [STRING_SCHEMA, _channel("/b")], chunked=chunked)
    (conflict,) = BagReader(file).damage().conflicts
    assert conflict == "bag_0.mcap: channel id 1 is defined twice, as '/a' and as '/b' " \
        "(the summary's differs from the data section's)"
    done = _cli("bag", "info", str(file.parent))
    assert done.returncode == 0, done.stderr
    assert f"Conflicts:         {conflict}" in done.stdout.splitlines(), done.stdout
    with pytest.raises(BagError, match="channel id 1 is defined twice"):
        list(BagReader(file).messages())  # before: played as /b (indexed)
    with pytest.raises(BagError, match="channel id 1 is defined twice"):
        list(BagReader(file).messages({"/b"}))
    (done_file,) = reindex(file.parent)
    assert done_file.messages == 2 and done_file.conflicts == [
        "channel id 1 is defined twice, as '/a' and as '/b'"]
    assert [m.topic for m in BagReader(file).messages()] == ["/a", "/a"]
    assert BagReader(file).damage().conflicts == []


def test_play_of_some_topics_reads_only_the_chunks_that_hold_them(tmp_path: Path) -> None:
    """As the mcap library did: a chunk whose index names none of the channels played is
    not read (a damaged one of another topic does not stop the playback)."""
    folder = tmp_path / "two"
    folder.mkdir()
    file = folder / "two_0.mcap"
    with file.open("wb") as stream:
        writer = Writer(stream, compression=CompressionType.LZ4, chunk_size=200)
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema(STRING, "ros2msg", b"string data\n")
        for topic in ("/a", "/b"):
            channel = writer.register_channel(topic, "cdr", schema, {})
            for i in range(15):
                writer.add_message(channel, log_time=i, publish_time=i,
                                   data=serialize(STRING, {"data": f"{topic} number {i:02}"}))
        writer.finish()
    _flip(file, _chunk_offsets(file)[-1] + 60)  # the last chunk: /b's only
    assert len([m for m in BagReader(file).messages({"/a"})]) == 15
    with pytest.raises(BagError, match="inflate"):
        list(BagReader(file).messages())


def _info(file: Path, check: bool | None, capsys: pytest.CaptureFixture[str]) -> str:
    assert bag_cmd.info_command(argparse.Namespace(bag=str(file), check=check)) == 0
    return capsys.readouterr().out


def test_a_large_bag_s_chunks_are_read_only_when_asked(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Reading every chunk of a bag of gigabytes takes minutes, where its summary comes at
    once: over CHECK_AUTO_BYTES `bag info` says it did not read them, `--check` does."""
    file = _chunked_bag(tmp_path / "many", CompressionType.NONE)
    _flip(file, file.read_bytes().index(b"message number 17") + 3)
    assert "Damaged chunks:    1" in _info(file, None, capsys)  # small: read
    assert "Damaged chunks" not in _info(file, False, capsys)  # --no-check
    monkeypatch.setattr(bag_cmd, "CHECK_AUTO_BYTES", file.stat().st_size - 1)
    large = _info(file, None, capsys)
    assert "Damaged chunks" not in large
    assert large.endswith("Chunks not read for damage: the bag is over 0 MiB (--check reads "
                          "them)\n"), large
    assert "Damaged chunks:    1" in _info(file, True, capsys)  # --check
