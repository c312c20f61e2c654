"""The RTPS related sample identity of received samples, read from Cyclone's packet capture.

rmw_fastrtps names the request a reply answers only in the reply's RTPS inline QoS
(PID_RELATED_SAMPLE_IDENTITY 0x0083, and Fast DDS' own 0x800f: request writer GUID and
request sequence number). Cyclone DDS 11 parses inline QoS but keeps nothing of it but
status info and key hash, so no API shows it (docs/design/rpc-identity.md). What Cyclone 11
does have is `Tracing/PacketCaptureFile`: it writes every UDP datagram it sends or receives,
whole, to a pcap file, from the socket thread, before the datagram is processed. So by the
time a sample can be taken from a reader, the datagram that carried it is in that file (or
in the C library's buffer of that file: `flush` pushes it out).

`IdentityCapture` tails that file (a regular file, so Cyclone's threads never wait for us:
a pipe could fill and block a DDS write that holds the GIL) through a read-only mapping, so
nothing is copied. While no client needs identities it only steps over record headers;
while one does, it walks the submessages of received datagrams and keeps
`(writer GUID, source timestamp) -> related identity` for the DATA and first DATA_FRAG
submessages whose inline QoS carries one. A reader takes a sample, then asks
`lookup(writer_guid, source_timestamp)`. The consumed part of the file is given back to the
system (a hole punched in the tmpfs file), so memory stays bounded by what arrived since
the last drain; the file has no name once Cyclone has opened it, so a killed process leaves
nothing behind. Limits: UDPv4 only (Cyclone's capture is), and nothing under DDS-Security
payload or submessage protection can be read.

It also notes the HEARTBEATs that arrived, by writer and addressee, and where in the capture
(`heard_heartbeat`): the first one Cyclone applies to a new reader decides which of the
writer's samples that reader takes (a Fast DDS writer announces itself to a new reader with
one GAP+HEARTBEAT; a Cyclone writer's reader takes nothing before one), and a client whose
reader has not heard one must not send its request or goal yet (handshake.py). With the
ACKNACKs our readers send (the one kind of sent datagram it reads), it tells whether a reader
may still be owed a sample a writer sent before some point (`repair_owed`): a goal's feedback
dropped at our socket whose repair waits for a HEARTBEAT that our socket dropped too.

And it keeps the payload of the reply a call expects (`expect_reply`: its request's identity
and the reply writers matched with its reader; captured_replies.py), so that a reply Cyclone
dropped as history after it reached our socket can still be delivered (`captured_reply`);
likewise an action goal's feedback samples (`expect_feedback`: its goal id and the feedback
writers matched with the client's reader), so that a first feedback dropped so still reaches
the goal, before the feedback the reader did deliver (`feedback_before`, `captured_feedback`).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import logging
import mmap
import os
import struct
import sys
import tempfile
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Collection, Container, Iterator
from pathlib import Path
from typing import TypeVar

import msgspec

from .captured_replies import CapturedSample, ReplyCollector

log = logging.getLogger(__name__)
T = TypeVar("T")

PID_SENTINEL = 0x0001
PID_RELATED_SAMPLE_IDENTITY = 0x0083  # OMG DDS-RPC
PID_FASTDDS_RELATED_SAMPLE_IDENTITY = 0x800F  # Fast DDS' older vendor-specific id
RELATED_PIDS = (PID_RELATED_SAMPLE_IDENTITY, PID_FASTDDS_RELATED_SAMPLE_IDENTITY)

PAD, ACKNACK, HEARTBEAT, INFO_TS, INFO_SRC, INFO_DST, DATA, DATA_FRAG = \
    0x01, 0x06, 0x07, 0x09, 0x0C, 0x0E, 0x15, 0x16
FLAG_LITTLE, FLAG_INLINE_QOS, FLAG_INVALIDATE = 0x01, 0x02, 0x02
FLAG_DATA, FLAG_FRAG_KEY = 0x04, 0x04  # DATA: has data; DATA_FRAG: carries a key
RTPS_HEADER_SIZE = 20
IP_UDP_SIZE = 28  # Cyclone's capture writes a made-up IPv4 + UDP header before each datagram
TTL_OFFSET = 8  # ... whose TTL is 128 on received datagrams, 255 on sent ones
RECEIVED_TTL = 128
PCAP_HEADER_SIZE, RECORD_HEADER_SIZE = 24, 16
PCAP_MAGICS = {b"\xd4\xc3\xb2\xa1": True, b"\xa1\xb2\xc3\xd4": False}  # → little-endian

KEPT_IDENTITIES = 8192  # newest identified samples remembered; far more than a reader keeps
KEPT_HEARTBEATS = 4096  # newest (writer, addressee) pairs a HEARTBEAT was heard for
NOT_HEARD = (-1, 0)  # (file offset, last sequence number) of no HEARTBEAT
KEPT_ACKNACKS = 4096  # newest (our reader, writer) pairs we sent an ACKNACK for
UNKNOWN_PREFIX = bytes(12)  # no INFO_DST before it: addressed to whoever received it
ENTITYID_UNKNOWN = bytes(4)
DRAIN_PERIOD = 0.05  # s between background drains of the capture file
CHUNK = 1 << 20  # bytes of records consumed per hold of the lock
MISS_BUDGET = 8 << 20  # bytes a lookup that missed may consume itself before answering
PUNCH_AFTER = 1 << 20  # bytes consumed before they are given back

_SUBMESSAGE = struct.Struct("<BBH")


class SampleIdentity(msgspec.Struct, frozen=True):
    """A DDS sample's identity: its writer's GUID (16 bytes) and its sequence number."""

    writer_guid: bytes
    seq: int


class ReceivedData(msgspec.Struct, frozen=True):
    """A received DATA (or first DATA_FRAG) submessage that names a related sample."""

    writer_guid: bytes
    seq: int
    source_timestamp: int  # ns since the epoch, converted as Cyclone does
    related: SampleIdentity


class ReceivedHeartbeat(msgspec.Struct, frozen=True):
    """A received HEARTBEAT: its writer, to whom it is addressed, and the last sequence
    number the writer says it has written."""

    writer_guid: bytes
    # The INFO_DST prefix (UNKNOWN_PREFIX if none: to whoever received it) + the reader's
    # entity id (ENTITYID_UNKNOWN: to every reader of that participant matched with the writer)
    reader_guid: bytes
    last_sn: int


def capture_config(path: str | Path) -> str:
    """The Cyclone configuration fragment that captures the domain's traffic into `path`."""
    return ("<CycloneDDS><Domain Id=\"any\"><Tracing><PacketCaptureFile>"
            f"{path}</PacketCaptureFile></Tracing></Domain></CycloneDDS>")


def nanoseconds(seconds: int, fraction: int) -> int:
    """An RTPS Time_t as Cyclone 11 converts it (rounding the 2^-32 s fraction to nearest)."""
    return seconds * 1_000_000_000 + ((1 << 31) + fraction * 1_000_000_000 >> 32)


def _inline_related(buf: bytes | mmap.mmap, offset: int, end: int,
                    order: str) -> SampleIdentity | None:
    """The related sample identity in a parameter list from `offset` to `end`, if any."""
    while offset + 4 <= end:
        pid, length = struct.unpack_from(order + "HH", buf, offset)
        offset += 4
        pid &= 0x3FFF if pid & 0x8000 == 0 else 0xFFFF  # drop the must-understand bit
        if pid == PID_SENTINEL:
            return None
        if pid in RELATED_PIDS:
            if length < 24 or offset + 24 > end:
                return None
            high, low = struct.unpack_from(order + "iI", buf, offset + 16)
            return SampleIdentity(bytes(buf[offset:offset + 16]), (high << 32) | low)
        offset += length
    return None


class ReceivedPiece(msgspec.Struct, frozen=True):
    """Where a received DATA's serialized payload, or a DATA_FRAG's fragments, lie in the
    buffer parsed (`buf[start:end]`, `at` bytes into the sample of `sample_size` bytes), for
    writers whose samples someone waits for (see captured_replies.py)."""

    writer_guid: bytes
    seq: int
    related: SampleIdentity | None  # from the inline QoS (a DATA_FRAG's first fragment only)
    start: int
    end: int
    at: int
    sample_size: int
    fragment_size: int = 0  # 0: a whole DATA
    first_fragment: int = 0  # fragment numbers first_fragment .. + fragments - 1
    fragments: int = 0
    source_timestamp: int | None = None  # ns, from the INFO_TS before it (None: none)


Received = ReceivedData | ReceivedHeartbeat | ReceivedPiece


class SentAcknack(msgspec.Struct, frozen=True):
    """An ACKNACK one of our readers sent: whose, to which writer, whether it asks for
    samples to be sent again (a non-empty set: the reader misses them), and its base: the
    reader has every sample before it."""

    reader_guid: bytes
    writer_guid: bytes
    missing: bool
    base: int


def parse_acknacks(buf: bytes | mmap.mmap, start: int = 0,
                   end: int | None = None) -> Iterator[SentAcknack]:
    """The ACKNACKs in the RTPS message `buf[start:end]` that our participant sent (its
    GUID prefix in the header; the writer's in the INFO_DST before them)."""
    end = len(buf) if end is None else end
    prefix = _sender_prefix(buf, start, end)
    if prefix is None:
        return
    destination = UNKNOWN_PREFIX
    for kind, flags, body, stop in _submessages(buf, start, end):
        if kind == INFO_DST and stop - body >= 12:
            destination = bytes(buf[body:body + 12])
        elif kind == ACKNACK and stop - body >= 24:
            order = "<" if flags & FLAG_LITTLE else ">"
            (bits,) = struct.unpack_from(order + "I", buf, body + 16)
            words = min((bits + 31) // 32, (stop - body - 20) // 4)
            asked = any(buf[body + 20:body + 20 + 4 * words])
            yield SentAcknack(prefix + bytes(buf[body:body + 4]),
                              destination + bytes(buf[body + 4:body + 8]), bits > 0 and asked,
                              _sequence_number(buf, body + 8, order))


def _sequence_number(buf: bytes | mmap.mmap, offset: int, order: str) -> int:
    """The RTPS SequenceNumber_t at `offset` (high: signed 32 bits, low: unsigned)."""
    high, low = struct.unpack_from(order + "iI", buf, offset)
    return int((high << 32) | low)


def _sender_prefix(buf: bytes | mmap.mmap, start: int, end: int) -> bytes | None:
    """The GUID prefix in the header of the RTPS message `buf[start:end]`; None when it is
    no RTPS message."""
    if end - start < RTPS_HEADER_SIZE or buf[start:start + 4] != b"RTPS":
        return None
    return bytes(buf[start + 8:start + 20])


def _submessages(buf: bytes | mmap.mmap, start: int,
                 end: int) -> Iterator[tuple[int, int, int, int]]:
    """Each submessage of the RTPS message `buf[start:end]`, in order: its kind, flags, and
    where its body starts and stops. Ends at one that claims more than the message holds:
    malformed, the rest too (Cyclone)."""
    offset = start + RTPS_HEADER_SIZE
    while offset + 4 <= end:
        kind, flags, length = _SUBMESSAGE.unpack_from(buf, offset)
        if not flags & FLAG_LITTLE:
            length = (length & 0xFF) << 8 | length >> 8
        body = offset + 4
        if body + length > end:
            return
        stop = end if length == 0 and kind not in (INFO_TS, PAD) else body + length
        yield kind, flags, body, stop
        offset = stop


def parse_rtps(buf: bytes | mmap.mmap, start: int = 0, end: int | None = None,
               pieces_of: Container[bytes] = ()) -> Iterator[Received]:
    """The DATA and first DATA_FRAG submessages naming a related sample, and the HEARTBEATs,
    in the RTPS message `buf[start:end]`, in order; for DATA and DATA_FRAG of the writers in
    `pieces_of`, also where their payload lies (after the ReceivedData of the same
    submessage, if any). Other submessages cost one header read each."""
    end = len(buf) if end is None else end
    prefix = _sender_prefix(buf, start, end)
    if prefix is None:
        return
    destination = UNKNOWN_PREFIX
    timestamp: int | None = None
    for kind, flags, body, stop in _submessages(buf, start, end):
        little = flags & FLAG_LITTLE
        if kind in (DATA, DATA_FRAG):
            order = "<" if little else ">"
            found = None
            if flags & FLAG_INLINE_QOS and timestamp is not None and stop - body >= 24:
                found = _data(buf, body, stop, order, kind, prefix, timestamp)
                if found is not None:
                    yield found
            if pieces_of and stop - body >= 24 and \
                    prefix + bytes(buf[body + 8:body + 12]) in pieces_of:
                piece = _piece(buf, body, stop, order, kind, flags, prefix, timestamp)
                if piece is not None:
                    yield piece
        elif kind == INFO_TS:
            timestamp = None if flags & FLAG_INVALIDATE or stop - body < 8 else \
                nanoseconds(*struct.unpack_from("<iI" if little else ">iI", buf, body))
        elif kind == HEARTBEAT and stop - body >= 28:
            yield ReceivedHeartbeat(prefix + bytes(buf[body + 4:body + 8]),
                                    destination + bytes(buf[body:body + 4]),
                                    _sequence_number(buf, body + 16, "<" if little else ">"))
        elif kind == INFO_SRC and stop - body >= 20:
            prefix = bytes(buf[body + 8:body + 20])
        elif kind == INFO_DST and stop - body >= 12:
            destination = bytes(buf[body:body + 12])


def _data(buf: bytes | mmap.mmap, body: int, stop: int, order: str, kind: int, prefix: bytes,
          timestamp: int) -> ReceivedData | None:
    if kind == DATA_FRAG and struct.unpack_from(order + "I", buf, body + 20)[0] != 1:
        return None  # inline QoS travels with the first fragment only
    (to_inline_qos,) = struct.unpack_from(order + "H", buf, body + 2)
    related = _inline_related(buf, body + 4 + to_inline_qos, stop, order)
    if related is None:
        return None
    return ReceivedData(prefix + bytes(buf[body + 8:body + 12]),
                        _sequence_number(buf, body + 12, order), timestamp, related)


def _parameters_end(buf: bytes | mmap.mmap, offset: int, end: int, order: str) -> int | None:
    """Where the parameter list from `offset` ends (past its sentinel); None if it does not
    end before `end`."""
    while offset + 4 <= end:
        pid, length = struct.unpack_from(order + "HH", buf, offset)
        offset += 4
        if pid == PID_SENTINEL:  # exactly: a vendor's 0x8001 is just another parameter
            return offset
        if length % 4:  # malformed (DDSI 9.4.2.11): Cyclone drops the submessage
            return None
        offset += length
    return None


def _piece(buf: bytes | mmap.mmap, body: int, stop: int, order: str, kind: int, flags: int,
           prefix: bytes, timestamp: int | None) -> ReceivedPiece | None:
    """Where a DATA's or DATA_FRAG's serialized payload lies; None for a key, a DATA without
    data (a dispose), or a submessage shorter than it says."""
    frag = kind == DATA_FRAG
    if flags & FLAG_FRAG_KEY if frag else not flags & FLAG_DATA:
        return None
    if frag and stop - body < 32:
        return None
    (to_inline_qos,) = struct.unpack_from(order + "H", buf, body + 2)
    payload = body + 4 + to_inline_qos
    related = None
    if flags & FLAG_INLINE_QOS:
        related = _inline_related(buf, payload, stop, order)
        found = _parameters_end(buf, payload, stop, order)
        if found is None:
            return None
        payload = found
    if payload > stop:
        return None
    writer = prefix + bytes(buf[body + 8:body + 12])
    high, low = struct.unpack_from(order + "iI", buf, body + 12)
    seq = (high << 32) | low
    if not frag:  # malformed without room for the encapsulation header (Cyclone drops it)
        return None if stop - payload < 4 else \
            ReceivedPiece(writer, seq, related, payload, stop, 0, stop - payload,
                          source_timestamp=timestamp)
    first, count, size, sample_size = struct.unpack_from(order + "IHHI", buf, body + 20)
    if first < 1 or count < 1 or size < 1 or (first == 1 and stop - payload < 4):
        return None
    at = (first - 1) * size
    length = min(count * size, sample_size - at)
    if length <= 0 or payload + length > stop:
        return None
    return ReceivedPiece(writer, seq, related, payload, payload + length, at, sample_size,
                         size, first, count, timestamp)


class _Libc:
    """The two C library calls the capture needs, if this platform has them."""

    def __init__(self) -> None:
        name = ctypes.util.find_library("c")
        self._lib = ctypes.CDLL(name) if name else None
        self._punch = getattr(self._lib, "fallocate", None)
        if self._punch is not None:
            self._punch.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int64, ctypes.c_int64]

    def flush_all(self) -> None:
        """fflush(NULL): pushes out what Cyclone's capture FILE holds (ctypes drops the GIL)."""
        if self._lib is not None:
            self._lib.fflush(None)

    @property
    def can_punch(self) -> bool:
        return self._punch is not None

    def punch_hole(self, fd: int, offset: int, length: int) -> bool:
        """Frees a consumed range of the capture file (FALLOC_FL_PUNCH_HOLE|KEEP_SIZE);
        False if the file system (or platform) cannot."""
        return self._punch is not None and self._punch(fd, 0x02 | 0x01, offset, length) == 0


def capture_supported() -> bool:
    """Whether a capture stays bounded here: consumed bytes given back (fallocate) and
    Cyclone's descriptor found (/proc) to point it at /dev/null while nobody reads. Linux
    only: elsewhere (macOS) Cyclone would write all the domain's traffic to a file that
    only grows, so no capture is configured at all."""
    return sys.platform.startswith("linux") and os.path.isdir("/proc/self/fd") and \
        _Libc().can_punch


def capture_directory() -> str | None:
    """Where capture files go: $RCAN_RTPS_CAPTURE_DIR, else /dev/shm (tmpfs), else the
    system's temporary directory."""
    chosen = os.environ.get("RCAN_RTPS_CAPTURE_DIR")
    return chosen or ("/dev/shm" if os.path.isdir("/dev/shm") else None)


class IdentityCapture:
    """Tails a Cyclone packet capture and answers `lookup(writer_guid, source_timestamp)`.

    Make it before the domain (Cyclone opens the file when the domain starts), pass
    `config` to the domain, `start()` it once the domain exists, `close()` it after."""

    def __init__(self, directory: str | Path | None = None) -> None:
        self._dir = tempfile.mkdtemp(prefix="rcan-rtps-capture-",
                                     dir=directory or capture_directory())
        self.path = Path(self._dir) / "domain.pcap"
        self.config = capture_config(self.path)
        self._libc = _Libc()
        self._file: int | None = None
        self._offset = 0  # bytes of the file consumed (whole records only)
        self._punched = 0
        self._record_size = struct.Struct("<I")
        self._known: OrderedDict[tuple[bytes, int], SampleIdentity] = OrderedDict()
        # (writer, addressee) → file offset of the newest record with such a HEARTBEAT, and
        # the last sequence number that HEARTBEAT named
        self._heartbeats: OrderedDict[tuple[bytes, bytes], tuple[int, int]] = OrderedDict()
        # (our reader, writer) → file offset of the newest HEARTBEAT of that writer applied to
        # that reader that the reader then answered asking for nothing (`repair_owed`)
        self._answered: OrderedDict[tuple[bytes, bytes], int] = OrderedDict()
        self._replies = ReplyCollector()  # payloads of replies calls wait for (`expect_reply`)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._users = 0  # clients that need identities; with none, records are only skipped
        # Cyclone's descriptor of the capture, pointed at /dev/null while nobody needs
        # identities (writing ~all traffic to tmpfs is most of the cost) and back at the
        # file (opened for appending) when someone does: see `_route`.
        self._cyclone_fd: int | None = None
        self._sink: int | None = None
        self._appender: int | None = None
        self._resync_at: int | None = None  # file offset where writing resumed mid-stream
        self._broken = False  # given up (the file could not be kept bounded)
        self.datagrams = 0  # received datagrams parsed so far
        self.identified = 0  # DATA submessages found naming a related sample
        self.unparsed = 0  # received datagrams skipped: the parser failed on them

    @property
    def reading(self) -> bool:
        """Whether received datagrams are being read (started, not given up, a user)."""
        return self._file is not None and not self._broken and self._users > 0

    def lag(self) -> int:
        """Bytes Cyclone has written to the capture that are not read yet."""
        self._libc.flush_all()
        with self._lock:
            return 0 if self._file is None else os.fstat(self._file).st_size - self._offset

    def use(self) -> None:
        """A client needs identities from now on (until `unuse`)."""
        with self._lock:
            if self._broken:
                return
            self._users += 1
            if self._users == 1:
                self._route(True)

    def unuse(self) -> None:
        with self._lock:
            self._users = max(0, self._users - 1)
            if self._users == 0:
                self._route(False)

    def _route(self, to_file: bool) -> None:
        """Points Cyclone's capture descriptor at the file or at /dev/null (under the lock).

        Cyclone writes each record with buffered fwrite and never flushes, so a switch cuts
        its byte stream anywhere: the file may end in a partial record, and what is written
        after the switch may start in the middle of one. The drain therefore drops a record
        crossing the switch point and looks for the next record header after it (`_resync`).
        A client's request is written after `use()`, so the replies it waits for are whole."""
        if self._cyclone_fd is None or self._file is None:
            return
        if to_file:
            assert self._appender is not None
            self._resync_at = os.fstat(self._file).st_size
            os.dup2(self._appender, self._cyclone_fd)
        else:
            assert self._sink is not None
            self._libc.flush_all()  # what Cyclone buffered still goes to the file
            os.dup2(self._sink, self._cyclone_fd)

    def _find_cyclone_fd(self) -> int | None:
        """Cyclone's descriptor of the capture file (Linux: the only other descriptor of
        its inode; by inode, not by name, which a symlinked directory would change)."""
        assert self._file is not None
        ours = os.fstat(self._file)
        found = []
        with contextlib.suppress(OSError):
            for name in os.listdir("/proc/self/fd"):
                with contextlib.suppress(OSError, ValueError):
                    other = os.stat(f"/proc/self/fd/{name}")
                    if int(name) != self._file and \
                            (other.st_dev, other.st_ino) == (ours.st_dev, ours.st_ino):
                        found.append(int(name))
        return found[0] if len(found) == 1 else None

    def start(self) -> bool:
        """Opens the capture Cyclone has made, drops its name and drains it in the
        background. False (and nothing runs) if Cyclone has not made it."""
        try:
            self._file = os.open(self.path, os.O_RDWR)
        except FileNotFoundError:
            return False
        # Cyclone wrote the pcap header when it opened the file (fopen "wb"; buffered, hence
        # the flush): seeing it proves Cyclone holds this very inode open.
        self._libc.flush_all()
        little = PCAP_MAGICS.get(os.pread(self._file, 4, 0))
        if little is None:
            os.close(self._file)
            self._file = None
            return False
        self._record_size = struct.Struct("<I" if little else ">I")
        self._offset = PCAP_HEADER_SIZE
        self._cyclone_fd = self._find_cyclone_fd()  # by name: before the name goes
        if self._cyclone_fd is not None:
            self._appender = os.open(self.path, os.O_WRONLY | os.O_APPEND)
            self._sink = os.open(os.devnull, os.O_WRONLY)
            with self._lock:
                self._route(self._users > 0)
        # Both descriptors keep the inode: without a name, a killed process leaves nothing.
        self._remove_names()
        self._thread = threading.Thread(target=self._run, name="rtps-capture", daemon=True)
        self._thread.start()
        return True

    def _remove_names(self) -> None:
        with contextlib.suppress(OSError):
            self.path.unlink()
        with contextlib.suppress(OSError):
            os.rmdir(self._dir)

    def _run(self) -> None:
        while not self._stop.wait(DRAIN_PERIOD):
            self.drain()

    def drain(self) -> None:
        """Consumes the records the file holds now, a chunk per hold of the lock, so a
        `lookup` never waits for more than one chunk."""
        while True:
            with self._lock:
                if self._file is None or not self._consume(CHUNK):
                    return
            time.sleep(0)  # a waiting lookup gets the lock (and the GIL) between chunks

    def _consume(self, limit: int) -> int:
        """Steps over about `limit` bytes of whole records (parsing the received datagrams
        while a client needs identities), gives back what is consumed; bytes consumed."""
        assert self._file is not None
        size = os.fstat(self._file).st_size
        if size - self._offset < RECORD_HEADER_SIZE:
            return 0
        base = self._offset & ~(mmap.ALLOCATIONGRANULARITY - 1)
        with mmap.mmap(self._file, size - base, access=mmap.ACCESS_READ, offset=base) as buf:
            start = offset = self._offset - base
            available, stop = size - base, offset + limit
            parse, record_size = self._users > 0, self._record_size.unpack_from
            mark = None if self._resync_at is None else self._resync_at - base
            while offset < stop:
                if mark is not None and offset + RECORD_HEADER_SIZE > mark:
                    offset = self._resync(buf, max(offset, mark), available)
                    if self._resync_at is not None:
                        break  # no whole header after the switch yet
                    mark = None
                if offset + RECORD_HEADER_SIZE > available:
                    break
                (length,) = record_size(buf, offset + 8)
                end = offset + RECORD_HEADER_SIZE + length
                if mark is not None and end > mark:
                    offset = mark  # its tail went to /dev/null
                    continue
                if end > available:
                    break  # Cyclone has not written all of it yet
                packet = offset + RECORD_HEADER_SIZE
                if parse and length > IP_UDP_SIZE:
                    if buf[packet + TTL_OFFSET] == RECEIVED_TTL:
                        self._parse_or_skip(buf, packet + IP_UDP_SIZE, end, base + offset)
                    else:
                        self._note_acknacks(buf, packet + IP_UDP_SIZE, end, base + offset)
                offset = end
        self._offset = base + offset
        if self._offset - self._punched >= PUNCH_AFTER:
            # Page-aligned, below what was consumed: the hole never touches unread bytes.
            punch_to = self._offset & ~0xFFF
            if not self._libc.punch_hole(self._file, self._punched, punch_to - self._punched):
                self._give_up("the capture's file system cannot give consumed bytes back")
                return offset - start
            self._punched = punch_to
        return offset - start

    def _give_up(self, why: str) -> None:
        """Stops capturing for good (under the lock): Cyclone's descriptor to /dev/null,
        lookups answer unknown, so clients keep the rule for unnamed replies."""
        log.warning("Fast DDS request identities off: %s", why)
        self._users = 0
        if self._cyclone_fd is not None:
            self._route(False)
        else:
            log.error("the packet capture cannot be stopped and will grow: set "
                      "RCAN_RTPS_RPC_IDENTITY=off")
        self._known.clear()
        self._heartbeats.clear()
        self._answered.clear()
        self._replies = ReplyCollector()
        self._broken = True

    def _resync(self, buf: mmap.mmap, offset: int, available: int) -> int:
        """The first record header at or after `offset` (clearing the switch mark), or
        where to look again once more is written. A header is recognised by Cyclone's
        made-up IPv4 header: version/IHL 0x45, TOS 0, total length = captured length =
        original length, protocol UDP."""
        while True:
            found = buf.find(b"\x45\x00", offset + RECORD_HEADER_SIZE, available)
            if found < 0:
                return max(offset, available - RECORD_HEADER_SIZE - 1)
            start = found - RECORD_HEADER_SIZE
            if found + IP_UDP_SIZE > available:
                return start
            captured, original = struct.unpack_from(self._record_size.format[0] + "II",
                                                    buf, start + 8)
            (total,) = struct.unpack_from(">H", buf, found + 2)
            if captured == original == total > IP_UDP_SIZE and buf[found + 9] == 17:
                self._resync_at = None
                return start
            offset = start + 1

    def _parse_or_skip(self, buf: mmap.mmap, start: int, end: int, at: int) -> None:
        """`_parse`, skipping a datagram it fails on: a datagram from the wire must not stop
        the drain thread, raise out of a lookup, or stay unconsumed to fail every drain."""
        try:
            self._parse(buf, start, end, at)
        except Exception as exc:  # bad input (or a parser bug): said once, counted
            self.unparsed += 1
            if self.unparsed == 1:
                log.warning("packet capture: a received datagram could not be read, skipped "
                            "(%s: %s); later ones are only counted", type(exc).__name__, exc)

    def _parse(self, buf: mmap.mmap, start: int, end: int, at: int) -> None:
        self.datagrams += 1
        for data in parse_rtps(buf, start, end, self._replies.writers):
            if isinstance(data, ReceivedPiece):
                self._replies.piece(data, buf)
                continue
            if isinstance(data, ReceivedHeartbeat):
                pair = (data.writer_guid, data.reader_guid)
                self._heartbeats[pair] = (at, data.last_sn)
                self._heartbeats.move_to_end(pair)
                if len(self._heartbeats) > KEPT_HEARTBEATS:
                    self._heartbeats.popitem(last=False)
                continue
            self.identified += 1
            key = (data.writer_guid, data.source_timestamp)
            self._known[key] = data.related
            self._known.move_to_end(key)
            if len(self._known) > KEPT_IDENTITIES:
                self._known.popitem(last=False)

    def _note_acknacks(self, buf: mmap.mmap, start: int, end: int, at: int) -> None:
        """Notes, for each ACKNACK of a datagram we sent that takes everything the newest
        HEARTBEAT applied to its reader named (it asks for nothing, and its base is past that
        HEARTBEAT's last sequence number), that HEARTBEAT's place. One that asks for nothing
        with its base not past it answers nothing: Cyclone sends such an ACKNACK when it holds
        back a NACK it sent less than NackDelay ago (the sample still missing: ddsi_acknack.c,
        `AANR_SUPPRESSED_NACK`), and one built before the HEARTBEAT was applied can be captured
        after it. (Our own datagram: never malformed; a failure is skipped all the same, as
        for received ones.)"""
        try:
            for sent in parse_acknacks(buf, start, end):
                heard_at, last = self._heard_at(sent.writer_guid, sent.reader_guid)
                if sent.missing or heard_at < 0 or sent.base <= last:
                    continue
                pair = (sent.reader_guid, sent.writer_guid)
                self._answered[pair] = heard_at
                self._answered.move_to_end(pair)
                if len(self._answered) > KEPT_ACKNACKS:
                    self._answered.popitem(last=False)
        except Exception:  # (a parser bug): the question it answers stays "owed"
            self.unparsed += 1

    def _heard_at(self, writer_guid: bytes, reader_guid: bytes) -> tuple[int, int]:
        """Where the newest HEARTBEAT of `writer_guid` addressed so that Cyclone applies it
        to `reader_guid` is in the capture, and the last sequence number it named
        (NOT_HEARD: none heard)."""
        entity, ours = reader_guid[12:], reader_guid[:12]
        return max(self._heartbeats.get((writer_guid, r), NOT_HEARD)
                   for r in (reader_guid, UNKNOWN_PREFIX + entity, ours + ENTITYID_UNKNOWN,
                             UNKNOWN_PREFIX + ENTITYID_UNKNOWN))

    def held(self) -> int:
        """Bytes of the capture file in memory now (tmpfs pages not yet given back)."""
        with self._lock:
            return 0 if self._file is None else os.fstat(self._file).st_blocks * 512

    def lookup(self, writer_guid: bytes, source_timestamp: int) -> SampleIdentity | None:
        """The related identity of the sample `writer_guid` wrote at `source_timestamp`, or
        None: unknown (the sample named none, or its datagram is not in the capture: not
        UDPv4, protected, the capture is off or further behind than MISS_BUDGET).

        Call it after the sample was taken: its datagram is then in the capture or in the
        capture's C buffer, which a miss flushes before reading the file up to its end
        (in chunks, so the drain thread never holds it up for more than one)."""
        key = (writer_guid, source_timestamp)
        return self._find(lambda: self._known.get(key))

    def expect_reply(self, identity: SampleIdentity, writers: Collection[bytes]) -> bool:
        """Keeps, from now on, the payload of a received sample of one of `writers` whose
        related sample identity is `identity` (a DATA, or DATA_FRAGs put together; bounded:
        captured_replies.py), for `captured_reply`, until `forget_reply`. Call it before the
        request goes out: its reply is then in the part of the capture not read yet. False
        (nothing kept) while the capture is not reading."""
        with self._lock:
            if not self.reading or not writers:
                return False
            self._replies.expect(identity, writers)
            return True

    def captured_reply(self, identity: SampleIdentity) -> bytes | None:
        """The serialized payload (encapsulation header and body) of the expected reply
        naming `identity`, once its datagram has reached our socket — delivered to our reader
        or not. A miss flushes and reads the capture to its end first, as `lookup` does."""
        return self._find(lambda: self._replies.take(identity))

    def forget_reply(self, identity: SampleIdentity) -> None:
        with self._lock:
            self._replies.forget(identity)

    def expect_feedback(self, goal_id: bytes, writers: Collection[bytes]) -> bool:
        """Keeps, from now on, the feedback samples of goal `goal_id` that one of `writers`
        sends (captured_replies.py), for `feedback_before` and `captured_feedback`, until
        `forget_feedback`. Call it before the goal goes out. False (nothing kept) while the
        capture is not reading."""
        with self._lock:
            if not self.reading or not writers:
                return False
            self._replies.expect_feedback(goal_id, writers)
            return True

    def feedback_before(self, goal_id: bytes, writer_guid: bytes,
                        source_timestamp: int) -> list[CapturedSample] | None:
        """The goal's kept feedback samples of `writer_guid` that it sent before the one it
        wrote at `source_timestamp` (which a reader delivered: its datagram is in the capture
        or its C buffer, so a miss flushes and reads to the end first, as `lookup` does);
        None if that one is not in the capture (then nothing can be put before it)."""
        def earlier() -> list[CapturedSample] | None:
            kept = [s for s in self._replies.feedback(goal_id) if s.writer_guid == writer_guid]
            at = min((s.seq for s in kept if s.source_timestamp == source_timestamp),
                     default=None)
            return None if at is None else [s for s in kept if s.seq < at]
        return self._find(earlier)

    def captured_feedback(self, goal_id: bytes) -> list[CapturedSample]:
        """The goal's feedback samples that have reached our socket, delivered to our reader
        or not, once the capture is read to its end (after a flush, as by a `lookup` that
        missed)."""
        self._find(lambda: None)  # (nothing short of the end will do)
        with self._lock:
            return self._replies.feedback(goal_id)

    def forget_feedback(self, goal_id: bytes) -> None:
        with self._lock:
            self._replies.forget_feedback(goal_id)

    def mark(self) -> int:
        """Where the capture is now: a datagram received after this call is at or after it
        (see `heard_heartbeat`)."""
        self._libc.flush_all()
        with self._lock:
            return 0 if self._file is None else os.fstat(self._file).st_size

    def heard_heartbeat(self, writer_guid: bytes, reader_guid: bytes, since: int) -> bool:
        """Whether a HEARTBEAT of `writer_guid` that Cyclone applies to the reader
        `reader_guid` has reached our socket while a client needed identities (`use`):
        one addressed to that reader, or one addressed to all readers (of our participant, or
        of whoever received it) at or after `since`: a `mark` taken once the reader was made
        (and matched: Cyclone matches a new reader with the writers it knows as it makes it).
        Cyclone writes a datagram here before it processes it, so one after the mark was
        processed after the reader was there; one before it may have been processed before,
        and not applied to the reader (it then costs the caller a wait, never a false "heard").
        The file is first flushed and read up to its end, as by a `lookup` that missed."""
        entity, ours = reader_guid[12:], reader_guid[:12]
        pairs = ((writer_guid, reader_guid, 0), (writer_guid, UNKNOWN_PREFIX + entity, 0),
                 (writer_guid, ours + ENTITYID_UNKNOWN, since),
                 (writer_guid, UNKNOWN_PREFIX + ENTITYID_UNKNOWN, since))

        def heard() -> bool | None:
            return True if any(self._heartbeats.get((w, r), NOT_HEARD)[0] >= at
                               for w, r, at in pairs) \
                else None
        return self._find(heard) is True

    def repair_owed(self, writer_guid: bytes, reader_guid: bytes, since: int) -> bool:
        """Whether our reader `reader_guid` may still be owed a sample `writer_guid` wrote
        before `since` (a `mark`): True until a HEARTBEAT of that writer applied to that
        reader has reached our socket at or after `since`, and an ACKNACK the reader sent
        after it takes all that HEARTBEAT named (asks for nothing, its base past the
        HEARTBEAT's last sequence number: `_note_acknacks`). A reader answers every HEARTBEAT
        that asks for an answer (as Fast DDS's and Cyclone's periodic ones do) and NACKs what
        it misses of what the HEARTBEAT says was written; once one heard after `since` was
        answered so, what was written before `since` was taken, and later HEARTBEATs change
        nothing. So a sample written before `since` and dropped at our
        socket keeps this True until the writer has sent it again and the reader took it.
        Only while a client uses the capture (`use`); the file is first flushed and read up
        to its end, as by a `lookup` that missed."""
        def settled() -> bool | None:
            return True if self._answered.get((reader_guid, writer_guid), -1) >= since \
                else None
        return self._find(settled) is None

    def _find(self, found: Callable[[], T | None]) -> T | None:
        """`found()` (called under the lock), else again while the file is read up to the
        end it has after a flush (at most MISS_BUDGET bytes, a chunk per hold of the lock)."""
        with self._lock:
            answer = found()
            if answer is not None:
                return answer
        self._libc.flush_all()
        with self._lock:
            if self._file is None:
                return None
            target = os.fstat(self._file).st_size
        budget = MISS_BUDGET
        while budget > 0:
            with self._lock:
                answer = found()
                if answer is not None or self._file is None or self._offset >= target:
                    return answer
                used = self._consume(min(CHUNK, budget))
            if not used:
                break
            budget -= used
        with self._lock:
            return found()

    def close(self) -> None:
        """Stops the drain and closes the capture (removing its name if it still has one)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        with self._lock:
            # Cyclone's descriptor is left on /dev/null, and never touched again: once the
            # domain is gone its number may be anyone's.
            if self._users:
                self._route(False)
            self._cyclone_fd = None
            for fd in (self._file, self._appender, self._sink):
                if fd is not None:
                    os.close(fd)
            self._file = self._appender = self._sink = None
        self._remove_names()
