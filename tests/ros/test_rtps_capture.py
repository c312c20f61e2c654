"""Cyclone's packet capture as the source of RTPS related sample identities (rtps_capture.py).

The parser and the tailing run on capture files written here the way Cyclone writes them
(pcap records with a made-up IPv4/UDP header, TTL 128 for received datagrams); the crash
test runs a real domain in a child process and kills it.
"""

from __future__ import annotations

import os
import signal
import struct
import subprocess
import sys
import tracemalloc
from collections.abc import Callable, Container, Iterator
from pathlib import Path

import pytest

from rcan_rtps.ros import captured_replies, participant, rtps_capture
from rcan_rtps.ros.rtps_capture import (
    UNKNOWN_PREFIX,
    IdentityCapture,
    ReceivedData,
    ReceivedHeartbeat,
    SampleIdentity,
    nanoseconds,
    parse_rtps,
)

PREFIX = bytes(range(1, 13))
WRITER_ID = b"\x00\x00\x12\x03"
SERVER = PREFIX + WRITER_ID
REQUEST_WRITER = bytes(range(100, 116))


def rtps_message(seq: int, related: SampleIdentity | None, *, little: bool = True,
                 frag: int | None = None, stamp: tuple[int, int] = (1_700_000_000, 1 << 31),
                 payload: bytes = b"\x00\x01\x00\x00hello!!\x00") -> bytes:
    """An RTPS message: INFO_TS, then one DATA (or DATA_FRAG number `frag`) whose inline QoS
    names `related` (PID 0x0083) if given."""
    o = "<" if little else ">"
    e = 0x01 if little else 0x00
    info_ts = struct.pack(o + "BBHiI", 0x09, e, 8, *stamp)
    qos = b""
    if related is not None:
        qos = struct.pack(o + "HH", 0x0083, 24) + related.writer_guid + \
            struct.pack(o + "iI", related.seq >> 32, related.seq & 0xFFFFFFFF) + \
            struct.pack(o + "HH", 0x0001, 0)
    flags = e | (0x02 if qos else 0)
    head = struct.pack(o + "HH", 0, 16 if frag is None else 28) + b"\x00\x00\x12\x04" + \
        WRITER_ID + struct.pack(o + "iI", seq >> 32, seq & 0xFFFFFFFF)
    if frag is None:
        body = head + qos + payload
        sub = struct.pack(o + "BBH", 0x15, flags | 0x04, len(body)) + body
    else:
        body = head + struct.pack(o + "IHHI", frag, 1, len(payload), 4 * len(payload)) + \
            qos + payload
        sub = struct.pack(o + "BBH", 0x16, flags, len(body)) + body
    return b"RTPS\x02\x03\x01\x0f" + PREFIX + info_ts + sub


OUR_PREFIX = bytes(range(40, 52))
OUR_READER = OUR_PREFIX + b"\x00\x00\x36\x04"


def heartbeat_message(reader_id: bytes, *, destination: bytes | None = None,
                      little: bool = True, last: int = 15) -> bytes:
    """An RTPS message from SERVER's participant: INFO_DST (if given), then a GAP and a
    HEARTBEAT addressed to `reader_id` (ENTITYID_UNKNOWN: to every reader), as a Fast DDS
    writer announces itself to a new reader; the HEARTBEAT names samples 6 to `last`."""
    o = "<" if little else ">"
    e = 0x01 if little else 0x00
    info_dst = b"" if destination is None else struct.pack(o + "BBH", 0x0E, e, 12) + destination
    gap_body = reader_id + WRITER_ID + struct.pack(o + "iI", 0, 6) + \
        struct.pack(o + "iII", 0, 15, 0)
    gap = struct.pack(o + "BBH", 0x08, e, len(gap_body)) + gap_body
    hb_body = reader_id + WRITER_ID + \
        struct.pack(o + "iIiIi", 0, 6, last >> 32, last & 0xFFFFFFFF, 21)
    hb = struct.pack(o + "BBH", 0x07, e, len(hb_body)) + hb_body
    return b"RTPS\x02\x03\x01\x0f" + PREFIX + info_dst + gap + hb


def pcap_record(message: bytes, ttl: int = 128) -> bytes:
    """A record as Cyclone writes it: pcap header, made-up IPv4 and UDP headers, datagram."""
    total = 28 + len(message)
    ip_udp = struct.pack(">BBHIBBH4s4sHHHH", 0x45, 0, total, 0, ttl, 17, 0, bytes([127, 0, 0, 1]),
                         bytes([239, 255, 0, 1]), 7400, 7401, total - 20, 0)
    packet = ip_udp + message
    return struct.pack("<IIII", 1, 2, len(packet), len(packet)) + packet


PCAP_HEADER = struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1)


def test_parse_finds_only_data_naming_a_related_sample() -> None:
    related = SampleIdentity(REQUEST_WRITER, 7)
    stamp = nanoseconds(1_700_000_000, 1 << 31)
    for little in (True, False):
        found = list(parse_rtps(rtps_message(3, related, little=little)))
        assert found == [ReceivedData(SERVER, 3, stamp, related)]
    assert list(parse_rtps(rtps_message(3, None))) == []
    assert [d.related for d in parse_rtps(rtps_message(4, related, frag=1))] == [related]
    assert list(parse_rtps(rtps_message(4, related, frag=2))) == []


def test_parse_finds_heartbeats_and_whom_they_address() -> None:
    for little in (True, False):
        found = list(parse_rtps(heartbeat_message(OUR_READER[12:], destination=OUR_PREFIX,
                                                  little=little)))
        assert found == [ReceivedHeartbeat(SERVER, OUR_READER, 15)]
    assert list(parse_rtps(heartbeat_message(OUR_READER[12:]))) == \
        [ReceivedHeartbeat(SERVER, UNKNOWN_PREFIX + OUR_READER[12:], 15)]
    to_all = heartbeat_message(bytes(4), destination=OUR_PREFIX, last=2**32 + 3)
    assert list(parse_rtps(to_all)) == \
        [ReceivedHeartbeat(SERVER, OUR_PREFIX + bytes(4), 2**32 + 3)]  # to all our readers


@pytest.fixture
def capture(tmp_path: Path) -> Iterator[tuple[IdentityCapture, int]]:
    """A started capture and a descriptor that appends to its file as Cyclone's does (and
    is redirected as Cyclone's is: the only other descriptor of the file). Made in a
    symlinked directory: Cyclone's descriptor is found by its inode, not by a name."""
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    capture = IdentityCapture(tmp_path / "link")
    writer = os.open(capture.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
    os.write(writer, PCAP_HEADER)
    assert capture.start()
    yield capture, writer
    capture.close()
    os.close(writer)


def test_the_file_loses_its_name_once_opened(tmp_path: Path,
                                             capture: tuple[IdentityCapture, int]) -> None:
    assert list((tmp_path / "real").iterdir()) == []


def test_idle_capture_writes_nothing_and_a_user_gets_identities(
        capture: tuple[IdentityCapture, int]) -> None:
    tail, writer = capture
    stamp = nanoseconds(1_700_000_000, 1 << 31)
    big = bytes(1000)
    os.write(writer, pcap_record(rtps_message(1, SampleIdentity(REQUEST_WRITER, 1),
                                              payload=big)) * 50)
    assert tail.held() <= 4096  # nobody needs identities: Cyclone's writes go to /dev/null
    assert tail.lookup(SERVER, stamp) is None
    assert (tail.datagrams, tail.identified) == (0, 0)

    mine = SampleIdentity(REQUEST_WRITER, 2)
    cut = pcap_record(rtps_message(1, mine))
    os.write(writer, cut[:30])  # the switch cuts a record: its head went to /dev/null ...
    tail.use()
    os.write(writer, cut[30:])  # ... its tail reaches the file, and is skipped
    record = pcap_record(rtps_message(2, mine, stamp=(1_700_000_001, 0)))
    os.write(writer, pcap_record(rtps_message(9, mine), ttl=255))  # one we sent: not parsed
    os.write(writer, record[:50])  # Cyclone has written a part of it so far
    tail.drain()
    os.write(writer, record[50:])
    assert tail.lookup(SERVER, nanoseconds(1_700_000_001, 0)) == mine  # the miss drains
    assert tail.lookup(SERVER, nanoseconds(1_700_000_002, 0)) is None
    assert (tail.datagrams, tail.identified) == (1, 1)

    tail.unuse()
    os.write(writer, pcap_record(rtps_message(3, mine, stamp=(1_700_000_003, 0))))
    assert tail.lookup(SERVER, nanoseconds(1_700_000_003, 0)) is None


def test_no_identity_is_kept_for_data_without_one(capture: tuple[IdentityCapture, int]) -> None:
    tail, writer = capture
    tail.use()
    os.write(writer, pcap_record(rtps_message(5, None)))
    assert tail.lookup(SERVER, nanoseconds(1_700_000_000, 1 << 31)) is None
    assert (tail.datagrams, tail.identified) == (1, 0)


CHILD = """
import sys, time
from rcan_rtps.ros.participant import RosNode
with RosNode("capture_crash", "/", domain_id=int(sys.argv[1])) as node:
    assert node.identities is not None
    print(node.identities.path, flush=True)
    time.sleep(60)
"""


def test_a_killed_process_leaves_no_capture_behind(tmp_path: Path, domain_id: int) -> None:
    env = {**os.environ, "RCAN_RTPS_CAPTURE_DIR": str(tmp_path),
           "PYTHONPATH": os.pathsep.join(sys.path)}
    env.pop("RCAN_RTPS_RPC_IDENTITY", None)
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(domain_id)],
                             stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert child.stdout is not None
        made = Path(child.stdout.readline().strip())
        assert made.parent.parent == tmp_path  # the capture was made where we said
        os.kill(child.pid, signal.SIGKILL)
        assert child.wait(30) == -signal.SIGKILL
    finally:
        child.kill()
    assert [p.name for p in tmp_path.glob("rcan-rtps-capture-*")] == []


def test_a_file_system_that_cannot_give_bytes_back_ends_the_capture(
        capture: tuple[IdentityCapture, int], monkeypatch: pytest.MonkeyPatch) -> None:
    tail, writer = capture
    # what fallocate(PUNCH_HOLE) answers on a file system without it (EOPNOTSUPP)
    monkeypatch.setattr(tail._libc, "punch_hole", lambda fd, offset, length: False)
    tail.use()
    mine = SampleIdentity(REQUEST_WRITER, 3)
    record = pcap_record(rtps_message(1, mine, payload=bytes(1000)))
    os.write(writer, record * (rtps_capture.PUNCH_AFTER // len(record) + 2))
    tail.drain()  # consumed past PUNCH_AFTER: the hole is refused, the capture gives up
    before = tail.held()
    os.write(writer, record * 100)  # Cyclone's writes now go to /dev/null
    assert tail.held() == before
    tail.use()  # and nobody turns it back on
    os.write(writer, pcap_record(rtps_message(2, mine, stamp=(1_700_000_005, 0))))
    assert tail.lookup(SERVER, nanoseconds(1_700_000_005, 0)) is None
    assert tail.held() == before


def test_no_capture_where_it_could_not_be_kept_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    assert rtps_capture.capture_supported()  # this machine: Linux, /proc, fallocate
    monkeypatch.setattr(rtps_capture.sys, "platform", "darwin")
    assert not rtps_capture.capture_supported()
    assert participant._new_capture() is None  # Cyclone is given no capture at all


def test_a_heartbeat_to_our_reader_is_heard_while_a_client_uses_the_capture(
        capture: tuple[IdentityCapture, int]) -> None:
    tail, writer = capture
    announce = pcap_record(heartbeat_message(OUR_READER[12:], destination=OUR_PREFIX))
    os.write(writer, announce)  # nobody uses the capture: it went to /dev/null
    assert not tail.heard_heartbeat(SERVER, OUR_READER, 0)
    assert not tail.reading
    tail.use()
    assert tail.reading
    other = OUR_PREFIX + b"\x00\x00\x39\x04"
    os.write(writer, pcap_record(heartbeat_message(other[12:], destination=OUR_PREFIX)))
    assert not tail.heard_heartbeat(SERVER, OUR_READER, 0)  # to another reader
    assert tail.heard_heartbeat(SERVER, other, 0)
    os.write(writer, pcap_record(heartbeat_message(OUR_READER[12:], destination=OUR_PREFIX),
                                 ttl=255))  # one we sent: not parsed
    assert not tail.heard_heartbeat(SERVER, OUR_READER, 0)
    os.write(writer, announce)
    assert tail.heard_heartbeat(SERVER, OUR_READER, 0)  # the miss reads the file to its end
    assert not tail.heard_heartbeat(PREFIX + b"\x00\x00\x14\x03", OUR_READER, 0)
    tail.unuse()


@pytest.mark.parametrize("destination", [OUR_PREFIX, None])
def test_a_heartbeat_to_every_reader_counts_only_after_the_reader_was_made(
        capture: tuple[IdentityCapture, int], destination: bytes | None) -> None:
    """A Cyclone writer that matches a new reader sends a HEARTBEAT to all of the
    participant's readers (reader id unknown), which Cyclone applies to the readers matched
    with the writer then: one that came before our reader was made was not applied to it."""
    tail, writer = capture
    tail.use()
    to_all = pcap_record(heartbeat_message(bytes(4), destination=destination))
    os.write(writer, to_all)
    made = tail.mark()  # our reader is made now
    assert not tail.heard_heartbeat(SERVER, OUR_READER, made)
    assert tail.heard_heartbeat(SERVER, OUR_READER, 0)  # it would do for an older reader
    other_participant = bytes(range(60, 72))
    os.write(writer, pcap_record(heartbeat_message(bytes(4), destination=other_participant)))
    assert not tail.heard_heartbeat(SERVER, OUR_READER, made)
    os.write(writer, to_all)
    assert tail.heard_heartbeat(SERVER, OUR_READER, made)
    assert not tail.heard_heartbeat(SERVER, OUR_READER, tail.mark())  # nor for a newer one
    tail.unuse()


OTHER_WRITER = PREFIX + b"\x00\x00\x13\x03"  # another writer of the server's participant
OTHER_CLIENT = bytes(range(120, 136))  # another client's request writer


def related_qos(related: SampleIdentity, o: str) -> bytes:
    return struct.pack(o + "HH", 0x800F, 24) + related.writer_guid + \
        struct.pack(o + "iI", related.seq >> 32, related.seq & 0xFFFFFFFF) + \
        struct.pack(o + "HH", 0x0001, 0)


def data_message(writer: bytes, seq: int, related: SampleIdentity | None, payload: bytes, *,
                 little: bool = True, stamp: tuple[int, int] = (1_700_000_000, 0)) -> bytes:
    """One DATA of `writer` (in its participant's message) whose inline QoS names `related`
    (Fast DDS' PID 0x800f) if given, carrying `payload`, written at `stamp`."""
    o, e = ("<", 0x01) if little else (">", 0x00)
    qos = b"" if related is None else related_qos(related, o)
    body = struct.pack(o + "HH", 0, 16) + b"\x00\x00\x12\x04" + writer[12:] + \
        struct.pack(o + "iI", seq >> 32, seq & 0xFFFFFFFF) + qos + payload
    flags = e | 0x04 | (0x02 if qos else 0)
    info_ts = struct.pack(o + "BBHiI", 0x09, e, 8, *stamp)
    return b"RTPS\x02\x03\x01\x0f" + writer[:12] + info_ts + \
        struct.pack(o + "BBH", 0x15, flags, len(body)) + body


def fragment_messages(writer: bytes, seq: int, related: SampleIdentity | None, payload: bytes,
                      size: int, *, little: bool = True,
                      stamp: tuple[int, int] | None = None) -> list[bytes]:
    """The DATA_FRAGs of `payload` in fragments of `size` bytes, one per message; the first
    names `related` in its inline QoS (as Fast DDS sends them), if given; each message
    begins with an INFO_TS of `stamp`, if given."""
    o, e = ("<", 0x01) if little else (">", 0x00)
    info_ts = b"" if stamp is None else struct.pack(o + "BBHiI", 0x09, e, 8, *stamp)
    messages = []
    for number, at in enumerate(range(0, len(payload), size), start=1):
        qos = related_qos(related, o) if number == 1 and related is not None else b""
        body = struct.pack(o + "HH", 0, 28) + b"\x00\x00\x12\x04" + writer[12:] + \
            struct.pack(o + "iI", seq >> 32, seq & 0xFFFFFFFF) + \
            struct.pack(o + "IHHI", number, 1, size, len(payload)) + qos + \
            payload[at:at + size]
        messages.append(b"RTPS\x02\x03\x01\x0f" + writer[:12] + info_ts +
                        struct.pack(o + "BBH", 0x16, e | (0x02 if qos else 0), len(body)) + body)
    return messages


def test_an_expected_reply_is_kept_only_from_its_writer_and_for_its_identity(
        capture: tuple[IdentityCapture, int]) -> None:
    """A reply Cyclone dropped as history is still in the capture: a call that expects it
    (its request's identity, the reply writers matched with its reader) can take it there.
    Nothing else is kept: not another request's reply, not a reply from another writer."""
    tail, writer = capture
    ours, reply = SampleIdentity(REQUEST_WRITER, 3), b"\x00\x01\x00\x00ours...."
    os.write(writer, pcap_record(data_message(SERVER, 1, ours, reply)))
    assert not tail.expect_reply(ours, [SERVER])  # nobody uses the capture: nothing read
    tail.use()
    assert tail.expect_reply(ours, [SERVER])
    assert tail.captured_reply(ours) is None  # what came before is not looked at
    for little in (True, False):
        os.write(writer, pcap_record(data_message(OTHER_WRITER, 2, ours, b"\x00\x01\x00\x00x",
                                                  little=little)))  # not the matched writer
        os.write(writer, pcap_record(data_message(SERVER, 3, SampleIdentity(OTHER_CLIENT, 3),
                                                  b"\x00\x01\x00\x00y", little=little)))
        os.write(writer, pcap_record(data_message(SERVER, 4, SampleIdentity(REQUEST_WRITER, 2),
                                                  b"\x00\x01\x00\x00z", little=little)))
        os.write(writer, pcap_record(data_message(SERVER, 5, None, b"\x00\x01\x00\x00w",
                                                  little=little)))
    assert tail.captured_reply(ours) is None
    os.write(writer, pcap_record(data_message(SERVER, 6, ours, reply), ttl=255))  # one we sent
    assert tail.captured_reply(ours) is None
    os.write(writer, pcap_record(data_message(SERVER, 6, ours, reply, little=False)))
    os.write(writer, pcap_record(data_message(SERVER, 6, ours, b"\x00\x01\x00\x00again")))
    assert tail.captured_reply(ours) == reply  # the first one
    assert tail._replies.held == len(reply)
    tail.forget_reply(ours)
    assert tail.captured_reply(ours) is None
    assert tail._replies.held == 0
    tail.unuse()


def test_a_fragmented_reply_is_put_together_from_its_pieces(
        capture: tuple[IdentityCapture, int]) -> None:
    tail, writer = capture
    tail.use()
    ours, theirs = SampleIdentity(REQUEST_WRITER, 1), SampleIdentity(OTHER_CLIENT, 1)
    reply = b"\x00\x01\x00\x00" + bytes(range(256)) * 11 + b"end"
    assert tail.expect_reply(ours, [SERVER])
    mine = fragment_messages(SERVER, 7, ours, reply, 1000)
    other = fragment_messages(SERVER, 8, theirs, reply[::-1], 1000)
    elsewhere = fragment_messages(OTHER_WRITER, 7, ours, bytes(len(reply)), 1000)
    assert len(mine) == 3
    # The later pieces first (the first one was dropped at our socket and sent again),
    # interleaved with another client's reply and another writer's sample naming ours.
    for message in [mine[2], other[1], elsewhere[0], other[0], mine[1], elsewhere[1], other[2]]:
        os.write(writer, pcap_record(message))
    assert tail.captured_reply(ours) is None
    # ours being put together (its bytes, a byte a fragment, its objects); theirs let go of
    assert tail._replies.held == len(reply) + 3 + captured_replies.ASSEMBLY_OVERHEAD
    os.write(writer, pcap_record(mine[0]))
    assert tail.captured_reply(ours) == reply
    tail.forget_reply(ours)
    assert tail._replies.held == 0
    theirs_expected = SampleIdentity(REQUEST_WRITER, 2)
    assert tail.expect_reply(theirs_expected, [SERVER])
    for message in fragment_messages(SERVER, 9, theirs_expected, reply, 512, little=False):
        os.write(writer, pcap_record(message))
    assert tail.captured_reply(theirs_expected) == reply
    tail.forget_reply(theirs_expected)
    tail.unuse()


def test_captured_replies_stay_bounded(capture: tuple[IdentityCapture, int],
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """A reply bigger than MAX_SAMPLE is not put together, and pieces of samples whose first
    fragment has not come are let go of, oldest first, to stay within HELD_BUDGET."""
    monkeypatch.setattr(captured_replies, "MAX_SAMPLE", 4000)
    monkeypatch.setattr(captured_replies, "HELD_BUDGET", 6000)
    tail, writer = capture
    tail.use()
    ours = SampleIdentity(REQUEST_WRITER, 1)
    assert tail.expect_reply(ours, [SERVER])
    for message in fragment_messages(SERVER, 1, ours, bytes(5000), 1000):
        os.write(writer, pcap_record(message))
    assert tail.captured_reply(ours) is None
    assert tail._replies.held == 0
    for seq in range(2, 12):  # later pieces of samples whose first fragment never came
        os.write(writer, pcap_record(fragment_messages(SERVER, seq, ours, bytes(3000), 1000)[1]))
    tail.drain()
    assert tail._replies.held <= 6000
    reply = b"\x00\x01\x00\x00" + b"r" * 2996
    for message in fragment_messages(SERVER, 20, ours, reply, 1000):
        os.write(writer, pcap_record(message))
    assert tail.captured_reply(ours) == reply  # room made for it
    tail.forget_reply(ours)
    assert tail._replies.held == 0
    tail.unuse()


def data_with_qos(qos: bytes, payload: bytes, *, claimed_extra: int = 0) -> bytes:
    """One little-endian DATA of SERVER with inline QoS `qos` (as given: parameters and
    sentinel) and `payload`, whose submessage header claims `claimed_extra` bytes more than
    the message holds."""
    body = struct.pack("<HH", 0, 16) + b"\x00\x00\x12\x04" + WRITER_ID + \
        struct.pack("<iI", 0, 1) + qos + payload
    info_ts = struct.pack("<BBHiI", 0x09, 0x01, 8, 1_700_000_000, 0)
    return b"RTPS\x02\x03\x01\x0f" + PREFIX + info_ts + \
        struct.pack("<BBH", 0x15, 0x01 | 0x02 | 0x04, len(body) + claimed_extra) + body


def test_a_reply_is_taken_only_from_what_cyclone_accepts_as_well_formed(
        capture: tuple[IdentityCapture, int]) -> None:
    """The payload starts after the inline QoS' sentinel (PID 0x0001 exactly: a vendor's
    0x8001 is just a parameter); a parameter list with a length not a multiple of 4, or a
    DATA whose submessage claims more bytes than its message holds, is malformed (Cyclone
    drops it: DDSI 9.4.2.11) and never taken as our reply, cut short or shifted; so is a DATA
    whose payload has no room for its 4-byte encapsulation header (it would block the real
    reply: the first one kept wins)."""
    tail, writer = capture
    tail.use()
    ours, reply = SampleIdentity(REQUEST_WRITER, 1), b"\x00\x01\x00\x00ours...."
    vendor = struct.pack("<HH", 0x8001, 4) + b"\x00\x01\x00\x00"  # looks like a header
    assert tail.expect_reply(ours, [SERVER])
    os.write(writer, pcap_record(data_with_qos(vendor + related_qos(ours, "<"), reply)))
    assert tail.captured_reply(ours) == reply
    tail.forget_reply(ours)

    odd = struct.pack("<HH", 0x0070, 3) + b"abc"
    for message in (data_with_qos(odd + related_qos(ours, "<"), reply),
                    data_with_qos(related_qos(ours, "<"), reply, claimed_extra=8),
                    data_with_qos(related_qos(ours, "<"), b"\x00\x01")):  # no room for a header
        assert tail.expect_reply(ours, [SERVER])
        os.write(writer, pcap_record(message))
        assert tail.captured_reply(ours) is None
        tail.forget_reply(ours)
    tail.unuse()


def fragment_piece(seq: int, first: int, count: int, size: int, sample_size: int,
                   related: SampleIdentity | None = None) -> bytes:
    """One DATA_FRAG of SERVER carrying fragments first .. first + count - 1 (zeros)."""
    qos = b"" if related is None else related_qos(related, "<")
    length = min(count * size, sample_size - (first - 1) * size)
    body = struct.pack("<HH", 0, 28) + b"\x00\x00\x12\x04" + WRITER_ID + \
        struct.pack("<iI", 0, seq) + struct.pack("<IHHI", first, count, size, sample_size) + \
        qos + bytes(length)
    return b"RTPS\x02\x03\x01\x0f" + PREFIX + \
        struct.pack("<BBH", 0x16, 0x01 | (0x02 if qos else 0), len(body)) + body


def feed(collector: captured_replies.ReplyCollector, message: bytes) -> None:
    for piece in parse_rtps(message, 0, None, collector.writers):
        if isinstance(piece, rtps_capture.ReceivedPiece):
            collector.piece(piece, message)


def traced_while(action: Callable[[], object]) -> int:
    """Bytes allocated by `action` and still held after it."""
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        action()
        return tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()


def test_fragments_cost_no_more_memory_than_is_counted_as_held() -> None:
    """What the collector holds is what its budget counts, whatever the fragments claim:
    1-byte fragments (a million fragment numbers for one sample), or a flood of tiny samples
    whose first fragment never comes."""
    collector = captured_replies.ReplyCollector()
    collector.expect(SampleIdentity(REQUEST_WRITER, 1), [SERVER])
    sample_size = 1 << 20
    messages = [fragment_piece(1, first, 0xFF00, 1, sample_size)
                for first in range(2, sample_size, 0xFF00)]

    def pieces() -> None:
        for message in messages:
            feed(collector, message)
    assert traced_while(pieces) <= collector.held + (64 << 10)

    flood = captured_replies.ReplyCollector()
    flood.expect(SampleIdentity(REQUEST_WRITER, 1), [SERVER])
    tiny = [fragment_piece(seq, 2, 1, 1, 2) for seq in range(2, 20_002)]

    def samples() -> None:
        for message in tiny:
            feed(flood, message)
    assert traced_while(samples) <= flood.held + (64 << 10)


def test_a_datagram_the_parser_fails_on_is_skipped_and_the_capture_goes_on(
        capture: tuple[IdentityCapture, int], monkeypatch: pytest.MonkeyPatch) -> None:
    """Whatever a datagram makes the parser raise, the capture skips that datagram (counted,
    said once) and goes on: no exception out of a drain or a lookup, none killing the drain
    thread, nothing left unconsumed to fail again on every drain."""
    parse = rtps_capture.parse_rtps

    def fails_on_poison(buf: bytes, start: int = 0, end: int | None = None,
                        pieces_of: Container[bytes] = ()) -> Iterator[rtps_capture.Received]:
        if b"poison" in bytes(buf[start:end]):
            raise ValueError("a parser bug")
        return parse(buf, start, end, pieces_of)
    monkeypatch.setattr(rtps_capture, "parse_rtps", fails_on_poison)
    tail, writer = capture
    tail.use()
    mine = SampleIdentity(REQUEST_WRITER, 2)
    os.write(writer, pcap_record(rtps_message(1, mine, payload=b"\x00\x01\x00\x00poison")) * 2)
    os.write(writer, pcap_record(rtps_message(2, mine, stamp=(1_700_000_001, 0))))
    tail.drain()
    assert tail.lookup(SERVER, nanoseconds(1_700_000_001, 0)) == mine
    assert tail.unparsed == 2
    tail.unuse()


def test_a_sample_that_does_not_fit_the_budget_is_never_allocated(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A fragment claiming a sample the budget has no room for costs nothing (checked before
    anything is made: each such 57-byte datagram cost 15 ms of zeroing otherwise)."""
    monkeypatch.setattr(captured_replies, "HELD_BUDGET", 1 << 20)
    collector = captured_replies.ReplyCollector()
    collector.expect(SampleIdentity(REQUEST_WRITER, 1), [SERVER])
    message = fragment_piece(2, 2, 1, 1, 8 << 20)
    tracemalloc.start()
    try:
        feed(collector, message)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert collector.held == 0
    assert peak < 1 << 20


def test_a_fragment_sent_again_after_its_sample_was_put_together_is_not_kept() -> None:
    """A repair of a fragment of a sample already put together (sent again on a NACK) starts
    no new assembly: it would hold the whole sample's room for nothing."""
    collector = captured_replies.ReplyCollector()
    ours = SampleIdentity(REQUEST_WRITER, 1)
    collector.expect(ours, [SERVER])
    reply = b"\x00\x01\x00\x00" + bytes(2996)
    pieces = fragment_messages(SERVER, 7, ours, reply, 1000)
    for message in pieces:
        feed(collector, message)
    assert collector.take(ours) == reply
    feed(collector, pieces[1])
    assert collector.held == len(reply)


GOAL = bytes(range(200, 216))
OTHER_GOAL = bytes(range(216, 232))


def feedback_payload(goal: bytes, body: bytes, *, little: bool = True) -> bytes:
    """A feedback message's serialized payload: plain CDR, the goal id first."""
    return (b"\x00\x01\x00\x00" if little else b"\x00\x00\x00\x00") + goal + body


def at(second: int) -> tuple[int, int]:
    return (1_700_000_000 + second, 0)


def test_a_goal_s_feedback_is_kept_only_from_its_writers_and_for_its_goal(
        capture: tuple[IdentityCapture, int]) -> None:
    """A feedback Cyclone dropped as history is still in the capture: a goal that expects its
    feedback (its goal id, the feedback writers matched with the client's reader) finds
    there what came before the first one its reader delivered. Nothing else is kept: not
    another goal's feedback, not a sample of another writer, not one we sent, not one that
    came before the goal said it waits; a repair of one kept is not kept twice."""
    tail, writer = capture
    first = feedback_payload(GOAL, b"first...")
    os.write(writer, pcap_record(data_message(SERVER, 1, None, first, stamp=at(1))))
    assert not tail.expect_feedback(GOAL, [SERVER])  # nobody uses the capture: nothing read
    tail.use()
    assert tail.expect_feedback(GOAL, [SERVER])
    assert tail.captured_feedback(GOAL) == []  # what came before is not looked at
    for little in (True, False):
        os.write(writer, pcap_record(data_message(  # not a matched writer
            OTHER_WRITER, 2, None, feedback_payload(GOAL, b"x", little=little), little=little,
            stamp=at(2))))
        os.write(writer, pcap_record(data_message(  # another goal's
            SERVER, 3, None, feedback_payload(OTHER_GOAL, b"y", little=little), little=little,
            stamp=at(3))))
    os.write(writer, pcap_record(data_message(  # not plain CDR (XCDR2): not read
        SERVER, 4, None, b"\x00\x07\x00\x00" + GOAL + b"z", stamp=at(4))))
    os.write(writer, pcap_record(data_message(SERVER, 5, None, first, stamp=at(5)),
                                 ttl=255))  # one we sent
    assert tail.captured_feedback(GOAL) == []
    second = feedback_payload(GOAL, b"second", little=False)
    third = feedback_payload(GOAL, b"third..")
    os.write(writer, pcap_record(data_message(SERVER, 7, None, second, little=False,
                                              stamp=at(7))))
    os.write(writer, pcap_record(data_message(SERVER, 8, None, third, stamp=at(8))))
    os.write(writer, pcap_record(data_message(SERVER, 7, None, second, stamp=at(7))))  # repair
    kept = tail.captured_feedback(GOAL)
    assert [(s.writer_guid, s.seq, s.source_timestamp, s.payload) for s in kept] == \
        [(SERVER, 7, nanoseconds(*at(7)), second), (SERVER, 8, nanoseconds(*at(8)), third)]
    assert tail._replies.held == len(second) + len(third)
    # What came before the one the reader delivered (same writer), and nothing if that one
    # is not in the capture (nothing can be put before it then)
    assert [s.seq for s in tail.feedback_before(GOAL, SERVER, nanoseconds(*at(8))) or ()] == [7]
    assert tail.feedback_before(GOAL, SERVER, nanoseconds(*at(7))) == []
    assert tail.feedback_before(GOAL, SERVER, nanoseconds(*at(9))) is None
    assert tail.feedback_before(GOAL, OTHER_WRITER, nanoseconds(*at(2))) is None
    tail.forget_feedback(GOAL)
    assert tail.captured_feedback(GOAL) == []
    assert tail._replies.held == 0
    tail.unuse()


def test_a_fragmented_feedback_is_put_together_from_its_pieces(
        capture: tuple[IdentityCapture, int]) -> None:
    """A feedback sent in DATA_FRAGs names its goal in its first fragment: put together from
    its pieces in any order, interleaved with another goal's; the other goal's let go of."""
    tail, writer = capture
    tail.use()
    assert tail.expect_feedback(GOAL, [SERVER])
    ours = feedback_payload(GOAL, bytes(range(256)) * 11)
    theirs = feedback_payload(OTHER_GOAL, bytes(len(ours) - 20))
    mine = fragment_messages(SERVER, 7, None, ours, 1000, stamp=at(7))
    other = fragment_messages(SERVER, 8, None, theirs, 1000, stamp=at(8))
    elsewhere = fragment_messages(OTHER_WRITER, 7, None, ours, 1000, stamp=at(7))
    assert len(mine) == 3
    for message in [mine[2], other[0], elsewhere[0], other[1], mine[1], elsewhere[1],
                    other[2], elsewhere[2]]:
        os.write(writer, pcap_record(message))
    assert tail.captured_feedback(GOAL) == []
    # ours being put together (its bytes, a byte a fragment, its objects); theirs let go of
    assert tail._replies.held == len(ours) + 3 + captured_replies.ASSEMBLY_OVERHEAD
    os.write(writer, pcap_record(mine[0]))
    kept = tail.captured_feedback(GOAL)
    assert [(s.seq, s.source_timestamp, s.payload) for s in kept] == \
        [(7, nanoseconds(*at(7)), ours)]
    assert tail._replies.held == len(ours)
    tail.forget_feedback(GOAL)
    assert tail._replies.held == 0
    tail.unuse()


def test_a_goal_s_kept_feedback_stays_bounded(capture: tuple[IdentityCapture, int],
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """At most FEEDBACK_KEPT samples a goal (the ones before its reader's first are what is
    looked for), within the same budget as replies; a call's reply and a goal's feedback
    kept side by side go each with its own forget."""
    monkeypatch.setattr(captured_replies, "FEEDBACK_KEPT", 3)
    tail, writer = capture
    tail.use()
    reply_to = SampleIdentity(REQUEST_WRITER, 1)
    assert tail.expect_feedback(GOAL, [SERVER])
    assert tail.expect_reply(reply_to, [OTHER_WRITER])
    for seq in range(1, 6):
        os.write(writer, pcap_record(data_message(
            SERVER, seq, None, feedback_payload(GOAL, b"f%d" % seq), stamp=at(seq))))
    reply = b"\x00\x01\x00\x00reply"
    os.write(writer, pcap_record(data_message(OTHER_WRITER, 1, reply_to, reply)))
    assert [s.seq for s in tail.captured_feedback(GOAL)] == [1, 2, 3]
    assert tail.captured_reply(reply_to) == reply
    tail.forget_feedback(GOAL)
    assert tail.captured_reply(reply_to) == reply
    assert tail._replies.held == len(reply)
    tail.forget_reply(reply_to)
    assert tail._replies.held == 0
    tail.unuse()


def acknack_message(reader: bytes, writer: bytes, missing: list[int], *, base: int = 16,
                    little: bool = True) -> bytes:
    """An ACKNACK our reader sends `writer` (INFO_DST: the writer's participant): the samples
    from `base` on that it misses (none: it has everything before `base`)."""
    o, e = ("<", 0x01) if little else (">", 0x00)
    bits = max(missing, default=base - 1) - base + 1
    words = [0] * ((bits + 31) // 32)
    for seq in missing:
        words[(seq - base) // 32] |= 1 << (31 - (seq - base) % 32)
    body = reader[12:] + writer[12:] + struct.pack(o + "iII", 0, base, bits) + \
        struct.pack(o + f"{len(words)}I", *words) + struct.pack(o + "i", 7)
    info_dst = struct.pack(o + "BBH", 0x0E, e, 12) + writer[:12]
    return b"RTPS\x02\x01\x01\x10" + reader[:12] + info_dst + \
        struct.pack(o + "BBH", 0x06, e | 0x02, len(body)) + body


def test_parse_finds_the_acknacks_we_sent_and_whether_they_ask_again() -> None:
    for little in (True, False):
        assert list(rtps_capture.parse_acknacks(acknack_message(
            OUR_READER, SERVER, [16, 40], little=little))) == \
            [rtps_capture.SentAcknack(OUR_READER, SERVER, True, 16)]
        assert list(rtps_capture.parse_acknacks(acknack_message(
            OUR_READER, SERVER, [], little=little, base=40))) == \
            [rtps_capture.SentAcknack(OUR_READER, SERVER, False, 40)]


def test_a_repair_is_owed_until_a_heartbeat_since_the_mark_was_answered_asking_nothing(
        capture: tuple[IdentityCapture, int]) -> None:
    """A goal's feedback dropped at our socket comes again only after a HEARTBEAT of its
    writer reached our reader: until one heard after the goal's end (the mark) was answered
    by an ACKNACK that asks for nothing, the repair may still be owed. Before the mark, a
    HEARTBEAT may have been sent before the feedback was written; an answer asking for
    samples again means it is owed; an answer of another reader tells nothing of ours."""
    tail, writer = capture
    tail.use()
    to_us = pcap_record(heartbeat_message(bytes(4), destination=OUR_PREFIX))  # all our readers
    os.write(writer, to_us)
    os.write(writer, pcap_record(acknack_message(OUR_READER, SERVER, []), ttl=255))
    end = tail.mark()
    assert tail.repair_owed(SERVER, OUR_READER, end)  # heard, answered, but before the end
    os.write(writer, pcap_record(acknack_message(OUR_READER, SERVER, []), ttl=255))
    assert tail.repair_owed(SERVER, OUR_READER, end)  # an answer to no HEARTBEAT since
    os.write(writer, to_us)
    assert tail.repair_owed(SERVER, OUR_READER, end)  # heard; not answered yet
    os.write(writer, pcap_record(acknack_message(OUR_READER, SERVER, [16]), ttl=255))
    assert tail.repair_owed(SERVER, OUR_READER, end)  # it asks for #16 again
    other = OUR_PREFIX + b"\x00\x00\x39\x04"
    os.write(writer, pcap_record(acknack_message(other, SERVER, []), ttl=255))
    assert tail.repair_owed(SERVER, OUR_READER, end)  # another reader's answer
    os.write(writer, pcap_record(acknack_message(OUR_READER, SERVER, [], base=17), ttl=255))
    assert not tail.repair_owed(SERVER, OUR_READER, end)  # everything taken
    assert tail.repair_owed(OTHER_WRITER, OUR_READER, end)  # another writer: never heard
    os.write(writer, pcap_record(heartbeat_message(OUR_READER[12:], destination=OUR_PREFIX)))
    os.write(writer, pcap_record(acknack_message(OUR_READER, SERVER, [17]), ttl=255))
    assert not tail.repair_owed(SERVER, OUR_READER, end)  # later samples are not the goal's
    assert tail.repair_owed(SERVER, OUR_READER, tail.mark())  # (but a later goal's)
    tail.unuse()


def test_an_acknack_asking_nothing_with_its_base_not_past_the_heartbeat_answers_nothing(
        capture: tuple[IdentityCapture, int]) -> None:
    """A repair is owed until an ACKNACK takes all the HEARTBEAT named: its base past the
    HEARTBEAT's last sequence number. Cyclone answers a HEARTBEAT within NackDelay of its last
    NACK with an empty set whose base is the sample it still misses (ddsi_acknack.c,
    AANR_SUPPRESSED_NACK), and an ACKNACK built before a HEARTBEAT was applied can be captured
    after it: neither says the sample came. (Taken as answers, a Fast DDS server's feedback
    dropped at our socket and dropped again on its repair was given up on.)"""
    tail, writer = capture
    tail.use()
    end = tail.mark()
    os.write(writer, pcap_record(heartbeat_message(OUR_READER[12:], destination=OUR_PREFIX,
                                                   last=16)))
    os.write(writer, pcap_record(acknack_message(OUR_READER, SERVER, [16]), ttl=255))
    assert tail.repair_owed(SERVER, OUR_READER, end)  # NACKed
    suppressed = pcap_record(acknack_message(OUR_READER, SERVER, [], base=16), ttl=255)
    os.write(writer, suppressed)
    assert tail.repair_owed(SERVER, OUR_READER, end)  # #16 still missing, the NACK held back
    os.write(writer, pcap_record(acknack_message(OUR_READER, SERVER, [], base=12), ttl=255))
    assert tail.repair_owed(SERVER, OUR_READER, end)  # built before #12 to #16 were named
    os.write(writer, pcap_record(acknack_message(OUR_READER, SERVER, [], base=17), ttl=255))
    assert not tail.repair_owed(SERVER, OUR_READER, end)  # #16 taken
    later = tail.mark()
    os.write(writer, pcap_record(heartbeat_message(bytes(4), destination=OUR_PREFIX, last=20)))
    os.write(writer, pcap_record(acknack_message(OUR_READER, SERVER, [], base=17), ttl=255))
    assert tail.repair_owed(SERVER, OUR_READER, later)  # to all our readers: #17 to #20 owed
    os.write(writer, pcap_record(acknack_message(OUR_READER, SERVER, [], base=21), ttl=255))
    assert not tail.repair_owed(SERVER, OUR_READER, later)
    tail.unuse()
