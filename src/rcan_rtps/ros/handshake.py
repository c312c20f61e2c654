"""Making sure a peer's next sample reaches our readers: a reply, or the first feedback.

Two things can make a volatile writer's sample miss a reader that is matched in our view:

1. The peer has not matched our reader yet, and a volatile writer drops what it writes
   before the match. An rmw_fastrtps server replies at once to a client it cannot identify
   (it waits for the client's reply reader only when the request names that reader in its
   RTPS related-sample identity, which cyclonedds cannot write), and a feedback publisher
   does not wait at all.
2. Cyclone starts a volatile reader at the last sequence number of the first HEARTBEAT it
   hears from a remote writer: a sample that arrived before and is covered by it is
   dropped as history. A Fast DDS writer sends a new reader a GAP+HEARTBEAT once, when it
   matches it, and ignores Cyclone's pre-emptive ACKNACKs (count 0). If it matched our
   reader before we knew its writer, that HEARTBEAT was dropped, the next one came with
   the reply, and the reply was dropped (traced; issue 12: 5 of 118 fresh CLI calls). So
   clients make a reader only once discovery shows the writer it waits for.
3. The same when our socket drops that one GAP+HEARTBEAT (its receive buffer full). The
   writer's next HEARTBEAT, sent with the reply and ahead of its DATA, names the reply as
   its last sample; being the first Cyclone hears from that writer since none of our
   readers was matched with it (`ddsi_receive.c`, `handle_Heartbeat`), it makes Cyclone
   drop the reply as history and ACK it: lost for good (traced, docs/design/zero-loss.md).
   So a client hears that HEARTBEAT in the packet capture before its first request, and
   makes its reader again when it does not come (`ServiceClient._await_announced`).
4. Cyclone drops a Cyclone writer's DATA while it has seen no HEARTBEAT of that writer
   since a reliable reader of ours matched it (`ddsi_receive.c`: "no heartbeat seen yet"):
   the writer sends one to our participant when it matches our reader, but from a timer
   thread, rate-limited per writer, while a sample it writes goes out at once. A first
   feedback that overtakes it is dropped, and comes again only once the writer has our
   NACK: on a busy machine after the goal's end (docs/design/zero-loss.md). So an action
   client hears a HEARTBEAT of each feedback writer applied to its new reader before its
   first goal, as in 3.

Against 1: discovery sends our readers to a peer on one reliable stream (SEDP
subscriptions) in creation order, and the peer matches them in that order. A fresh
transient-local reader of `ros_discovery_info` created *after* our other readers receives
the peer's latched ParticipantEntitiesInfo only once the peer has matched it, so only after
it has matched every reader created before it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable, Collection, Iterable, Mapping
from typing import TYPE_CHECKING, Any

from cyclonedds.core import DDSException
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader

from .info_inbox import INFO_GID, gid_of
from .participant import RosNode
from .raw_cdr import RawSample
from .readers import Watch

if TYPE_CHECKING:
    from .rtps_capture import IdentityCapture

log = logging.getLogger(__name__)

POLL = 0.01
FASTDDS_VENDOR = b"\x01\x0f"  # eProsima: its writers announce themselves once (3. above)
CYCLONE_VENDOR = b"\x01\x10"  # Eclipse: its readers take nothing before a HEARTBEAT (4.)
# How long after the handshake a writer's first HEARTBEAT to our new reader may take to show
# in the capture before the reader is made again, and how many readers at most.
ANNOUNCE_WAIT = 0.3
ANNOUNCE_TRIES = 4


def participant_prefix(guid: bytes) -> bytes:
    """The 12-byte GUID prefix naming an endpoint's participant."""
    return bytes(guid[:12])


_RETRIES = 8


def matched_publications(reader: DataReader[Any]) -> list[int]:
    """`reader.get_matched_publications()`, asked again when a writer matched between the
    binding's two calls: it sizes its buffer by the first and then indexes up to the count the
    second returns (cyclonedds 0.10 and 11 raise IndexError). Empty if it never settles."""
    for _ in range(_RETRIES):
        try:
            return list(reader.get_matched_publications())
        except IndexError:
            continue
    return []


def matched_subscriptions(writer: DataWriter[Any]) -> list[int]:
    """`writer.get_matched_subscriptions()`, as `matched_publications`."""
    for _ in range(_RETRIES):
        try:
            return list(writer.get_matched_subscriptions())
        except IndexError:
            continue
    return []


HANDLE_MASK = 0xFFFF_FFFF_FFFF_FFFF


def writer_handle(handle: int) -> int:
    """A writer's instance handle as one number: the binding gives the matched-publication
    list's as signed 64-bit integers and a sample's `publication_handle` as unsigned."""
    return int(handle) & HANDLE_MASK


class WriterGuids:
    """The GUIDs of the writers whose samples `reader` takes, by their handle (a sample
    names its writer by handle only; the capture knows it by GUID). The writers no longer
    matched are let go of — looked at when a new one comes: a robot that restarts its
    servers brings new ones for as long as we run — once `node` has delivered what they
    sent: a sample a writer sent just before it left can still be on its way, and the
    reader no longer tells that writer's GUID."""

    def __init__(self, node: RosNode, reader: DataReader[Any]) -> None:
        self._node, self._reader = node, reader
        self._guids: dict[int, bytes] = {}
        self._letting_go: asyncio.Task[None] | None = None

    def __len__(self) -> int:
        return len(self._guids)

    def of(self, publication_handle: int) -> bytes | None:
        """The GUID of the writer of a sample (its `sample_info.publication_handle`); None
        if the reader does not know it (not matched). Call on the event loop."""
        handle = writer_handle(publication_handle)
        guid = self._guids.get(handle)
        if guid is None:
            found = self._reader.get_matched_publication_data(handle)
            if found is None:
                return None
            guid = self._guids[handle] = bytes(found.key.bytes)
            self._let_go_of_gone_writers()
        return guid

    def of_sample(self, sample: Any) -> bytes | None:
        """The GUID of the writer of a sample our reader delivered (its `sample_info`); None
        for one with none (taken from the capture), or whose writer the reader no longer
        knows, or once the reader is deleted."""
        info = getattr(sample, "sample_info", None)
        if info is None:
            return None
        try:
            return self.of(info.publication_handle)
        except DDSException:  # (the reader deleted meanwhile)
            return None

    def _let_go_of_gone_writers(self) -> None:
        if self._letting_go is not None:
            return  # the next new writer looks again
        gone = self._guids.keys() - {writer_handle(h) for h in matched_publications(self._reader)}
        if gone:
            self._letting_go = asyncio.get_running_loop().create_task(
                self._let_go_once_delivered(gone))

    async def _let_go_once_delivered(self, gone: set[int]) -> None:
        try:
            await self._node.delivered()
        finally:
            self._letting_go = None
        for handle in gone:
            self._guids.pop(handle, None)

    def close(self) -> None:
        if self._letting_go is not None:
            self._letting_go.cancel()


def matched_writers(reader: DataReader[Any]) -> dict[int, bytes]:
    """The writers `reader` is matched with (our view): instance handle (`writer_handle`)
    → GUID."""
    found = {}
    for handle in matched_publications(reader):
        data = reader.get_matched_publication_data(handle)
        if data is not None:
            found[writer_handle(handle)] = bytes(data.key.bytes)
    return found


async def writers_ready(node: RosNode, writers: Mapping[int, bytes], timeout: float) -> None:
    """Waits (at most `timeout`, then goes on) until the participants of these writers
    (handle → GUID, matched by readers of `node`) have matched our readers."""
    await peers_know_our_readers(node, {participant_prefix(g) for g in writers.values()},
                                 timeout)


async def peers_know_our_readers(node: RosNode, peers: Iterable[bytes],
                                 timeout: float) -> set[bytes]:
    """Waits until each peer (participant prefix) has matched every reader this node created
    so far. Returns the peers confirmed; peers that publish no `ros_discovery_info` (not a
    ROS node) cannot be confirmed and are not waited for."""
    wanted = set(peers)
    if not wanted:
        return set()
    probe = node.discovery_reader()
    heard: set[bytes] = set()  # (added to by the reader thread: C-level set operations only)
    try:
        # Any peer may write infos of any size (and a deep latched history of them): the
        # node's reader thread takes each as it arrives and keeps only the gid it names.
        watch = node.reader_thread.add(Watch(
            probe, lambda samples: _note_heard(heard, wanted, samples),
            "ros_discovery_info (probe)", raw=True))
        try:
            return await _await_latched(probe, heard, wanted, timeout)
        finally:
            node.reader_thread.remove(watch, wait=False)
    finally:
        with contextlib.suppress(DDSException):
            probe.__del__()


def _note_heard(heard: set[bytes], wanted: set[bytes], samples: list[RawSample]) -> None:
    """Notes the wanted peers these infos name. Only those: a peer flooding infos of made-up
    gids during the wait (it may last the caller's whole timeout) grew the set by one entry
    each, ~100,000 (10 MB traced) in a 5 s wait."""
    for data, info in samples:
        if info.valid_data and len(data) >= INFO_GID.stop:
            prefix = participant_prefix(gid_of(data))
            if prefix in wanted:
                heard.add(prefix)


async def _await_latched(probe: DataReader[Any], heard: set[bytes], wanted: set[bytes],
                         timeout: float) -> set[bytes]:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while True:
        # A peer without a ros_discovery_info writer (not a ROS node) cannot be waited for.
        announcing = {participant_prefix(g) for g in matched_writers(probe).values()}
        waiting = (wanted & announcing) - heard
        if not waiting:
            return wanted & heard
        if loop.time() >= deadline:
            log.debug("peers %s did not confirm our readers within %.1f s",
                      [p.hex() for p in waiting], timeout)
            return wanted & heard
        await asyncio.sleep(POLL)


async def acquire_by(lock: asyncio.Lock, deadline: float) -> bool:
    """Takes `lock`, waiting for it at most until `deadline` (loop time); False when another
    still held it then. A free lock is taken at once, whatever the deadline. The announcement
    wait a lock holder does (`hear_announcements`) is bounded by the holder's deadline, not by
    a waiter's: without this a call waiting its turn ran up to ~1.2 s past its own."""
    if not lock.locked():
        await lock.acquire()  # free: taken without suspending
        return True
    loop = asyncio.get_running_loop()
    try:
        await asyncio.wait_for(lock.acquire(), max(0.0, deadline - loop.time()))
    except asyncio.TimeoutError:
        return False
    return True


def may_withhold_before_heartbeat(guid: bytes) -> bool:
    """Whether our reader may drop this writer's samples until it has heard one of its
    HEARTBEATs (4. above): a Cyclone writer — or one whose vendor its GUID does not tell.
    Under DDS-Security (SROS2) a GUID prefix is derived from the participant's certificate
    and carries no vendor id, while Cyclone still knows the vendor (the RTPS header, SPDP's
    PID_VENDORID) and holds a Cyclone writer's DATA back all the same; the binding shows
    neither, and SROS2's metadata protection encrypts the HEARTBEATs the capture would hear.
    So only a writer known to be Fast DDS's (whose samples Cyclone takes before any
    HEARTBEAT) is not waited for: not knowing fails closed (a repair wait, not a lost
    feedback)."""
    return bytes(guid[:2]) != FASTDDS_VENDOR


def fastdds_writers(reader: DataReader[Any], skip: Collection[int] = ()) -> dict[int, bytes]:
    """The Fast DDS writers matched with `reader` (handle → GUID), but for `skip`."""
    return writers_of(reader, (FASTDDS_VENDOR,), skip)


def writers_of(reader: DataReader[Any], vendors: Collection[bytes],
               skip: Collection[int] = ()) -> dict[int, bytes]:
    """The writers of these vendors matched with `reader` (handle → GUID), but for `skip`."""
    return {h: g for h, g in matched_writers(reader).items()
            if h not in skip and g[:2] in vendors}


async def hear_announcements(capture: IdentityCapture, reader: Callable[[], DataReader[Any]],
                             since: Callable[[], int],
                             renew: Callable[[], Awaitable[None]], deadline: float, *,
                             vendors: Collection[bytes] = (FASTDDS_VENDOR,),
                             skip: Callable[[], Collection[int]] = frozenset,
                             may_renew: Callable[[], bool] = lambda: True,
                             closed: Callable[[], bool] = lambda: False,
                             ) -> tuple[set[int], dict[int, bytes]]:
    """Waits until a HEARTBEAT of every matched writer of `vendors` applied to `reader()`
    was heard in the packet capture (3. and 4. above; `since()`: the capture's mark taken
    once that reader was made); when one has not come within ANNOUNCE_WAIT, `renew()`
    makes the reader again (matched and handshaken), which the writers announce themselves
    to afresh. At most ANNOUNCE_TRIES readers, within `deadline` (loop time), while
    `may_renew()`. Returns the writers (handles) heard, and those still unheard (handle →
    GUID) when it gave up, of the last reader; nothing at once when its owner is `closed()`
    (its reader deleted: the caller says so)."""
    loop = asyncio.get_running_loop()
    writers: dict[int, bytes] = {}
    unheard: dict[int, bytes] = {}
    for attempt in range(ANNOUNCE_TRIES):
        if attempt and not closed():
            await renew()
        until = min(deadline, loop.time() + ANNOUNCE_WAIT)
        while True:
            if closed():
                return set(), {}
            current = reader()
            guid = bytes(current.guid.bytes)
            writers, mark = writers_of(current, vendors, skip()), since()
            unheard = {h: g for h, g in writers.items()
                       if not capture.heard_heartbeat(g, guid, mark)}
            if not unheard or loop.time() >= until:
                break
            await asyncio.sleep(POLL)
        if not unheard or loop.time() >= deadline or not may_renew():
            break
    return writers.keys() - unheard.keys(), unheard
