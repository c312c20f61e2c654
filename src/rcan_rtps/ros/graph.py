"""The ROS graph as seen from DDS discovery: topics, nodes, services, actions.

Endpoints come from the builtin publication/subscription topics (name, type, QoS,
USER_DATA type hash, vendor from the GUID prefix); nodes and the endpoint → node
mapping come from other participants' `ros_discovery_info`.

Any peer may write ros_discovery_info, and cyclonedds' reader does not keep the bounds of
its IDL (`string<256>` for a node's namespace and name): a name is cut to that bound where
the sample is read (`bound_node_name`), so every view — `node list`, `node info`, `topic
info`, the bridge's other publishers — shows at most it.

Any peer may also make and delete endpoints (or whole participants) faster than a refresh
reads their discovery samples (~150 µs each, in Python), and a refresh runs on the caller's
event loop (the bridge's commander watch, a service call, a stop's goal cancel): it takes at
most REFRESH_TAKE samples of each builtin reader and says whether it caught up (`refresh`
returns False while more wait), so that no flood holds the loop for as long as it lasts.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import time
import weakref
from collections import Counter
from collections.abc import Callable, Hashable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import msgspec
from cyclonedds.builtin import (
    BuiltinDataReader,
    BuiltinTopicDcpsParticipant,
    BuiltinTopicDcpsPublication,
    BuiltinTopicDcpsSubscription,
)
from cyclonedds.core import DDSException, InstanceState

from . import qos as qos_mod
from .info_inbox import MAX_INFO_BYTES, InfoInbox
from .names import EndpointKind, action_of, demangle, is_hidden, mangle_topic
from .participant import DISCOVERY_TYPE, RosNode
from .qos import QosProfile
from .readers import BAD_LOG_S, Watch
from .typesys.store import normalize_name

log = logging.getLogger(__name__)

# ros_discovery_info entries kept for participants discovery has not (yet) announced: any peer
# may write any gid there, so what names no live participant is bounded, then let go. They
# share a budget of bytes as well as a count (an info may be up to MAX_INFO_BYTES, and its
# decoded objects ~4 times that, kept while it is).
MAX_UNKNOWN_INFOS = 256
MAX_UNKNOWN_INFO_BYTES = 8 << 20
# ros_discovery_info bytes one refresh decodes, about: decoding is ~150 ms of Python a MiB of
# gids, on the caller's loop, and a peer may rewrite an info near MAX_INFO_BYTES as often as
# it likes (each one read again). Past this a refresh stops and says it is behind
# (`refresh`), so the loop gets a turn between ~2 MiB of decoding and the next.
INFO_BYTES_TAKE = MAX_INFO_BYTES
# Discovery samples one refresh takes from each builtin reader at most. A refresh took every
# waiting sample, and while a peer churning endpoints wrote them faster than they were read,
# it went on taking: 11 s on the event loop for two peers each making 2,000 writers and
# leaving, round after round (red team 32), the bridge's e-stop unanswered meanwhile. What is
# left waits in the reader (Cyclone keeps one sample per endpoint) for the next refresh;
# ~150 ms of work at most per reader.
REFRESH_TAKE = 1024
# ros_discovery_info writers whose participant is remembered before the table starts anew.
WRITERS_KNOWN = 4096
# Distinct QoS profiles, and topic and type names, kept before those no endpoint uses are
# let go of (`KeptOnce`).
PROFILES_KEPT = 64
TEXTS_KEPT = 1024
# Departures kept (`left_at`): those older than DEPARTURES_KEPT_S go once the table doubled
# past DEPARTURES_BOUND, so a peer churning ever new topics cannot grow it for good.
DEPARTURES_BOUND = 256
DEPARTURES_KEPT_S = 120.0
# ros_discovery_info's IDL bound for a node's namespace and for its name, each.
MAX_INFO_NAME = 256
# A node's fully qualified name made of two names at that bound (`node_fqn`).
MAX_NODE_FQN = 2 * MAX_INFO_NAME + 1

VENDORS = {
    b"\x01\x01": "RTI Connext DDS",
    b"\x01\x03": "OpenDDS",
    b"\x01\x0f": "eProsima Fast DDS",
    b"\x01\x10": "Eclipse Cyclone DDS",
    b"\x01\x12": "RTI Connext Micro",
    b"\x01\x0a": "GurumNetworks GurumDDS",
}


class Direction(enum.Enum):
    PUBLISHER = "PUBLISHER"
    SUBSCRIPTION = "SUBSCRIPTION"


@dataclass(frozen=True)
class Endpoint:
    direction: Direction
    kind: EndpointKind
    ros_name: str
    ros_type: str
    dds_topic: str
    dds_type: str
    gid: bytes
    participant_gid: bytes
    qos: QosProfile
    type_hash: str
    vendor: str
    node_name: str = "_NODE_NAME_UNKNOWN_"
    node_namespace: str = "_NODE_NAMESPACE_UNKNOWN_"
    # rmw_cyclonedds' `serviceid=`/`clientid=` of a service endpoint: the mark of its
    # request-reply mapping that survives DDS-Security (which rewrites the GUID's vendor bytes)
    service_id: str = ""
    # Who governs this endpoint, when its USER_DATA says (`RosNode.governed_by`): a writer
    # the robot obeys, or a reader of a governed action's status.
    governed_by: str = ""


class _Node(msgspec.Struct, frozen=True):
    """A node a participant's ros_discovery_info announces: its names (bounded). With the
    info's endpoint index (`_Info`), what the views use of the sample, not the decoded one."""

    namespace: str
    name: str


class _Info(msgspec.Struct, frozen=True):
    """A participant's ros_discovery_info as the views use it: its nodes, and the node of each
    endpoint gid it names — indexed once, when the sample is read. A view that walked every
    gid of every info to name a few endpoints cost ~550 ms per call with eight peers each
    announcing 120,000 made-up gids (within MAX_INFO_BYTES), and services and actions call
    one before each call, a stop's goal cancel included (red team 32)."""

    nodes: tuple[_Node, ...]
    owners: dict[bytes, _Node]


class _Seen(msgspec.Struct, frozen=True):
    """What the views need of a discovered endpoint, taken from its builtin sample when it
    arrives. The sample itself (its `Qos` a dict of policy objects, ~2 kB) is not kept: a
    graph holds one per endpoint of the domain, its own included, for as long as it lives."""

    direction: Direction
    topic_name: str
    type_name: str
    participant: bytes
    qos: QosProfile  # one object per distinct profile (`RosGraph._profiles`)
    type_hash: str
    service_id: str
    governed_by: str


def vendor_of(gid: bytes) -> str:
    return VENDORS.get(gid[:2], f"unknown vendor {gid[:2].hex('.')}")


def ros_type_of(dds_type: str, kind: EndpointKind) -> str:
    name = normalize_name(dds_type)
    if kind is EndpointKind.REQUEST and name.endswith("_Request"):
        return name[: -len("_Request")]
    if kind is EndpointKind.REPLY and name.endswith("_Response"):
        return name[: -len("_Response")]
    return name


K = TypeVar("K", bound=Hashable)


class KeptOnce(Generic[K]):
    """One object kept for each distinct value (`one`), so that equal values a graph's
    endpoints share are one object. Past `bound` values the table is rebuilt from those
    `in_use()` still names, and its bound doubles what is in use (a rebuild costs one pass
    per as many new values)."""

    def __init__(self, bound: int, in_use: Callable[[], Iterable[K]]) -> None:
        self._kept: dict[K, K] = {}
        self._least = self._bound = bound
        self._in_use = in_use

    def one(self, value: K) -> K:
        kept = self._kept.get(value)
        if kept is not None:
            return kept
        if len(self._kept) >= self._bound:
            self._kept = {v: v for v in self._in_use()}
            self._bound = max(self._least, 2 * len(self._kept))
        self._kept[value] = value
        return value

    def __len__(self) -> int:
        return len(self._kept)


class RosGraph:
    """A live view of the graph, kept current by reading DDS discovery data."""

    def __init__(self, node: RosNode) -> None:
        self.node = node
        self._pubs = BuiltinDataReader(node.participant, BuiltinTopicDcpsPublication)
        self._subs = BuiltinDataReader(node.participant, BuiltinTopicDcpsSubscription)
        self._participants = BuiltinDataReader(node.participant, BuiltinTopicDcpsParticipant)
        self._info = node.discovery_reader()
        # (taken as it arrives by the node's reader thread, its size looked at first)
        self._inbox = InfoInbox(self._participant_of)
        # writer handle → its participant's GUID prefix (the reader thread's alone)
        self._writer_participants: dict[int, bytes] = {}
        self._info_watch = node.reader_thread.add(
            Watch(self._info, self._inbox.arrived, "ros_discovery_info", raw=True))
        self._decode_info = node.codecs.of(DISCOVERY_TYPE).prepare_decoder().decode
        self._endpoints: dict[bytes, _Seen] = {}
        # Discovered QoS profiles, and topic and type names, each kept once: a graph's
        # endpoints share a handful. Those no endpoint uses any more are let go of once a
        # table doubled: a peer making endpoints of ever new QoS (a deadline per run) or
        # names must not grow it for good. (Not `sys.intern`: any peer chooses the names,
        # and CPython 3.12.0-3.12.5 never frees an interned string, cpython#113993.)
        self._profiles = KeptOnce(PROFILES_KEPT, self._profiles_in_use)
        self._texts = KeptOnce(TEXTS_KEPT, self._texts_in_use)
        self._node_infos: dict[bytes, _Info] = {}
        self._info_sizes: dict[bytes, int] = {}  # bytes of each kept info's sample
        self._alive: set[bytes] = set()  # participants discovery knows (this one included)
        self.bad_infos = 0  # ros_discovery_info samples that did not decode (dropped)
        self.large_infos = 0  # and those larger than MAX_INFO_BYTES (dropped undecoded)
        self.dropped_infos = 0  # and those dropped waiting for a refresh (InfoInbox's bounds)
        # (DDS topic, direction) -> monotonic time an endpoint of it was last seen leaving
        # (`left_at`), oldest first
        self._left_at: dict[tuple[str, Direction], float] = {}
        self._departures_bound = DEPARTURES_BOUND
        # monotonic time each kind of those was last logged: at most one per BAD_LOG_S
        self._dropped_logged_at: dict[str, float] = {}
        # Grows whenever a refresh took anything: a view computed at one generation is
        # still current while it has not moved.
        self.generation = 0

    def close(self) -> None:
        """Deletes the graph's readers; idempotent. A graph let go of without it keeps them
        for as long as the collector has not found their cycle (each builtin reader and its
        read condition refer to each other), for good once `gc.freeze()` (`run`) froze
        them: unread, each kept every participant and endpoint that came and went after
        (~2 kB each, for as long as the process runs)."""
        with contextlib.suppress(DDSException):  # (the node's thread closed first)
            self.node.reader_thread.remove(self._info_watch)
        for reader in (self._pubs, self._subs, self._participants, self._info):
            with contextlib.suppress(DDSException):
                reader.__del__()

    def _participant_of(self, handle: int) -> bytes:
        """The participant (GUID prefix) of a ros_discovery_info writer, by the handle its
        samples name it by; b"" once it is no longer matched. On the node's reader thread
        (InfoInbox), with no lock of ours held: a DDS call that calls back into no Python."""
        known = self._writer_participants.get(handle)
        if known is None:
            try:
                data = self._info.get_matched_publication_data(handle)
            except Exception:  # (no longer matched, the reader deleted: never the sample lost)
                data = None
            known = b"" if data is None else bytes(data.participant_key.bytes)[:12]
            if len(self._writer_participants) >= WRITERS_KNOWN:  # (writers that left)
                self._writer_participants.clear()
            self._writer_participants[handle] = known
        return known

    def refresh(self) -> bool:
        """Takes what discovery changed since the last refresh, REFRESH_TAKE samples of each
        reader at most: True when it took all there was, False when more is waiting (a flood
        of discovery: call again, after giving the loop a turn)."""
        taken, caught_up = 0, True
        for direction, reader in ((Direction.PUBLISHER, self._pubs),
                                  (Direction.SUBSCRIPTION, self._subs)):
            endpoints = 0
            for sample in _take_all(reader):
                endpoints += 1
                key = sample.key.bytes
                if sample.sample_info.instance_state == InstanceState.Alive:
                    self._endpoints[key] = self._seen(direction, sample)
                else:
                    gone = self._endpoints.pop(key, None)
                    # One never seen alive (it came and went between two refreshes: the
                    # reader keeps an endpoint's last sample) left all the same; its
                    # disposal names its topic.
                    topic = gone.topic_name if gone is not None else \
                        getattr(sample, "topic_name", None)
                    if isinstance(topic, str) and topic:
                        self._note_left(topic, direction)
            taken += endpoints
            caught_up &= endpoints < REFRESH_TAKE
        # Participants before their nodes: an info is kept by its participant being alive.
        # ros_discovery_info is keyless: a participant that leaves leaves its last sample
        # behind while any other writer remains. Its nodes go with it, as in rmw's graph.
        participants = 0
        for participant in _take_all(self._participants):
            participants += 1
            key = participant.key.bytes
            if participant.sample_info.instance_state == InstanceState.Alive:
                self._alive.add(key)
            else:
                self._alive.discard(key)
                self._forget_info(key)
        infos, infos_caught_up = self._take_node_infos()
        taken += participants + infos
        if taken:
            self.generation += 1
        return caught_up and participants < REFRESH_TAKE and infos_caught_up

    def _seen(self, direction: Direction, sample: Any) -> _Seen:
        user_data = qos_mod.user_data_of(sample.qos)
        profile = qos_mod.from_dds(sample.qos)
        text = self._texts.one
        return _Seen(direction, text(sample.topic_name), text(sample.type_name),
                     sample.participant_key.bytes, self._profiles.one(profile),
                     user_data.get("typehash", ""),
                     user_data.get("serviceid") or user_data.get("clientid") or "",
                     text(user_data.get(qos_mod.GOVERNED_BY, "")))

    def _note_left(self, topic: str, direction: Direction) -> None:
        now = time.monotonic()
        where = (self._texts.one(topic), direction)
        self._left_at.pop(where, None)  # (re-inserted last: the table stays oldest first)
        self._left_at[where] = now
        if len(self._left_at) > self._departures_bound:
            self._left_at = {k: at for k, at in self._left_at.items()
                             if now - at < DEPARTURES_KEPT_S}
            self._departures_bound = max(DEPARTURES_BOUND, 2 * len(self._left_at))

    def left_at(self, dds_topic: str, direction: Direction) -> float | None:
        """When (time.monotonic) an endpoint on this DDS topic in this direction was last seen
        leaving the graph, by any refresh (whoever refreshed, whether or not anyone was
        looking at that topic then); None if none was in the last DEPARTURES_KEPT_S at least.
        A service client that came and went between two calls of ours left this behind."""
        return self._left_at.get((dds_topic, direction))

    def _profiles_in_use(self) -> Iterator[QosProfile]:
        return (seen.qos for seen in self._endpoints.values())

    def _texts_in_use(self) -> Iterator[str]:
        for seen in self._endpoints.values():
            yield from (seen.topic_name, seen.type_name, seen.governed_by)
        for topic, _ in self._left_at:
            yield topic

    def _take_node_infos(self) -> tuple[int, bool]:
        """Each participant's nodes from ros_discovery_info: (how many infos were taken,
        whether all waiting were). The infos that arrived since the last refresh, the newest
        per participant (`InfoInbox`), until about INFO_BYTES_TAKE were decoded. Any peer
        may write there: an info that does not decode is dropped alone, and never fails the
        refresh (services and actions refresh before each call, a stop's goal cancel
        included)."""
        bad = 0
        arrivals, drained = self._inbox.take(INFO_BYTES_TAKE)
        for raw_gid, arrived in arrivals:
            if arrived.data is None:
                # Past the size bound (or dropped waiting): the info it replaces is stale.
                self._forget_info(raw_gid)
                continue
            try:
                info: Any = self._decode_info(arrived.data)
                gid = bytes(info.gid.data)[:16]
                read = _info_of(info)
            except Exception:
                bad += 1
                continue
            if arrived.alive:
                self._node_infos.pop(gid, None)  # re-inserted: the newest last
                self._node_infos[gid], self._info_sizes[gid] = read, len(arrived.data)
            else:
                self._forget_info(gid)
        self._report_dropped(bad)
        self._bound_unknown_infos()
        return len(arrivals), drained

    def _report_dropped(self, bad: int) -> None:
        """Counts the samples dropped; a peer may write them as often as we refresh (before
        each call, at each poll): each kind is logged at most once per BAD_LOG_S."""
        self.bad_infos += bad
        large, self.large_infos = self._inbox.large - self.large_infos, self._inbox.large
        dropped, self.dropped_infos = \
            self._inbox.dropped - self.dropped_infos, self._inbox.dropped
        if bad and self._may_log("bad"):
            log.warning("dropped ros_discovery_info sample(s) that do not decode (%d so far; "
                        "logged at most every %.0f s)", self.bad_infos, BAD_LOG_S)
        if large and self._may_log("large"):
            log.warning("dropped ros_discovery_info sample(s) larger than %d bytes, "
                        "undecoded: their participants' nodes are not shown (%d so far; "
                        "logged at most every %.0f s)", MAX_INFO_BYTES, self.large_infos,
                        BAD_LOG_S)
        if dropped and self._may_log("dropped"):
            log.warning("dropped ros_discovery_info sample(s) arriving faster than they were "
                        "read (%d so far; logged at most every %.0f s)", self.dropped_infos,
                        BAD_LOG_S)

    def _may_log(self, kind: str) -> bool:
        now, last = time.monotonic(), self._dropped_logged_at.get(kind)
        if last is not None and now - last < BAD_LOG_S:
            return False
        self._dropped_logged_at[kind] = now
        return True

    def _forget_info(self, gid: bytes) -> None:
        self._node_infos.pop(gid, None)
        self._info_sizes.pop(gid, None)

    def _bound_unknown_infos(self) -> None:
        """An info may come before its participant is discovered, so one naming no live
        participant is kept (never listed) — but only so many, and so many bytes: ids that
        never match a participant (a peer writing made-up gids) would otherwise pile up for
        good. The oldest go first."""
        unknown = [gid for gid in self._node_infos if gid not in self._alive]
        size = sum(self._info_sizes.get(gid, 0) for gid in unknown)
        for n, gid in enumerate(unknown):
            if len(unknown) - n <= MAX_UNKNOWN_INFOS and size <= MAX_UNKNOWN_INFO_BYTES:
                break
            size -= self._info_sizes.get(gid, 0)
            self._forget_info(gid)

    def _live_infos(self) -> list[tuple[_Node, ...]]:
        return [info.nodes for gid, info in self._node_infos.items() if gid in self._alive]

    async def settle(self, seconds: float = 1.0, patience: float = 4.0) -> None:
        """Lets discovery run for `seconds`, then up to `patience` more until the graph has
        read all waiting discovery and every participant with ROS endpoints has announced
        its nodes. Fast DDS hands its
        latched ros_discovery_info to a late reader only on its next heartbeat (3 s)."""
        loop = asyncio.get_running_loop()
        start = loop.time()
        while True:
            caught_up = self.refresh()  # (False: more discovery waits, a big graph's or a flood's)
            elapsed = loop.time() - start
            if elapsed >= seconds + patience or \
                    (elapsed >= seconds and caught_up and not self._unannounced()):
                return
            await asyncio.sleep(0.1)

    def _unannounced(self) -> set[bytes]:
        ros_participants = {seen.participant for seen in self._endpoints.values()
                            if demangle(seen.topic_name) is not None}
        return ros_participants - set(self._node_infos)

    # -- views -----------------------------------------------------------------
    def _owner(self, participant: bytes, endpoint: bytes) -> _Node | None:
        """The node of `endpoint`, looked for in its own participant's info only (as rmw's
        graph cache does): another peer's info cannot claim it. A lookup, whatever the size
        of the infos."""
        info = self._node_infos.get(participant)
        if info is None or participant not in self._alive:
            return None
        return info.owners.get(endpoint)

    def endpoints(self) -> list[Endpoint]:
        return self._described(self._endpoints.items())

    def publishers_on(self, topics: set[str]) -> list[Endpoint]:
        """The publishers of these ROS topics (fully qualified names), of any participant.
        Costs a set lookup per endpoint of the graph; only theirs are described."""
        wanted = {mangle_topic(t) for t in topics}
        chosen = [(key, seen) for key, seen in self._endpoints.items()
                  if seen.direction is Direction.PUBLISHER and seen.topic_name in wanted]
        return self._described(chosen)

    def gids_on(self, dds_topic: str, direction: Direction) -> set[bytes]:
        """The GUIDs of the endpoints on this DDS topic in this direction (none described:
        a set lookup per endpoint of the graph)."""
        return {key for key, seen in self._endpoints.items()
                if seen.direction is direction and seen.topic_name == dds_topic}

    def _described(self, chosen: Iterable[tuple[bytes, _Seen]]) -> list[Endpoint]:
        found = []
        for key, seen in chosen:
            mangled = demangle(seen.topic_name)
            if mangled is None:
                continue
            node = self._owner(seen.participant, key)
            namespace, name = (node.namespace, node.name) if node is not None else \
                ("_NODE_NAMESPACE_UNKNOWN_", "_NODE_NAME_UNKNOWN_")
            found.append(Endpoint(
                seen.direction, mangled.kind, mangled.name,
                ros_type_of(seen.type_name, mangled.kind), seen.topic_name,
                seen.type_name, key, seen.participant, seen.qos, seen.type_hash,
                vendor_of(key), name, namespace, seen.service_id, seen.governed_by,
            ))
        return sorted(found, key=lambda e: (e.ros_name, e.direction.value, e.node_name))

    def topics(self, include_hidden: bool = False) -> dict[str, list[str]]:
        topics: dict[str, set[str]] = {}
        for e in self.endpoints():
            if e.kind is not EndpointKind.TOPIC:
                continue
            if not include_hidden and is_hidden(e.ros_name):
                continue
            topics.setdefault(e.ros_name, set()).add(e.ros_type)
        return {name: sorted(types) for name, types in sorted(topics.items())}

    def topic_endpoints(self, topic: str) -> list[Endpoint]:
        return [e for e in self.endpoints()
                if e.kind is EndpointKind.TOPIC and e.ros_name == topic]

    def services(self, include_hidden: bool = False) -> dict[str, list[str]]:
        services: dict[str, set[str]] = {}
        for e in self.endpoints():
            if e.kind is EndpointKind.REQUEST and (include_hidden or not is_hidden(e.ros_name)):
                services.setdefault(e.ros_name, set()).add(e.ros_type)
        return {name: sorted(types) for name, types in sorted(services.items())}

    def actions(self) -> dict[str, list[str]]:
        actions: dict[str, set[str]] = {}
        for e in self.endpoints():
            member = action_of(e.ros_name)
            if member and member[1] == "send_goal" and e.kind is EndpointKind.REQUEST:
                actions.setdefault(member[0], set()).add(
                    e.ros_type.removesuffix("_SendGoal"))
        return {name: sorted(types) for name, types in sorted(actions.items())}

    def nodes(self) -> list[tuple[str, str]]:
        """(namespace, name) of every node announced by a participant discovery knows
        alive, another or this one (an info naming no such participant names no node)."""
        found = {(n.namespace, n.name) for nodes in self._live_infos() for n in nodes}
        return sorted(found)

    def nodes_sharing_a_name(self) -> list[tuple[str, str]]:
        """(namespace, name) of every name more than one live node announces (two processes
        started under one name): the graph, services and parameters cannot tell them apart."""
        announced = Counter((n.namespace, n.name) for nodes in self._live_infos() for n in nodes)
        return sorted(name for name, count in announced.items() if count > 1)


def _take_all(reader: BuiltinDataReader, batch: int = 256,
              limit: int | None = None) -> Iterator[Any]:
    """The samples waiting, up to `limit` (REFRESH_TAKE), a batch at a time: the binding sizes
    its buffers by the count asked for, so one take of 100,000 cost ~0.6 ms even with nothing
    to take (a refresh polled each second on a quiet graph paid that thrice)."""
    limit = REFRESH_TAKE if limit is None else limit
    taken = 0
    while taken < limit:
        samples = reader.take(N=min(batch, limit - taken))
        yield from samples
        taken += len(samples)
        if len(samples) < batch:
            return


def bound_node_name(text: str) -> str:
    """A namespace or node name as ros_discovery_info's IDL bounds it: itself, or its first
    characters and how many more there were — which no valid name holds, so a cut name never
    equals one declared (expected publishers)."""
    if len(text) <= MAX_INFO_NAME:
        return text
    more = f"… (+{len(text) - MAX_INFO_NAME} chars)"
    return text[:MAX_INFO_NAME - len(more)] + more


def _info_of(info: Any) -> _Info:
    nodes, owners = [], {}
    for n in info.node_entities_info_seq:
        node = _Node(bound_node_name(n.node_namespace), bound_node_name(n.node_name))
        nodes.append(node)
        for g in (*n.reader_gid_seq, *n.writer_gid_seq):
            owners[bytes(g.data)[:16]] = node  # a gid two nodes name: the later one's
    return _Info(tuple(nodes), owners)


def node_fqn(namespace: str, name: str) -> str:
    return f"{namespace.rstrip('/')}/{name}"


def short_gid(gid: bytes) -> str:
    return ".".join(f"{b:02x}" for b in gid)


# One discovery view per node, shared by its service and action clients and the bridge's
# commander watch (which reads it even when no call is made: its readers never fill up).
_graphs: weakref.WeakKeyDictionary[RosNode, RosGraph] = weakref.WeakKeyDictionary()


def shared_graph(node: RosNode) -> RosGraph:
    """One discovery view per node, shared by its clients."""
    graph = _graphs.get(node)
    if graph is None:
        graph = _graphs[node] = RosGraph(node)
    return graph
