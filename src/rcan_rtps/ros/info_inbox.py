"""ros_discovery_info as it arrives, taken by the node's reader thread one sample at a time.

Any peer may write ros_discovery_info samples of any size, and the reader keeps up to 1,000
of them (keyless: a deep history keeps one participant's update from pushing out another's
unread one). Taken only by a graph's refresh, they waited inside Cyclone until the next one:
200 samples of 4.8 MB grew a process by 920 MB (red team 32), and a process that never
refreshed (a CLI command between two calls) held them for good.

Here the node's reader thread takes each sample as it arrives (`Watch(raw=True)`), looks at
its size before anything else, and keeps only what a refresh needs: per participant gid the
newest sample, or for one past MAX_INFO_BYTES a mark that its participant's info is unknown
now. What waits is bounded in count and bytes; a refresh decodes it on its own loop
(`InfoInbox.take`), oldest first, so many bytes at a time.
"""

from __future__ import annotations

import threading
from collections import Counter, OrderedDict
from collections.abc import Callable
from typing import Any

import msgspec
from cyclonedds.core import InstanceState

from .raw_cdr import RawSample

# The IDL bounds no sequence of an info, and decoding one costs ~4 times its size in Python
# objects, kept while its participant lives: a sample larger than this is dropped undecoded
# (a participant of 1,000 nodes with 60 endpoints each needs ~1 MB of it).
MAX_INFO_BYTES = 2 << 20
# An info's gid, in its first 16 bytes after the 4-byte CDR header (octets: no alignment),
# read there from a sample before (or without) decoding it.
INFO_GID = slice(4, 20)
# Infos waiting for a refresh, at most: as many participants as a refresh takes samples of
# each builtin reader. Past it the oldest of the participant whose writers have the most
# waiting goes: a peer writing made-up gids faster than a refresh runs, from one writer or
# thousands, pushes out its own, not the one info each honest participant wrote (the oldest
# overall went: 1,024 made-up gids written between two refreshes dropped an honest node's
# info, written once, for good). Not when the flood comes from as many participants as it has
# infos: all tie at one, and the source counted first goes first.
WAITING_INFOS = 1024
# And their bytes, at most: room for four samples at the size bound beside a graph's honest,
# small infos. Past it the largest waiting sample is dropped first (it is a mark then: its
# participant's nodes are not known), so a flood of large infos cannot push out small ones.
WAITING_INFO_BYTES = 4 * MAX_INFO_BYTES + (4 << 20)


class Arrived(msgspec.Struct, frozen=True):
    """What arrived for one participant gid: its newest info's CDR bytes, or None when that
    was past MAX_INFO_BYTES (or dropped waiting) — its nodes are unknown; whether the
    topic's instance was alive when it was taken (not: every writer left); and who wrote it
    (`InfoInbox`'s `source_of` its SampleInfo's `publication_handle`: the writer's
    participant)."""

    data: bytes | None
    alive: bool
    source: bytes = b""


def _handle_bytes(handle: int) -> bytes:
    return handle.to_bytes(8, "little")


class InfoInbox:
    """Infos taken by the reader thread (`arrived`), waiting for a refresh (`take`).

    One lock, held for dictionary work only: never across a DDS call or a decode."""

    def __init__(self, source_of: Callable[[int], bytes] = _handle_bytes) -> None:
        # Who wrote a sample, from its writer's handle: the bound on count is shared fairly
        # between sources. A graph gives the writer's participant (a peer may make writers
        # by the thousand in one participant: as one source they push out their own infos).
        self._source_of = source_of
        self._lock = threading.Lock()
        self._waiting: OrderedDict[bytes, Arrived] = OrderedDict()  # oldest first
        self._bytes = 0
        self._per_source: Counter[bytes] = Counter()  # infos waiting, by who wrote them
        self.large = 0  # samples past MAX_INFO_BYTES, dropped as they arrived
        self.dropped = 0  # samples dropped waiting (the bounds above)

    # -- the reader thread ------------------------------------------------------------------
    def arrived(self, samples: list[RawSample]) -> None:
        """`Watch(raw=True)`'s delivery: one sample (CDR bytes, SampleInfo) at a time."""
        for data, info in samples:
            if not info.valid_data:
                continue  # keyless: an invalid sample names no participant
            alive = info.instance_state == InstanceState.Alive
            large = len(data) > MAX_INFO_BYTES
            source = self._source_of(int(info.publication_handle))  # (before the lock)
            self._keep(gid_of(data), Arrived(None if large else data, alive, source), large)

    def _keep(self, gid: bytes, arrived: Arrived, large: bool) -> None:
        with self._lock:
            self.large += large
            self._let_go(self._waiting.pop(gid, None))
            self._waiting[gid] = arrived
            self._bytes += _size(arrived)
            self._per_source[arrived.source] += 1
            while len(self._waiting) > WAITING_INFOS:
                self._drop_of_busiest_source()
            while self._bytes > WAITING_INFO_BYTES:
                self._drop_largest()

    def _let_go(self, arrived: Arrived | None) -> None:
        """Accounts for an info no longer waiting (under the lock)."""
        if arrived is None:
            return
        self._bytes -= _size(arrived)
        self._per_source[arrived.source] -= 1
        if not self._per_source[arrived.source]:
            del self._per_source[arrived.source]

    def _drop_of_busiest_source(self) -> None:
        """The oldest info of the source with the most waiting goes (O(infos waiting) at
        most, on the reader thread, only while the count bound is crossed)."""
        busiest = max(self._per_source, key=self._per_source.__getitem__)
        gid = next(g for g, a in self._waiting.items() if a.source == busiest)
        self._let_go(self._waiting.pop(gid))
        self.dropped += 1

    def _drop_largest(self) -> None:
        gid = max(self._waiting, key=lambda g: _size(self._waiting[g]))
        kept = self._waiting[gid]
        self._bytes -= _size(kept)
        # (in place: its participant's older info, if any, is stale all the same)
        self._waiting[gid] = Arrived(None, kept.alive, kept.source)
        self.dropped += 1

    # -- the graph's loop -------------------------------------------------------------------
    def take(self, budget: int) -> tuple[list[tuple[bytes, Arrived]], bool]:
        """What waits, oldest first, until the infos' bytes reach `budget` (the one that
        crosses it included): ((gid, what arrived) pairs, whether nothing is left)."""
        taken: list[tuple[bytes, Arrived]] = []
        size = 0
        with self._lock:
            while self._waiting and size < budget:
                gid, arrived = self._waiting.popitem(last=False)
                self._let_go(arrived)
                size += _size(arrived)
                taken.append((gid, arrived))
            return taken, not self._waiting

    def waiting(self) -> int:
        with self._lock:
            return len(self._waiting)


def _size(arrived: Arrived | None) -> int:
    return 0 if arrived is None or arrived.data is None else len(arrived.data)


def gid_of(data: Any) -> bytes:
    """The participant gid an info's CDR bytes name, read without decoding it."""
    return bytes(data[INFO_GID])
