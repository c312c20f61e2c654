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
a pipe could fill and block a DDS write that holds the GIL), parses the received DATA and
DATA_FRAG submessages that carry a related sample identity, and keeps
`(writer GUID, source timestamp) -> related identity`. A reader takes a sample, then asks
`lookup(writer_guid, source_timestamp)`. The consumed part of the file is given back to the
system (a hole punched in the tmpfs file), so memory stays bounded by what arrived since
the last drain. Limits: UDPv4 only (Cyclone's capture is), and nothing under DDS-Security
payload or submessage protection can be read.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import struct
import tempfile
import threading
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

PID_SENTINEL = 0x0001
PID_PAD = 0x0000
PID_RELATED_SAMPLE_IDENTITY = 0x0083  # OMG DDS-RPC
PID_FASTDDS_RELATED_SAMPLE_IDENTITY = 0x800F  # Fast DDS' older vendor-specific id
RELATED_PIDS = (PID_RELATED_SAMPLE_IDENTITY, PID_FASTDDS_RELATED_SAMPLE_IDENTITY)

INFO_TS, INFO_SRC, DATA, DATA_FRAG = 0x09, 0x0C, 0x15, 0x16
FLAG_LITTLE, FLAG_INLINE_QOS, FLAG_INVALIDATE = 0x01, 0x02, 0x02
RTPS_HEADER_SIZE = 20
IP_UDP_SIZE = 28  # Cyclone's capture writes a made-up IPv4 + UDP header before each datagram
RECEIVED_TTL = 128  # ... with TTL 128 on received datagrams, 255 on sent ones
PCAP_HEADER_SIZE, RECORD_HEADER_SIZE = 24, 16

KEPT_IDENTITIES = 65536  # newest samples remembered; far more than a reader keeps
DRAIN_PERIOD = 0.05  # s between background drains of the capture file
PUNCH_AFTER = 1 << 20  # bytes consumed before they are given back


@dataclass(frozen=True)
class SampleIdentity:
    """A DDS sample's identity: its writer's GUID (16 bytes) and its sequence number."""

    writer_guid: bytes
    seq: int


@dataclass(frozen=True)
class ReceivedData:
    """What one received DATA (or first DATA_FRAG) submessage says about its sample."""

    writer_guid: bytes
    seq: int
    source_timestamp: int | None  # ns since the epoch, converted as Cyclone does
    related: SampleIdentity | None


def capture_config(path: str | Path) -> str:
    """The Cyclone configuration fragment that captures the domain's traffic into `path`."""
    return ("<CycloneDDS><Domain Id=\"any\"><Tracing><PacketCaptureFile>"
            f"{path}</PacketCaptureFile></Tracing></Domain></CycloneDDS>")


def nanoseconds(seconds: int, fraction: int) -> int:
    """An RTPS Time_t as Cyclone 11 converts it (rounding the 2^-32 s fraction to nearest)."""
    return seconds * 1_000_000_000 + ((1 << 31) + fraction * 1_000_000_000 >> 32)


def _related(value: memoryview, order: str) -> SampleIdentity | None:
    if len(value) < 24:
        return None
    high, low = struct.unpack_from(order + "iI", value, 16)
    return SampleIdentity(bytes(value[:16]), (high << 32) | low)


def _inline_related(body: memoryview, start: int, order: str) -> SampleIdentity | None:
    """The related sample identity in a parameter list starting at `start`, if any."""
    offset = start
    while offset + 4 <= len(body):
        pid, length = struct.unpack_from(order + "HH", body, offset)
        offset += 4
        pid &= 0x3FFF if pid & 0x8000 == 0 else 0xFFFF  # drop the must-understand bit
        if pid == PID_SENTINEL:
            return None
        if pid in RELATED_PIDS:
            return _related(body[offset:offset + length], order)
        offset += length
    return None


def parse_rtps(message: memoryview) -> Iterator[ReceivedData]:
    """The DATA and first DATA_FRAG submessages of one RTPS message, in order."""
    if len(message) < RTPS_HEADER_SIZE or bytes(message[:4]) != b"RTPS":
        return
    prefix = bytes(message[8:20])
    timestamp: int | None = None
    offset = RTPS_HEADER_SIZE
    while offset + 4 <= len(message):
        kind, flags = message[offset], message[offset + 1]
        order = "<" if flags & FLAG_LITTLE else ">"
        (length,) = struct.unpack_from(order + "H", message, offset + 2)
        start = offset + 4
        end = len(message) if length == 0 and kind not in (INFO_TS, 0x01) else start + length
        body = message[start:end]
        if kind == INFO_TS:
            timestamp = None if flags & FLAG_INVALIDATE or len(body) < 8 else \
                nanoseconds(*struct.unpack_from(order + "iI", body, 0))
        elif kind == INFO_SRC and len(body) >= 20:
            prefix = bytes(body[8:20])
        elif kind in (DATA, DATA_FRAG) and len(body) >= 20:
            found = _data(body, flags, order, kind, prefix, timestamp)
            if found is not None:
                yield found
        offset = end


def _data(body: memoryview, flags: int, order: str, kind: int, prefix: bytes,
          timestamp: int | None) -> ReceivedData | None:
    to_inline_qos, = struct.unpack_from(order + "H", body, 2)
    high, low = struct.unpack_from(order + "iI", body, 12)
    if kind == DATA_FRAG and struct.unpack_from(order + "I", body, 20)[0] != 1:
        return None  # inline QoS travels with the first fragment only
    related = _inline_related(body, 4 + to_inline_qos, order) \
        if flags & FLAG_INLINE_QOS else None
    return ReceivedData(prefix + bytes(body[8:12]), (high << 32) | low, timestamp, related)


def parse_records(buffer: bytes, little: bool) -> tuple[list[memoryview], int]:
    """The received datagrams among the whole pcap records at the front of `buffer`, and
    how many bytes those records take (a partial record stays for the next read)."""
    order = "<" if little else ">"
    offset, found = 0, []
    view = memoryview(buffer)
    while offset + RECORD_HEADER_SIZE <= len(buffer):
        (size,) = struct.unpack_from(order + "I", buffer, offset + 8)
        end = offset + RECORD_HEADER_SIZE + size
        if end > len(buffer):
            break
        packet = view[offset + RECORD_HEADER_SIZE:end]
        if size > IP_UDP_SIZE and packet[8] == RECEIVED_TTL:
            found.append(packet[IP_UDP_SIZE:])
        offset = end
    return found, offset


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

    def punch_hole(self, fd: int, offset: int, length: int) -> None:
        """Frees a consumed range of the capture file (FALLOC_FL_PUNCH_HOLE|KEEP_SIZE)."""
        if self._punch is not None:
            self._punch(fd, 0x02 | 0x01, offset, length)


class IdentityCapture:
    """Tails a Cyclone packet capture and answers `lookup(writer_guid, source_timestamp)`.

    Make it before the domain (Cyclone opens the file when the domain starts), pass
    `config` to the domain, `start()` it once the domain exists, `close()` it after."""

    def __init__(self, directory: str | Path | None = None) -> None:
        base = directory or ("/dev/shm" if os.path.isdir("/dev/shm") else None)
        self._dir = tempfile.mkdtemp(prefix="rcan-rtps-capture-", dir=base)
        self.path = Path(self._dir) / "domain.pcap"
        self.config = capture_config(self.path)
        self._libc = _Libc()
        self._file: int | None = None
        self._offset = 0  # bytes of the file consumed
        self._punched = 0
        self._pending = bytearray()
        self._little: bool | None = None
        self._known: OrderedDict[tuple[bytes, int], SampleIdentity | None] = OrderedDict()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._users = 0  # clients that need identities; with none, records are only skipped
        self.datagrams = 0  # received datagrams parsed so far
        self.data_submessages = 0

    def use(self) -> None:
        """A client needs identities from now on (until `unuse`)."""
        with self._lock:
            self._users += 1

    def unuse(self) -> None:
        with self._lock:
            self._users = max(0, self._users - 1)

    def start(self) -> None:
        """Opens the capture (Cyclone must have created it) and drains it in the background."""
        # Created if Cyclone has not opened it yet; its fopen("wb") then keeps this inode.
        self._file = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        self._thread = threading.Thread(target=self._run, name="rtps-capture", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(DRAIN_PERIOD):
            self.drain()

    def drain(self) -> None:
        """Reads and parses everything the file holds now."""
        with self._lock:
            if self._file is None:
                return
            while chunk := os.pread(self._file, 1 << 20, self._offset):
                self._offset += len(chunk)
                self._pending += chunk
            self._parse()
            if self._offset - self._punched >= PUNCH_AFTER:
                # Page-aligned, below what was consumed: the hole never touches unread bytes.
                end = self._offset & ~0xFFF
                with contextlib.suppress(OSError):
                    self._libc.punch_hole(self._file, self._punched, end - self._punched)
                self._punched = end

    def _parse(self) -> None:
        if self._little is None:
            if len(self._pending) < PCAP_HEADER_SIZE:
                return
            self._little = self._pending[:4] == b"\xd4\xc3\xb2\xa1"
            del self._pending[:PCAP_HEADER_SIZE]
        # Parsed from an immutable copy: views into the bytearray would pin its size.
        datagrams, used = parse_records(bytes(self._pending), self._little)
        for datagram in datagrams if self._users else ():
            self.datagrams += 1
            for data in parse_rtps(datagram):
                self.data_submessages += 1
                if data.source_timestamp is not None:
                    self._remember((data.writer_guid, data.source_timestamp), data.related)
        del self._pending[:used]

    def _remember(self, key: tuple[bytes, int], related: SampleIdentity | None) -> None:
        self._known[key] = related
        self._known.move_to_end(key)
        while len(self._known) > KEPT_IDENTITIES:
            self._known.popitem(last=False)

    def lookup(self, writer_guid: bytes,
               source_timestamp: int) -> tuple[bool, SampleIdentity | None]:
        """(seen, related identity) of the sample `writer_guid` wrote at `source_timestamp`.
        Call it after the sample was taken: its datagram is then in the capture or in the
        capture's C buffer, which this flushes. `seen` is False only if the datagram is not
        in the capture at all (not UDPv4, protected, or the capture is off)."""
        key = (writer_guid, source_timestamp)
        for attempt in range(2):
            with self._lock:
                if key in self._known:
                    return True, self._known[key]
            if attempt == 0:
                self._libc.flush_all()
                self.drain()
        return False, None

    def close(self) -> None:
        """Stops the drain and removes the capture file (Cyclone may still hold it open)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        with self._lock:
            if self._file is not None:
                os.close(self._file)
                self._file = None
        with contextlib.suppress(OSError):
            self.path.unlink()
        with contextlib.suppress(OSError):
            os.rmdir(self._dir)
