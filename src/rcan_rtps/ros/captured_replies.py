"""Replies and first feedback kept from the packet capture for the calls and goals that wait
for them.

A Fast DDS server's reply can reach our socket and still never reach our reader: when
Cyclone took the HEARTBEAT ahead of it as the reader's start, it drops the reply as history
and ACKs it (docs/design/zero-loss.md), and nothing sends it again. The datagram is in our
packet capture all the same (rtps_capture.py). `ReplyCollector` keeps the serialized payload
of such a reply — a DATA, or the DATA_FRAG pieces of one, put together — for the calls that
said they wait for it (`expect`: the request's identity and the reply writers matched with
the caller's reader), so that a call whose reader never delivered can take it (`take`).

Only what was asked for is kept, and bounded: a payload only for an expected identity (the
related sample identity must name our request exactly) from one of the writers given with it;
fragments only of those writers, at most HELD_BUDGET bytes in all (pieces of a sample whose
first fragment has not come yet are let go of first; an assembly counted with its bookkeeping),
at most MAX_ASSEMBLIES samples put together at once, no sample over MAX_SAMPLE bytes, at most
MAX_EXPECTED identities. Methods are called under the capture's lock.

An action goal's first feedback is exposed the same way (a Fast DDS feedback writer's
HEARTBEAT ahead of it taken as a fresh reader's start), so the collector also keeps, for a
goal that said it waits (`expect_feedback`: its goal id and the feedback writers matched with
the client's reader), the feedback samples of those writers whose goal_id field (the first
16 bytes of the plain-CDR body) is that goal id: at most FEEDBACK_KEPT a goal, each with its
writer, sequence number and source timestamp (`CapturedSample`), so that the client can tell
which ones came before the first its reader delivered. Same budget, same fragment rules.
"""

from __future__ import annotations

import logging
from collections import Counter, OrderedDict
from collections.abc import Collection
from typing import TYPE_CHECKING

import msgspec

if TYPE_CHECKING:
    from mmap import mmap

    from .rtps_capture import ReceivedPiece, SampleIdentity

log = logging.getLogger(__name__)

MAX_EXPECTED = 1024  # identities waited for at once (one per Fast DDS call in flight)
MAX_SAMPLE = 16 << 20  # bytes: a bigger reply is not put together (its reader's own path only)
HELD_BUDGET = 32 << 20  # bytes of payloads and fragments held at most
SETTLED_KEPT = 1024  # (writer, seq) of fragmented samples not to put together (again)
MAX_ASSEMBLIES = 64  # samples put together at once (one per call in flight, and others' replies)
# bytes an assembly is counted for beyond its sample and its one byte a fragment: its objects
# (a flood of tiny samples must not cost more than the budget counts)
ASSEMBLY_OVERHEAD = 512
# feedback samples kept a goal: those before the first one its reader delivers are looked for
# among them (Cyclone drops as history only what came before the reader's first HEARTBEAT)
FEEDBACK_KEPT = 32
PLAIN_CDR = (b"\x00\x00", b"\x00\x01")  # encapsulations whose body the goal id begins
GOAL_ID_END = 20  # the goal id: bytes 4..20 of the payload (after the encapsulation header)


class CapturedSample(msgspec.Struct, frozen=True):
    """A feedback sample kept from the capture: its writer, sequence number, source
    timestamp (ns, as Cyclone converts it; None if its message had none) and serialized
    payload (encapsulation header and body)."""

    writer_guid: bytes
    seq: int
    source_timestamp: int | None
    payload: bytes


def goal_named(piece: ReceivedPiece, buf: bytes | mmap) -> bytes | None:
    """The goal id a feedback sample's payload begins with, if this piece holds its start
    (a DATA, or the first fragment) in plain CDR."""
    if piece.at != 0 or piece.end - piece.start < GOAL_ID_END or \
            bytes(buf[piece.start:piece.start + 2]) not in PLAIN_CDR:
        return None
    return bytes(buf[piece.start + 4:piece.start + GOAL_ID_END])


class _Assembly:
    """The fragments of one sample received so far."""

    def __init__(self, sample_size: int, fragment_size: int) -> None:
        self.data = bytearray(sample_size)
        self.fragment_size = fragment_size
        # one byte a fragment, 1 once received: bounded by the sample (a set of fragment
        # numbers cost some 60 bytes each: 1-byte fragments made it 60 times the sample)
        self.received = bytearray(-(-sample_size // fragment_size))
        self.missing = len(self.received)
        # whom it is for: the related identity of a reply, the goal id of a feedback sample
        self.related: SampleIdentity | bytes | None = None
        self.source_timestamp: int | None = None

    @property
    def cost(self) -> int:
        """Bytes it is counted for in the budget."""
        return self.cost_of(len(self.data), self.fragment_size)

    @staticmethod
    def cost_of(sample_size: int, fragment_size: int) -> int:
        return sample_size + -(-sample_size // fragment_size) + ASSEMBLY_OVERHEAD

    def add(self, piece: ReceivedPiece, buf: bytes | mmap) -> None:
        self.data[piece.at:piece.at + piece.end - piece.start] = buf[piece.start:piece.end]
        first = piece.first_fragment - 1
        last = min(first + piece.fragments, len(self.received))
        self.missing -= self.received.count(0, first, last)
        self.received[first:last] = b"\x01" * (last - first)

    @property
    def complete(self) -> bool:
        return self.missing == 0


class ReplyCollector:
    """Payloads of expected replies, found in received datagrams (see the module doc)."""

    def __init__(self) -> None:
        self._expected: OrderedDict[SampleIdentity, frozenset[bytes]] = OrderedDict()
        self._writers: Counter[bytes] = Counter()  # writers of the expected, with multiplicity
        self._found: dict[SampleIdentity, bytes] = {}
        self._assemblies: OrderedDict[tuple[bytes, int], _Assembly] = OrderedDict()
        # another's (or another request's) reply, or ours already put together
        self._settled: OrderedDict[tuple[bytes, int], None] = OrderedDict()
        self._held = 0  # bytes in _found, _feedback_found and _assemblies
        self._feedback_expected: OrderedDict[bytes, frozenset[bytes]] = OrderedDict()
        self._feedback_writers: Counter[bytes] = Counter()
        self._feedback_found: dict[bytes, list[CapturedSample]] = {}

    @property
    def writers(self) -> Collection[bytes]:
        """The writers whose DATA and DATA_FRAG the capture must show (`piece`): reply and
        feedback writers both (counted in one table: this is asked once a datagram)."""
        return self._writers.keys()

    @property
    def held(self) -> int:
        return self._held

    def expect(self, identity: SampleIdentity, writers: Collection[bytes]) -> None:
        """Keeps the payload of a sample naming `identity` that one of `writers` sends."""
        self.forget(identity)
        if len(self._expected) >= MAX_EXPECTED:
            self.forget(next(iter(self._expected)))
        chosen = frozenset(bytes(w) for w in writers)
        self._expected[identity] = chosen
        self._writers.update(chosen)

    def forget(self, identity: SampleIdentity) -> None:
        """No longer waited for: whatever was kept for it goes."""
        writers = self._expected.pop(identity, None)
        if writers is None:
            return
        found = self._found.pop(identity, None)
        if found is not None:
            self._held -= len(found)
        self._forgotten(writers, identity)

    def _forgotten(self, writers: frozenset[bytes], named: SampleIdentity | bytes) -> None:
        self._writers.subtract(writers)
        self._writers += Counter()  # drops the writers no longer counted
        for key, assembly in list(self._assemblies.items()):
            if assembly.related == named:
                self._drop(key)
        if not self._expected and not self._feedback_expected:  # nothing waited for
            for key in list(self._assemblies):
                self._drop(key)
            self._settled.clear()

    def expect_feedback(self, goal_id: bytes, writers: Collection[bytes]) -> None:
        """Keeps the feedback samples of goal `goal_id` that one of `writers` sends."""
        self.forget_feedback(goal_id)
        if len(self._feedback_expected) >= MAX_EXPECTED:
            self.forget_feedback(next(iter(self._feedback_expected)))
        chosen = frozenset(bytes(w) for w in writers)
        self._feedback_expected[bytes(goal_id)] = chosen
        self._feedback_found[bytes(goal_id)] = []
        self._writers.update(chosen)
        self._feedback_writers.update(chosen)

    def forget_feedback(self, goal_id: bytes) -> None:
        """The goal's feedback is no longer looked for: what was kept of it goes."""
        writers = self._feedback_expected.pop(goal_id, None)
        if writers is None:
            return
        for sample in self._feedback_found.pop(goal_id, []):
            self._held -= len(sample.payload)
        self._feedback_writers.subtract(writers)
        self._feedback_writers += Counter()
        self._forgotten(writers, goal_id)

    def feedback(self, goal_id: bytes) -> list[CapturedSample]:
        """The goal's feedback samples kept so far, in the order they were received."""
        return list(self._feedback_found.get(goal_id, ()))

    def take(self, identity: SampleIdentity) -> bytes | None:
        """The payload (encapsulation header and body) of the reply naming `identity`, if
        it has come; it is kept until `forget`."""
        return self._found.get(identity)

    def piece(self, piece: ReceivedPiece, buf: bytes | mmap) -> None:
        """A DATA or DATA_FRAG of one of `writers`, where its payload lies in `buf`."""
        # A feedback writer's sample names its goal in its payload; a reply its request in
        # the inline QoS.
        named = goal_named(piece, buf) if piece.writer_guid in self._feedback_writers \
            else piece.related
        if piece.fragment_size == 0:
            if named is not None and self._wanted(named, piece.writer_guid):
                self._keep(named, piece.writer_guid, piece.seq, piece.source_timestamp,
                           bytes(buf[piece.start:piece.end]))
            return
        key = (piece.writer_guid, piece.seq)
        if key in self._settled or piece.sample_size > MAX_SAMPLE:
            return
        if named is not None and not self._wanted(named, piece.writer_guid):
            self._settle(key)  # another's (or another request's) reply, another goal's feedback
            return
        assembly = self._assembly(key, piece)
        if assembly is None:
            return
        if named is not None:
            assembly.related = named
        if assembly.source_timestamp is None:
            assembly.source_timestamp = piece.source_timestamp
        assembly.add(piece, buf)
        if assembly.complete:  # (without a related identity: nobody's, let go of)
            data, related = bytes(assembly.data), assembly.related
            self._settle(key)  # a fragment sent again later starts nothing
            if related is not None:
                self._keep(related, piece.writer_guid, piece.seq, assembly.source_timestamp,
                           data)

    def _settle(self, key: tuple[bytes, int]) -> None:
        """No piece of this sample is kept from now on."""
        self._settled[key] = None
        if len(self._settled) > SETTLED_KEPT:
            self._settled.popitem(last=False)
        self._drop(key)

    def _wanted(self, named: SampleIdentity | bytes, writer: bytes) -> bool:
        if isinstance(named, bytes):  # a goal id
            writers = self._feedback_expected.get(named)
            return writers is not None and writer in writers and \
                len(self._feedback_found[named]) < FEEDBACK_KEPT
        writers = self._expected.get(named)
        return writers is not None and writer in writers and named not in self._found

    def _keep(self, named: SampleIdentity | bytes, writer: bytes, seq: int,
              source_timestamp: int | None, data: bytes) -> None:
        if isinstance(named, bytes):
            kept = self._feedback_found[named]
            # a repair of one kept is the same sample
            if any(s.writer_guid == writer and s.seq == seq for s in kept) or \
                    not self._room(len(data)):
                return
            kept.append(CapturedSample(writer, seq, source_timestamp, data))
        else:
            if named in self._found or not self._room(len(data)):
                return
            self._found[named] = data  # the first wins: a repair of it is the same sample
        self._held += len(data)

    def _assembly(self, key: tuple[bytes, int], piece: ReceivedPiece) -> _Assembly | None:
        """The sample's assembly, made if there is room; None if the piece does not fit it
        (another fragment size or sample size: a malformed stream)."""
        assembly = self._assemblies.get(key)
        if assembly is None:
            if len(self._assemblies) >= MAX_ASSEMBLIES:
                self._drop(self._oldest())
            # Room first: a sample that cannot be held is never allocated (nor zeroed).
            cost = _Assembly.cost_of(piece.sample_size, piece.fragment_size)
            if not self._room(cost):
                return None
            assembly = self._assemblies[key] = _Assembly(piece.sample_size, piece.fragment_size)
            self._held += cost
        if assembly.fragment_size != piece.fragment_size or \
                len(assembly.data) != piece.sample_size:
            self._drop(key)
            return None
        return assembly

    def _room(self, size: int) -> bool:
        """Whether `size` more bytes fit HELD_BUDGET, after letting go of the oldest
        assemblies whose first fragment (naming whom they are for) has not come."""
        for key in [k for k, a in self._assemblies.items() if a.related is None]:
            if self._held + size <= HELD_BUDGET:
                break
            self._drop(key)
        if self._held + size > HELD_BUDGET:
            log.debug("captured replies: %d bytes more would exceed the budget", size)
            return False
        return True

    def _oldest(self) -> tuple[bytes, int]:
        """The assembly to let go of first: the oldest whose first fragment has not come,
        else the oldest."""
        unlinked = (k for k, a in self._assemblies.items() if a.related is None)
        return next(unlinked, next(iter(self._assemblies)))

    def _drop(self, key: tuple[bytes, int]) -> None:
        assembly = self._assemblies.pop(key, None)
        if assembly is not None:
            self._held -= assembly.cost
