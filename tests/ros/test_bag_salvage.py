"""`bag reindex` on a file damaged in the middle keeps every whole record after the damage:
a head overwritten, bytes inserted between two records, a chunk whose bytes changed (its CRC
no longer matches). Before, the first bad head ended the walk and the rest of the file was
"a torn last record"; a bad chunk refused the whole file. Whatever the damage, nothing that
is not one of the recorded messages comes out."""

from __future__ import annotations

import random
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from rcan_rtps.ros.bag import RECORD_HEAD, ReindexedFile, reindex
from rcan_rtps.ros.serialization import serialize

STRING = "std_msgs/msg/String"
COUNT = 300


def _bag(where: Path) -> tuple[Path, list[bytes]]:
    """A bag of COUNT distinct messages in many small uncompressed chunks."""
    where.mkdir()
    file = where / f"{where.name}_0.mcap"
    sent = [serialize(STRING, {"data": f"message {i:04d} " + "x" * 40}) for i in range(COUNT)]
    with file.open("wb") as stream:
        writer = Writer(stream, chunk_size=2048, compression=CompressionType.NONE)
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema(STRING, "ros2msg", b"string data")
        channel = writer.register_channel("/chatter", "cdr", schema)
        for i, data in enumerate(sent):
            writer.add_message(channel, log_time=1_000_000_000 + i, data=data,
                               publish_time=1_000_000_000 + i)
        writer.finish()
    return file, sent


def _chunk_starts(file: Path) -> list[int]:
    data = file.read_bytes()
    offset, starts = 8, []
    while offset + RECORD_HEAD.size <= len(data):
        opcode, length = RECORD_HEAD.unpack_from(data, offset)
        if opcode == 0x06:
            starts.append(offset)
        if opcode == 0x0F:  # DataEnd
            break
        offset += RECORD_HEAD.size + length
    return starts


def _read_back(file: Path) -> list[bytes]:
    with file.open("rb") as stream:
        return [m.data for _, _, m in make_reader(stream).iter_messages(log_time_order=False)]


def _reindexed(file: Path) -> tuple[ReindexedFile, list[bytes]]:
    (done,) = reindex(file.parent)
    return done, _read_back(file)


def test_an_overwritten_head_in_the_middle_loses_only_its_chunk(tmp_path: Path) -> None:
    file, sent = _bag(tmp_path / "bag")
    starts = _chunk_starts(file)
    assert len(starts) > 10
    data = bytearray(file.read_bytes())
    data[starts[5]:starts[5] + 32] = b"\xff" * 32  # the sixth chunk's head and more
    file.write_bytes(bytes(data))
    done, kept = _reindexed(file)
    assert done.skipped and done.skipped[0][0] == starts[5], done
    assert done.dropped_bytes == 0
    assert set(kept) <= set(sent)
    assert len(kept) > COUNT - 40  # one chunk's messages lost, not the rest of the file
    assert kept[-1] == sent[-1]  # the last chunk is there
    from rosbags.highlevel import AnyReader

    with AnyReader([file.parent]) as reader:
        assert sum(1 for _ in reader.messages()) == len(kept)


def test_bytes_inserted_between_two_chunks_lose_nothing(tmp_path: Path) -> None:
    file, sent = _bag(tmp_path / "bag")
    at = _chunk_starts(file)[7]
    data = file.read_bytes()
    file.write_bytes(data[:at] + random.Random(7).randbytes(333) + data[at:])
    done, kept = _reindexed(file)
    assert done.skipped == [(at, at + 333)], done
    assert kept == sent


def test_a_chunk_whose_bytes_changed_is_left_out_and_said(tmp_path: Path) -> None:
    file, sent = _bag(tmp_path / "bag")
    starts = _chunk_starts(file)
    data = bytearray(file.read_bytes())
    middle = (starts[3] + starts[4]) // 2
    data[middle] ^= 0x55  # inside the fourth chunk's records: its head still frames it
    file.write_bytes(bytes(data))
    done, kept = _reindexed(file)
    assert (done.unreadable, done.skipped) == (1, []), done
    assert "CRC" in done.unreadable_why or "parse" in done.unreadable_why, done
    assert set(kept) <= set(sent) and COUNT - 40 < len(kept) < COUNT


@pytest.mark.parametrize("seed", range(40))
def test_no_damage_makes_up_a_message(tmp_path: Path, seed: int) -> None:
    """Garbage written or inserted anywhere: what reindex keeps is recorded messages only,
    and it ends in one line, never a traceback."""
    file, sent = _bag(tmp_path / "bag")
    rng = random.Random(seed)
    data = bytearray(file.read_bytes())
    at, size = rng.randrange(8, len(data) - 8), rng.randrange(1, 600)
    junk = rng.randbytes(size) if seed % 2 else bytes([rng.randrange(1, 16)]) * size
    if seed % 3:
        data[at:at + size] = junk
    else:
        data[at:at] = junk
    file.write_bytes(bytes(data))
    done = subprocess.run([sys.executable, "-m", "rcan_rtps", "bag", "reindex",
                           str(file.parent)], capture_output=True, text=True, timeout=60)
    assert "Traceback" not in done.stderr, done.stderr
    if done.returncode == 0:
        assert set(_read_back(file)) <= set(sent)
    else:
        assert len(done.stderr.strip().splitlines()) == 1, done.stderr


def test_the_cli_says_what_it_stepped_over(tmp_path: Path) -> None:
    file, _ = _bag(tmp_path / "bag")
    at = _chunk_starts(file)[2]
    data = file.read_bytes()
    file.write_bytes(data[:at] + b"\x00" * 100 + data[at:])
    done = subprocess.run([sys.executable, "-m", "rcan_rtps", "bag", "reindex",
                           str(file.parent)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert f"stepped over 100 B of damage at byte {at}, kept what follows" in done.stdout, \
        done.stdout
