"""ROS 2 services over plain DDS, speaking both request-reply mappings.

    RequestMapping.CYCLONE  rmw_cyclonedds: a 16-byte in-band header (client guid, seq) in
                            every request and reply, so replies correlate exactly.
    RequestMapping.FASTDDS  rmw_fastrtps: plain samples; a reply names its request (request
                            writer GUID, sequence number) only as the RTPS related sample
                            identity in its inline QoS, which the cyclonedds API can neither
                            read nor write; we read it from Cyclone's packet capture
                            (rtps_capture.py, docs/design/rpc-identity.md). A
                            reply Cyclone dropped as history (it reached our socket,
                            never our reader) is taken from that capture too.
    RequestMapping.AUTO     chosen per call from the vendor of the server's request reader
                            (GUID prefix 01.10 Cyclone; anything else gets plain requests).

A Fast DDS server's reply writer sends each client's replies to every reply reader. A
client keeps one request outstanding per endpoint and queues the rest; a reply whose related
sample identity names another request (another client's, or one we gave up on) is dropped.
A reply whose identity cannot be read (the capture is off, RCAN_RTPS_RPC_IDENTITY=off; the
traffic is encrypted, DDS-Security; its datagram not found in the capture) is taken as ours
only while this client is the service's only one in the graph, when it was sent and when it
came, and the others left at least QUIET_AFTER_CLIENT_LEFT_S before: otherwise it could be
another client's answer, and the call fails with AmbiguousReply
(`ambiguous_reply`) rather than return it. Actions, which cross-check the reply themselves
(goal ids on the status topic, in a cancel's answer), and a stop's server-wide cancel, which
needs no answer, take it still (`unidentified_ok`); `ServiceClient.answer` tells them whether
the reply was tied to their request, and which writer sent it (`Answer`). Every server of a
name gets every request (in both mappings): a caller that knows which one it wants the
reply of names its participant (`from_participant`: an action's get_result, its goal's
server), and the others' replies are dropped. Replies
arriving while nothing is outstanding, or not tied to the request and failing the caller's
`accept` check, are dropped,
and after a timeout a late reply gets to drain before the next request.

`ServiceServer` speaks the Cyclone mapping only. Fast DDS clients cannot use it: they drop
every reply without the RTPS related-sample identity, which cyclonedds cannot set, and their
header-less requests would be misread, so requests from Fast DDS writers are dropped with a
warning instead.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import itertools
import logging
import time
import weakref
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from cyclonedds.core import DDSException
from cyclonedds.idl import IdlStruct
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader

from . import _cyclone_header as cyclone
from . import qos as qos_mod
from .errors import AmbiguousReply, ServiceTimeout, ServiceUnavailable, WireError, seconds
from .graph import Direction, Endpoint, shared_graph
from .handshake import (
    POLL,
    WriterGuids,
    acquire_by,
    fastdds_writers,
    hear_announcements,
    matched_writers,
    participant_prefix,
    writers_ready,
)
from .names import mangle_service
from .participant import RosNode
from .qos import QosProfile
from .readers import Decode
from .rtps_capture import IdentityCapture, SampleIdentity

log = logging.getLogger(__name__)

CYCLONE_VENDOR = b"\x01\x10"
STALE_REPLY_GRACE = 0.5  # s a timed-out Fast DDS request's late reply gets to arrive and be dropped
# s between looks, while a call waits for its reply, at whether its node was closed (then no
# reply can reach it: the node's reader thread has stopped)
NODE_CLOSED_POLL = 0.1
# s after a Fast DDS request before its reply is looked for in the packet capture, between
# looks, and once found there before it is delivered from it (the reader's turn first: Cyclone
# processes a datagram right after writing it to the capture)
CAPTURE_REPLY_AFTER = 0.5
CAPTURE_POLL = 0.1
CAPTURE_SETTLE = 0.2
# s after the other clients of a service left during which a reply without a readable
# identity is still not taken as ours: a reply to a request one of them gave up on may come
# after it left. Longer than a Fast DDS writer's repair of a lost reply (its HEARTBEAT period
# is 3 s) and than the late replies seen under load; a server slower than this to answer a
# request whose client left stays the window (docs/design/rpc-identity.md).
QUIET_AFTER_CLIENT_LEFT_S = 10.0

# A server's replies reach every client's reply reader, and every client's requests every
# server's request reader: a reader keeps this many while the node's reader thread waits for
# a core, so that others' samples cannot push ours out (the services profile keeps 10).
PAIR_READER_DEPTH = 1000

Accept = Callable[[IdlStruct], bool]


class RequestMapping(enum.Enum):
    AUTO = "auto"
    CYCLONE = "cyclone"
    FASTDDS = "fastdds"


def mapping_of_vendor(guid: bytes, service_id: str = "") -> RequestMapping:
    """rmw_cyclonedds' mapping for its endpoints: known by their vendor bytes, or, as a
    secured participant's GUID no longer starts with them (DDS-Security derives it from the
    certificate), by the serviceid/clientid rmw_cyclonedds puts in their USER_DATA."""
    if guid[:2] == CYCLONE_VENDOR or service_id:
        return RequestMapping.CYCLONE
    return RequestMapping.FASTDDS


_id_counters: weakref.WeakKeyDictionary[RosNode, itertools.count[int]] = \
    weakref.WeakKeyDictionary()


def new_endpoint_id(node: RosNode) -> bytes:
    """A client/service id as rmw_cyclonedds makes it: the participant's GUID prefix
    (12 bytes) followed by a per-participant counter, big-endian."""
    counter = _id_counters.setdefault(node, itertools.count(1))
    prefix: bytes = node.participant.guid.bytes[:12]
    return prefix + next(counter).to_bytes(4, "big")


def format_endpoint_id(raw: bytes) -> str:
    """rmw_cyclonedds' text form: hex bytes joined by '.', only the first zero-padded."""
    return f"{raw[0]:02x}" + "".join(f".{b:x}" for b in raw[1:])


def _user_data(endpoint: Any) -> dict[str, str]:
    return qos_mod.user_data_of(getattr(endpoint, "qos", None))


class _Pair:
    """One writer and one reader of a service, in one mapping, delivering to asyncio (the
    node's reader thread takes the samples; `deliver` runs on the event loop)."""

    def __init__(self, node: RosNode, mapping: RequestMapping, out: tuple[str, str],
                 into: tuple[str, str], qos: QosProfile, user: str,
                 deliver: Callable[[_Pair, list[Any]], None]) -> None:
        self.mapping = mapping
        self._deliver = deliver
        self._loop = asyncio.get_running_loop()
        self._node = node
        self._into, self._qos, self._user = into, qos, user
        self._what = f"a {out[1]}"  # what this pair writes, in errors: a request or reply
        self.writer: DataWriter[Any]
        if mapping is RequestMapping.CYCLONE:
            self.writer = cyclone.create_writer(node, *out, qos, user)
            self._decode: Decode | None = cyclone.decoder(node, into[1])
        else:
            self.writer = node.create_writer(*out, qos, extra_user_data=user)
            self._decode = None  # the plain type's own generated decoder
        self.reader, self.watch = self._make_reader()
        self.out_codec = node.codecs.of(out[1]).prepare_encoders()
        # rmw_cyclonedds names a client in the header by its request writer's handle.
        self.guid = int(self.writer.get_instance_handle()) & 0xFFFF_FFFF_FFFF_FFFF
        # RTPS names a sample (writer GUID, sequence number); Cyclone numbers a writer's
        # samples 1, 2, ... and this writer writes nothing but requests or replies.
        self.writer_guid = bytes(self.writer.guid.bytes)
        self.written = 0
        # Reply writers' GUIDs by handle (`related_identity`); the gone ones let go of.
        self.writer_guids = WriterGuids(node, self.reader)
        self.ready: set[int] = set()  # server writers whose next reply will reach us
        # Server writers whose first HEARTBEAT to this reader was heard (or given up on).
        self.announced: set[int] = set()
        self.announce_lock = asyncio.Lock()
        self.renewed = 0  # times the reader was made again (see `renew_reader`)
        self.unannounced = 0  # writers given up on: the request went out without their HEARTBEAT
        self.from_capture = 0  # replies our reader never delivered, taken from the capture

    def _make_reader(self) -> tuple[DataReader[Any], Any]:
        node, into, qos = self._node, self._into, self._qos.keeping(PAIR_READER_DEPTH)
        if self.mapping is RequestMapping.CYCLONE:
            reader = cyclone.create_reader(node, *into, qos, self._user)
        else:
            reader = node.create_reader(*into, qos, extra_user_data=self._user)
        # Where the packet capture was once the reader existed (handshake.hear_announcements)
        self.since = 0 if node.identities is None else node.identities.mark()

        def on_samples(samples: list[Any]) -> None:  # on the node's reader thread
            if reader is self.reader:  # not a renewed reader's last batch
                self._on_samples(samples)
        return reader, node.watch(reader, on_samples, f"{into[0]} ({self.mapping.value})",
                                  decode=self._decode)

    def renew_reader(self) -> None:
        """Replaces the reply reader with a new one, which the servers' writers will match
        and announce themselves to afresh (see `ServiceClient._await_announced`). Only
        before a request was sent on this pair: a reply in flight would miss the new one."""
        old, watch = self.reader, self.watch
        self._node.unwatch(watch)
        self._node.forget_reader(old)
        with contextlib.suppress(DDSException):
            old.__del__()
        self.reader, self.watch = self._make_reader()
        self.writer_guids.close()  # (before any request: nothing of the old one is awaited)
        self.writer_guids = WriterGuids(self._node, self.reader)
        self.ready.clear()
        self.announced.clear()
        self.renewed += 1

    def unready_writers(self) -> dict[int, bytes]:
        """The matched server reply writers not yet made ready (see `handshake.py`)."""
        return {h: g for h, g in matched_writers(self.reader).items() if h not in self.ready}

    def unannounced_writers(self) -> dict[int, bytes]:
        """The matched Fast DDS reply writers whose first HEARTBEAT to this reader was not
        heard yet."""
        return fastdds_writers(self.reader, self.announced)

    def _on_samples(self, samples: list[Any]) -> None:  # on the node's reader thread
        try:
            self._loop.call_soon_threadsafe(self._on_loop, samples)
        except RuntimeError:  # the loop closed while DDS was still delivering
            return

    def _on_loop(self, samples: list[Any]) -> None:
        if not self.watch.closed and not self._node.closed:
            self._deliver(self, samples)

    def write(self, message: IdlStruct, header: cyclone.RequestHeader | None = None) -> None:
        """Sends one request or reply (with the in-band header in the Cyclone mapping)."""
        data = self.out_codec.encode(message)
        sample = data if header is None else cyclone.wrap_cdr(header, data)
        self._node.write_cdr(self.writer, sample, self._what)
        self.written += 1

    def related_identity(self, sample: Any) -> SampleIdentity | None:
        """The request a received sample answers, from its RTPS inline QoS (None: unknown —
        no capture, not in it, or the writer sent none)."""
        capture = self._node.identities
        if capture is None:
            return None
        info = sample.sample_info
        guid = self.writer_guids.of(info.publication_handle)
        if guid is None:
            return None
        return capture.lookup(guid, info.source_timestamp)

    def matched(self) -> bool:
        return bool(self.writer.get_publication_matched_status().current_count and
                    self.reader.get_subscription_matched_status().current_count)

    def close(self) -> None:
        """Stops deliveries and deletes both endpoints; idempotent."""
        if self.watch.closed:
            return
        self.writer_guids.close()
        self._node.unwatch(self.watch)
        self._node.forget_reader(self.reader)
        self._node.forget_writer(self.writer)
        for entity in (self.reader, self.writer):
            with contextlib.suppress(DDSException):
                entity.__del__()


class _Role(enum.Enum):
    """Which end of a service; the value is the key rmw_cyclonedds gives its id in the
    endpoints' USER_DATA."""

    CLIENT = "clientid"  # writes requests, reads replies
    SERVER = "serviceid"  # writes replies, reads requests


class _ServiceEnd:
    """What a client and a server of a service both set up: the resolved name, the service
    type's request and response type names, the two DDS topics, an rmw_cyclonedds-style id,
    the QoS; and `_make_pair`, their writer and reader in one mapping."""

    _ROLE: ClassVar[_Role]

    def __init__(self, node: RosNode, service: str, type_name: str, qos: QosProfile,
                 governed: bool = False) -> None:
        self.node = node
        self.name = node.resolve(service)
        # A client the robot obeys (an action's goals and cancels): its request writer
        # carries the node's `governed_by`.
        self._governed = node.governed_entry if governed else ""
        srv = node.store.service(type_name)
        # Its endpoints are made by the first call, which may be a stop's (a server-wide
        # cancel): every type they nest is loaded now, so that call parses no IDL.
        node.store.load_nested(srv.request.name)
        node.store.load_nested(srv.response.name)
        self.type_name = srv.name
        self.request_type, self.response_type = srv.request.name, srv.response.name
        self.request_topic, self.reply_topic = mangle_service(self.name)
        self.id = new_endpoint_id(node)
        self._qos = qos

    def _make_pair(self, mapping: RequestMapping,
                   deliver: Callable[[_Pair, list[Any]], None]) -> _Pair:
        requests = (self.request_topic, self.request_type)
        replies = (self.reply_topic, self.response_type)
        out, into = (requests, replies) if self._ROLE is _Role.CLIENT else (replies, requests)
        return _Pair(self.node, mapping, out, into, self._qos,
                     f"{self._ROLE.value}={format_endpoint_id(self.id)};{self._governed}",
                     deliver)


@dataclass(slots=True)
class _Outstanding:
    """The one outstanding request in the Fast DDS mapping."""

    future: asyncio.Future[IdlStruct]
    accept: Accept | None  # the caller's check of a reply
    identity: SampleIdentity  # the request's (our writer's GUID, its sample number)
    unidentified_ok: bool  # taken without identity: the caller checks it itself (actions)
    alone: bool  # no other client of the service was in the graph as it was sent
    participant: bytes | None = None  # the only server whose reply is taken (`call`)
    tied: bool = False  # the reply taken names this request (see `Answer.tied`)

    def accepts(self, reply: Any) -> bool:
        return self.accept is None or self.accept(reply)


@dataclass(frozen=True, slots=True)
class Answer:
    """A call's reply, and whether it is known to answer this very request (`tied`): the
    Cyclone mapping's header names it, or the packet capture read the Fast DDS reply's
    related sample identity and it names our request (not under DDS-Security: there the
    capture sees only what travels in clear, which a forger could have sent). A reply not
    tied was taken only because this client was the service's only one in the graph, or
    because the caller checks it itself (`unidentified_ok`). `writer`: the GUID of the
    reply writer it came from, as our reader names it (None: taken from the packet capture,
    or its writer no longer matched): an action's goal is its status only from that
    writer's participant (action_goals.py)."""

    reply: IdlStruct
    tied: bool
    writer: bytes | None = None


class ServiceClient(_ServiceEnd):
    """Calls one service; `await call(request)` returns the response."""

    _ROLE = _Role.CLIENT

    def __init__(self, node: RosNode, service: str, type_name: str, *,
                 mapping: RequestMapping = RequestMapping.AUTO,
                 qos: QosProfile = qos_mod.SERVICES, governed: bool = False) -> None:
        super().__init__(node, service, type_name, qos, governed)
        self.mapping = mapping
        self._graph = shared_graph(node)
        self._pairs: dict[RequestMapping, _Pair] = {}
        self._seq = itertools.count(1)
        self._pending: dict[int, asyncio.Future[IdlStruct]] = {}
        # Cyclone mapping: the participant (GUID prefix) a pending request's reply must come
        # from, where the caller named one (`call`'s `from_participant`).
        self._pending_from: dict[int, bytes] = {}
        self._plain_lock = asyncio.Lock()
        self._plain_waiter: _Outstanding | None = None
        self._stale = False
        self.closed = False
        self.dropped_replies = 0  # replies not ours: foreign guid, unsolicited, not accepted

    def describe_ahead(self) -> None:
        """Describes the types of its topics now, in either mapping, and keeps that: its
        first call — a stop's server-wide cancel, for an action client — then makes its
        endpoints without describing anything (a bridge lets the describer go once started:
        `rcan_rtps._modules.START_ONLY`)."""
        for type_name in (self.request_type, self.response_type):
            self.node.types.keep_description(type_name)  # Fast DDS' mapping
            self.node.types.keep_description(type_name, cyclone.wrapper_model)

    # -- discovery --------------------------------------------------------------
    def server_guids(self) -> list[bytes]:
        """GUIDs of the request readers of this service's servers (from discovery)."""
        return [e.gid for e in self._server_readers()]

    def _server_readers(self) -> list[Endpoint]:
        self._graph.refresh()
        return [e for e in self._graph.endpoints()
                if e.dds_topic == self.request_topic and e.direction is Direction.SUBSCRIPTION]

    def _reply_writer_known(self) -> bool:
        self._graph.refresh()  # with a configured mapping, nothing else refreshes it
        return any(e.dds_topic == self.reply_topic and e.direction is Direction.PUBLISHER
                   for e in self._graph.endpoints())

    def _other_clients(self, pair: _Pair) -> bool:
        """Whether another client of this service is in the graph (another request writer or
        reply reader, of any process, this one's included), or left it less than
        QUIET_AFTER_CLIENT_LEFT_S ago: a reply without a readable identity could then be its
        answer. A client that left may have left its last request unanswered (it gave up
        on it: timed out, refused as ambiguous), and the server's reply to it still goes to
        every reply reader — ours, once we are the only one (a clean-clone CI under load
        took such a reply for its own request, 1 of 150)."""
        graph = self._graph
        graph.refresh()
        clients = graph.gids_on(self.request_topic, Direction.PUBLISHER) \
            | graph.gids_on(self.reply_topic, Direction.SUBSCRIPTION)
        if clients - {pair.writer_guid, bytes(pair.reader.guid.bytes)}:
            return True
        # When the graph saw the last request writer leave, whenever that was: a client that
        # came and went between two of our calls, never seen by one, counts as well.
        left = graph.left_at(self.request_topic, Direction.PUBLISHER)
        return left is not None and time.monotonic() - left < QUIET_AFTER_CLIENT_LEFT_S

    def resolve_mapping(self) -> RequestMapping | None:
        """The configured mapping, or the servers' (None while there is no server)."""
        if self.mapping is not RequestMapping.AUTO:
            return self.mapping
        mappings = {mapping_of_vendor(e.gid, e.service_id) for e in self._server_readers()}
        if len(mappings) > 1:
            raise WireError(f"servers of {self.name} use both request mappings; "
                            "choose one with RequestMapping.CYCLONE or FASTDDS")
        return mappings.pop() if mappings else None

    def _pair(self, mapping: RequestMapping) -> _Pair:
        # Endpoints are made once the mapping is known: the two mappings' samples have
        # different types on the wire, so one reader cannot serve both.
        pair = self._pairs.get(mapping)
        if pair is None:
            # The capture is on before the reader exists: its first HEARTBEAT is looked for.
            if mapping is RequestMapping.FASTDDS and self.node.identities is not None:
                self.node.identities.use()
            pair = self._pairs[mapping] = self._make_pair(mapping, self._deliver)
        return pair

    async def wait_for_service(self, timeout: float = 5.0) -> _Pair:
        """Waits until a request can be answered: our request writer and reply reader are
        matched with the server's endpoints, and the server has matched our reply reader
        too, and its reply cannot be dropped on arrival (see `handshake.py`)."""
        with self._closed_said():
            return await self._wait_for_service(timeout)

    async def _wait_for_service(self, timeout: float) -> _Pair:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        pair = await self.wait_matched(timeout)
        writers = pair.unready_writers()
        if writers:
            await writers_ready(self.node, writers, max(0.0, deadline - loop.time()))
            pair.ready |= writers.keys()  # ready, or best effort past the timeout: once
        await self._await_announced(pair, deadline)
        self._check_open()  # closed while it waited: its endpoints are deleted
        return pair

    def _check_open(self) -> None:
        if self.closed:
            raise ServiceUnavailable(f"the client of {self.name} is closed")
        if self.node.closed:
            raise ServiceUnavailable(f"the client of {self.name} is closed: its node "
                                     f"{self.node.fqn} was closed")

    def _gone(self) -> bool:
        """Closed, or its node closed: its endpoints are deleted, or about to be."""
        return self.closed or self.node.closed

    @contextlib.contextmanager
    def _closed_said(self) -> Iterator[None]:
        """The binding's DDSException from an endpoint deleted meanwhile (this client or its
        node closed while a call waited) becomes ServiceUnavailable, saying so."""
        try:
            yield
        except DDSException:
            if not self._gone():
                raise
        else:
            return
        self._check_open()  # raises; out of the handler, so not chained to the binding's

    async def _await_announced(self, pair: _Pair, deadline: float) -> None:
        """Waits until every Fast DDS reply writer's first HEARTBEAT to our reply reader has
        reached our socket, making the reader again (at most ANNOUNCE_TRIES times, within the
        deadline) when it did not come: the writer sends it once, when it matches the reader,
        and Cyclone takes the first HEARTBEAT it hears as the reader's start, so a reply that
        the next one covers would be dropped as history (handshake.py). Needs the packet
        capture; once per reader, before its first request (never with a reply in flight)."""
        capture = self.node.identities
        if capture is None or not capture.reading or pair.mapping is not RequestMapping.FASTDDS \
                or self._gone():
            return
        # Calls made at once share one wait; another's, under way, is bounded by its
        # deadline, not ours.
        if not await acquire_by(pair.announce_lock, deadline):
            raise ServiceTimeout(f"service {self.name}: timed out waiting behind another call "
                                 "for the server's reply writer to announce itself")
        try:
            await self._hear_announced(pair, capture, deadline)
        finally:
            pair.announce_lock.release()

    async def _hear_announced(self, pair: _Pair, capture: IdentityCapture,
                              deadline: float) -> None:
        if self._gone() or not pair.unannounced_writers():
            return

        async def renew() -> None:
            pair.renew_reader()
            log.debug("service %s: a reply writer's first HEARTBEAT to our reader did not "
                      "come; reader made again", self.name)
            await self._matched_again(pair, deadline)

        heard, unheard = await hear_announcements(
            capture, lambda: pair.reader, lambda: pair.since, renew, deadline,
            skip=lambda: pair.announced,
            may_renew=lambda: not pair.written,  # never with a request out: renew_reader
            closed=self._gone)  # then nothing heard, nothing unheard
        if unheard:
            log.debug("service %s: no first HEARTBEAT from %d reply writer(s) to our "
                      "reader after %d readers (capture %d bytes behind); the request "
                      "goes out without it", self.name, len(unheard), pair.renewed + 1,
                      capture.lag())
        pair.unannounced += len(unheard)
        pair.announced |= heard | unheard.keys()  # the unheard: best effort, once

    async def _matched_again(self, pair: _Pair, deadline: float) -> None:
        """After `renew_reader`: until the reader matches (our view), then the handshake."""
        loop = asyncio.get_running_loop()
        while not self._gone() and not pair.matched() and loop.time() < deadline:
            await asyncio.sleep(POLL)
        if self._gone():
            return
        writers = pair.unready_writers()
        if writers:
            await writers_ready(self.node, writers, max(0.0, deadline - loop.time()))
            pair.ready |= writers.keys()

    async def wait_matched(self, timeout: float = 5.0) -> _Pair:
        """Waits until our request writer and reply reader match a server's (our view)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            self._check_open()
            with self._closed_said():
                pair = self._matched_pair()
            if pair is not None:
                return pair
            if loop.time() >= deadline:
                raise ServiceUnavailable(
                    f"no server for service {self.name} ({self.type_name}) "
                    f"within {seconds(timeout)}")
            await asyncio.sleep(0.05)

    def _matched_pair(self) -> _Pair | None:
        """The pair of the servers' mapping, once it matches a server (our view)."""
        mapping = self.resolve_mapping()
        # Our reply reader is made only once we know a server's reply writer, so that
        # we hear the HEARTBEAT it sends when it matches the reader (handshake.py).
        if mapping is not None and (mapping in self._pairs or self._reply_writer_known()):
            pair = self._pair(mapping)
            if pair.matched():
                return pair
        return None

    # -- calls ------------------------------------------------------------------
    async def call(self, request: IdlStruct | Mapping[str, Any] | None = None,
                   timeout: float = 10.0, *, accept: Accept | None = None,
                   unidentified_ok: bool = False,
                   from_participant: bytes | None = None) -> IdlStruct:
        """Sends one request and returns its response. `accept` may refuse a reply not tied
        to this request (`Answer`) as not ours; the wait then goes on. A reply tied to it is
        ours whatever `accept` says, as the Cyclone mapping's always are: an action tells
        its replies from another client's by what the status topic lists, which any peer
        may write (red team 31: another writer listing our goal ended with another end had
        the server's own result refused until the call's timeout). A Fast DDS reply whose
        identity cannot be read while other clients of the service are in the graph is
        AmbiguousReply, unless `unidentified_ok`: the caller tells its reply from another
        client's itself (an action: the status topic, the goal ids) or needs none (a stop's
        server-wide cancel). `from_participant` (a GUID prefix): every server gets the
        request, and only this participant's reply is taken (an action's get_result: the
        goal's server, when a second server of the name ran the goal too); a reply whose
        writer is not known (taken from the capture) is taken still."""
        answer = await self.answer(request, timeout, accept=accept,
                                   unidentified_ok=unidentified_ok,
                                   from_participant=from_participant)
        return answer.reply

    async def answer(self, request: IdlStruct | Mapping[str, Any] | None = None,
                     timeout: float = 10.0, *, accept: Accept | None = None,
                     unidentified_ok: bool = False,
                     from_participant: bytes | None = None) -> Answer:
        """As `call`, also saying whether the reply is known to answer this request."""
        message = request if isinstance(request, IdlStruct) else \
            self.node.values.build(self.request_type, request)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        with self._closed_said():
            pair = await self._wait_for_service(timeout)
            if pair.mapping is RequestMapping.CYCLONE:
                reply = await self._call_cyclone(pair, message, deadline, from_participant)
                return Answer(reply, tied=True, writer=pair.writer_guids.of_sample(reply))
            return await self._call_plain(pair, message, deadline, accept, unidentified_ok,
                                          from_participant)

    @staticmethod
    def _from_elsewhere(pair: _Pair, sample: Any, participant: bytes | None) -> bool:
        """Whether a reply comes from a writer known to be of another participant than the
        one the call asked for (`from_participant`)."""
        if participant is None:
            return False
        writer = pair.writer_guids.of_sample(sample)
        return writer is not None and participant_prefix(writer) != participant

    async def _reply(self, future: asyncio.Future[IdlStruct], deadline: float) -> IdlStruct:
        """The reply `future` brings, or asyncio.TimeoutError at `deadline`; as soon as the
        node is closed, ServiceUnavailable (nothing can bring it any more: the client's
        own close fails the future itself)."""
        loop = asyncio.get_running_loop()
        try:
            while not future.done():
                left = deadline - loop.time()
                if left <= 0:
                    raise asyncio.TimeoutError
                await asyncio.wait((future,), timeout=min(left, NODE_CLOSED_POLL))
                if not future.done():
                    self._check_open()
            return future.result()
        finally:
            _abandon(future)

    async def _call_cyclone(self, pair: _Pair, message: IdlStruct, deadline: float,
                            participant: bytes | None = None) -> IdlStruct:
        loop = asyncio.get_running_loop()
        seq = next(self._seq)
        future: asyncio.Future[IdlStruct] = loop.create_future()
        self._pending[seq] = future
        if participant is not None:
            self._pending_from[seq] = participant
        try:
            pair.write(message, cyclone.RequestHeader(pair.guid, seq))
            return await self._reply(future, deadline)
        except asyncio.TimeoutError:
            raise ServiceTimeout(f"service {self.name}: no reply within the timeout") from None
        finally:
            self._pending.pop(seq, None)
            self._pending_from.pop(seq, None)

    async def _call_plain(self, pair: _Pair, message: IdlStruct, deadline: float,
                          accept: Accept | None, unidentified_ok: bool,
                          participant: bytes | None = None) -> Answer:
        loop = asyncio.get_running_loop()
        try:
            await asyncio.wait_for(self._plain_lock.acquire(), max(0.0, deadline - loop.time()))
        except asyncio.TimeoutError:
            raise ServiceTimeout(f"service {self.name}: still queued behind earlier requests "
                                 "(one request at a time with a Fast DDS server)") from None
        try:
            if self._stale:  # let a late reply to a timed-out request arrive and be dropped
                await asyncio.sleep(max(0.0, min(STALE_REPLY_GRACE, deadline - loop.time())))
                self._stale = False
            self._check_open()  # closed while this call was queued
            return await self._send_plain(pair, message, deadline, accept, unidentified_ok,
                                          participant)
        finally:
            self._plain_waiter = None
            self._plain_lock.release()

    async def _send_plain(self, pair: _Pair, message: IdlStruct, deadline: float,
                          accept: Accept | None, unidentified_ok: bool,
                          participant: bytes | None = None) -> Answer:
        """Sends the request and waits for its reply: from the reader, or, if the reader
        never delivers it, from the packet capture (`_reply_from_capture`)."""
        future: asyncio.Future[IdlStruct] = asyncio.get_running_loop().create_future()
        identity = SampleIdentity(pair.writer_guid, pair.written + 1)
        # Never under DDS-Security (fails closed): the capture sees only what travels in
        # clear, so all it could take is a plaintext DATA Cyclone refuses from a protected
        # writer — a forged reply.
        capture = None if self.node.secured else self.node.identities
        # Before the request goes out, so that its reply is in what the capture has not read.
        captured = capture is not None and capture.expect_reply(
            identity, [w for w in matched_writers(pair.reader).values()
                       if participant is None or participant_prefix(w) == participant])
        fallback = None
        alone = unidentified_ok or not self._other_clients(pair)
        try:
            pair.write(message)
            waiter = self._plain_waiter = _Outstanding(future, accept, identity,
                                                       unidentified_ok, alone, participant)
            if captured:
                assert capture is not None
                fallback = asyncio.create_task(
                    self._reply_from_capture(pair, capture, waiter))
            reply = await self._reply(future, deadline)
            return Answer(reply, waiter.tied, pair.writer_guids.of_sample(reply))
        except asyncio.TimeoutError:
            self._stale = True
            raise ServiceTimeout(f"service {self.name}: no reply within the timeout") from None
        except (AmbiguousReply, asyncio.CancelledError):
            self._stale = True  # ours may still come: it must not answer the next request
            raise
        finally:
            if fallback is not None:
                fallback.cancel()
            if captured:
                assert capture is not None
                capture.forget_reply(identity)

    async def _reply_from_capture(self, pair: _Pair, capture: IdentityCapture,
                                  waiter: _Outstanding) -> None:
        """Delivers the reply from the packet capture when the reader has not: its DATA
        reached our socket, but Cyclone dropped it as history (a HEARTBEAT ahead of it taken
        as our reader's start: docs/design/zero-loss.md), and nothing sends it again. Only
        the reply naming our request exactly, from a reply writer matched with our reader
        (`IdentityCapture.expect_reply`); the reader gets its turn first (CAPTURE_REPLY_AFTER,
        CAPTURE_SETTLE, then the reader thread's barrier), and whichever delivers first wins.
        Each look runs in a worker thread: one that misses reads the capture to its end, up to
        MISS_BUDGET bytes, which held the event loop 250-440 ms when they were small datagrams
        (docs/design/rpc-identity.md, "The event loop"); the capture's lock is taken a chunk
        at a time there, and no lock of ours is held meanwhile."""
        future = waiter.future
        await asyncio.sleep(CAPTURE_REPLY_AFTER)
        while not future.done():
            data = await asyncio.to_thread(capture.captured_reply, waiter.identity)
            if data is not None:
                await asyncio.sleep(CAPTURE_SETTLE)  # it may just have come: reader first
                await self.node.delivered()
                if not future.done():
                    self._deliver_captured(pair, data, waiter)
                return
            await asyncio.sleep(CAPTURE_POLL)

    def _deliver_captured(self, pair: _Pair, data: bytes, waiter: _Outstanding) -> None:
        """A reply the capture kept because it names our request (never on a secured node):
        tied to it, so ours whatever the caller's `accept` says (`call`)."""
        future = waiter.future
        try:
            reply: Any = self.node.codecs.of(self.response_type).prepare_decoder().decode(data)
        except Exception as exc:  # bad input from the wire: said, not raised
            log.warning("service %s: our reply, found in the packet capture, does not "
                        "decode: %s", self.name, exc)
            return
        reply.sample_info = None  # (not taken from a reader)
        pair.from_capture += 1
        log.info("service %s: our reply reached our socket but not our reader (dropped as "
                 "history); taken from the packet capture", self.name)
        waiter.tied = True
        future.set_result(reply)

    def _deliver(self, pair: _Pair, samples: list[Any]) -> None:
        for sample in samples:
            if pair.mapping is RequestMapping.CYCLONE:
                header, reply = sample.header, sample.payload
                future = self._pending.get(header.seq) \
                    if header.client_guid == pair.guid else None
                if future is not None and not future.done() and not self._from_elsewhere(
                        pair, sample, self._pending_from.get(header.seq)):
                    reply.sample_info = sample.sample_info  # (its writer: `Answer.writer`)
                    future.set_result(reply)
                else:  # another client's reply, one we gave up on, or another server's
                    # (`from_participant`): never ours
                    self.dropped_replies += 1
                continue
            waiter = self._plain_waiter
            if waiter is None or waiter.future.done():
                self.dropped_replies += 1
                continue
            related = pair.related_identity(sample)
            # (read from the clear: not what a secured node trusts, see `Answer`)
            tied = related is not None and not self.node.secured
            if (related is not None and related != waiter.identity) or \
                    self._from_elsewhere(pair, sample, waiter.participant) or \
                    (not tied and not waiter.accepts(sample)):
                self.dropped_replies += 1  # names another request, or the caller refused it
                continue
            if related is None and not waiter.unidentified_ok and \
                    (not waiter.alone or self._other_clients(pair)):
                self.dropped_replies += 1
                waiter.future.set_exception(self._ambiguous())
                continue
            waiter.tied = tied
            waiter.future.set_result(sample)

    def _ambiguous(self) -> AmbiguousReply:
        node = self.node
        why = ("the traffic is encrypted (DDS-Security)" if node.secured else
               "the packet capture is off (RCAN_RTPS_RPC_IDENTITY=off)"
               if node.identities is None else "its datagram was not in the packet capture")
        return AmbiguousReply(
            f"service {self.name}: a reply came that cannot be told from another client's "
            f"(the server names the request a reply answers only in RTPS inline QoS, and "
            f"{why}) while other clients of the service are in the graph: not taken as ours "
            "(ambiguous_reply); the call may be made again")

    def close(self) -> None:
        """Deletes the endpoints; calls still waiting fail with ServiceUnavailable.
        Idempotent."""
        if self.closed:
            return
        self.closed = True
        waiting = [*self._pending.values(), *([self._plain_waiter.future]
                                               if self._plain_waiter else [])]
        for future in waiting:
            if not future.done():
                future.set_exception(ServiceUnavailable(f"the client of {self.name} closed"))
        for mapping, pair in self._pairs.items():
            pair.close()
            if mapping is RequestMapping.FASTDDS and self.node.identities is not None:
                self.node.identities.unuse()


def _abandon(future: asyncio.Future[Any]) -> None:
    """A reply's future its call no longer waits for (timed out, cancelled, or done): one
    still pending is cancelled, so nothing fails it later, and an exception it holds is
    retrieved. A call cancelled as its client closes (an action client's close cancels its
    take-back calls, then closes their client) left one failed by the close and logged,
    when collected, as an exception never retrieved."""
    if not future.done():
        future.cancel()
    elif not future.cancelled():
        future.exception()


def __getattr__(name: str) -> Any:
    """`ServiceServer`, from its own module (`service_server`) on first use: a bridge only
    calls services, and never loads the server side (issue 27, idle memory)."""
    if name == "ServiceServer":
        from .service_server import ServiceServer

        return ServiceServer
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
