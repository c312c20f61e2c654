"""A ROS 2 node made of plain DDS: one participant, its endpoints and its graph presence.

The node announces itself on `ros_discovery_info` (so `ros2 node list` and rclpy's
graph API see it), tags the participant `enclave=/;` and every endpoint with its
`typehash=` (Jazzy and later). Subscriptions are read by one thread per node that waits
on a DDS WaitSet (see `readers.py`: never a Cyclone listener, which deadlocked against the
GIL) and deliver to asyncio or to a callback run on that thread. Discovery is loopback-only
when asked by flag or by the ROS environment variables.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
from collections.abc import AsyncIterator, Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

from cyclonedds.core import DDSException, Policy
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.pub import DataWriter, Publisher
from cyclonedds.qos import Qos
from cyclonedds.sub import DataReader, Subscriber
from cyclonedds.topic import Topic

from . import qos as qos_mod
from . import raw_cdr
from .errors import CdrDecodeError, GraphTimeout, SampleTooLarge, WireError, seconds
from .names import expand_topic_name, mangle_topic, normalize_namespace, validate_node_name
from .qos import GOVERNED_BY, QosProfile
from .readers import Decode, ReaderThread, Watch, WriterWatch
from .rtps_capture import IdentityCapture, capture_supported
from .sample_size import SampleBound, bound_in_force, past_bound, refused_for_size
from .typesys.cdr import CdrCodecs
from .typesys.ddstypes import DdsTypes, make_topic
from .typesys.store import TypeStore, env_idl_paths
from .typesys.values import MessageValues
from .udp_drops import dropped_at, made_between, udp_socket_inodes

log = logging.getLogger(__name__)

DISCOVERY_TOPIC = "ros_discovery_info"
DISCOVERY_TYPE = "rmw_dds_common/msg/ParticipantEntitiesInfo"
# The peer by address, not name: Cyclone aborts the process when a peer name does not
# resolve (a container without /etc/hosts), and loopback discovery needs no resolver.
_LOCALHOST_CONFIG = """<CycloneDDS><Domain Id="any"><General>
<Interfaces><NetworkInterface address="127.0.0.1" multicast="false"/></Interfaces>
<AllowMulticast>false</AllowMulticast></General>
<Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>32</MaxAutoParticipantIndex>
<Peers><Peer address="127.0.0.1"/></Peers></Discovery></Domain></CycloneDDS>"""
# ROS matches endpoints by type name (the hash travels in USER_DATA), never by XTypes. Fast DDS 3
# (Kilted) sends type objects Cyclone rejects, which left every endpoint with a sequence of
# strings or structs unmatched; so type information from Fast DDS (vendor 1.15) is ignored.
_COMPAT_CONFIG = """<CycloneDDS><Domain Id="any"><Compatibility>
<IgnoreTypeInformation>1.15</IgnoreTypeInformation></Compatibility></Domain></CycloneDDS>"""

# A reader that asked for a lost sample asks again after AutoReschedNackDelay (Cyclone's
# default 3 s) unless the writer's next HEARTBEAT comes first (Fast DDS's: 3 s as well), so a
# repair dropped at our socket again came only 3 s later each time: a first feedback 5-18 s
# after its goal's end, past the repair window (docs/design/zero-loss.md, "Repairs dropped
# again"). Asking again every 100 ms (Cyclone's NackDelay, the least it honours) costs an
# ACKNACK per missing sample's writer per 100 ms, only while a sample is owed. Put before the
# user's CYCLONEDDS_URI, which may override it.
_REPAIR_CONFIG = """<CycloneDDS><Domain Id="any"><Internal>
<AutoReschedNackDelay>100 ms</AutoReschedNackDelay></Internal></Domain></CycloneDDS>"""

# The largest sample (CDR bytes) Cyclone takes in or sends, by default. Any peer on the domain
# may write a sample of any size to a topic we read: Cyclone reassembled it whole before any
# code of ours could look at it (one 50 MB ros_discovery_info sample peaked the process at
# +100 MB; a 1 GB one would take a robot computer's memory). Past it, Cyclone drops the sample
# with a warning as it arrives. Above what ROS sends: a 4K rgb8 Image is 25 MB, a 10,000²
# OccupancyGrid 100 MB. A node or the user's CYCLONEDDS_URI (`<Internal><MaxSampleSize>`)
# may set another.
DEFAULT_MAX_SAMPLE_BYTES = 256 << 20


def _limits_config(max_sample_bytes: int) -> str:
    return ('<CycloneDDS><Domain Id="any"><Internal>'
            f"<MaxSampleSize>{max_sample_bytes}B</MaxSampleSize>"
            "</Internal></Domain></CycloneDDS>")


_domains: dict[int, tuple[Domain, int]] = {}  # domain id → (configured domain, nodes using it)
_domain_bounds: dict[int, SampleBound] = {}  # domain id → its bound on sample size in force
_domains_lock = threading.Lock()
# Per domain: Cyclone's packet capture, read for the request identity in Fast DDS replies
# (rtps_capture.py). RCAN_RTPS_RPC_IDENTITY=off leaves it out; RCAN_RTPS_CAPTURE_DIR says
# where its file is made (it loses its name as soon as Cyclone has opened it).
_captures: dict[int, IdentityCapture] = {}
# domain id → the UDP sockets Cyclone made for it (None: not known; see udp_drops.py)
_domain_sockets: dict[int, frozenset[str] | None] = {}
# Per domain: the GUID prefixes of this process's participants. Cyclone hands samples between
# them directly, without RTPS (no HEARTBEAT, nothing to be in sync with: handshake.py).
_local_prefixes: dict[int, set[bytes]] = {}


def _new_capture() -> IdentityCapture | None:
    if os.environ.get("RCAN_RTPS_RPC_IDENTITY", "").lower() in ("off", "0", "false"):
        return None
    if not capture_supported():  # it could not be kept bounded here (not Linux)
        log.debug("no packet capture for Fast DDS request identities on this platform")
        return None
    try:
        return IdentityCapture()
    except OSError as exc:  # no writable temporary directory: replies stay unnamed
        log.warning("no packet capture for Fast DDS request identities: %s", exc)
        return None


def resolve_domain_id(explicit: int | None = None,
                      env: Mapping[str, str] | None = None) -> int:
    """`explicit`, else ROS_DOMAIN_ID, else 0; a value that is not a domain id is an error
    (a typo must not silently put the process on domain 0)."""
    if explicit is None:
        raw = (os.environ if env is None else env).get("ROS_DOMAIN_ID", "").strip()
        if raw and not raw.isdigit():
            raise WireError(f"ROS_DOMAIN_ID={raw!r} is not a domain id (an integer 0..232)")
        explicit = int(raw) if raw else 0
    if not 0 <= explicit <= 232:
        raise WireError(f"domain id {explicit} is outside 0..232")
    return explicit


def localhost_requested(explicit: bool | None = None) -> bool:
    """`--localhost`, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST or ROS_LOCALHOST_ONLY=1."""
    if explicit is not None:
        return explicit
    if os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").upper() == "LOCALHOST":
        return True
    return os.environ.get("ROS_LOCALHOST_ONLY", "") == "1"


def _acquire_domain(domain_id: int, localhost: bool, max_sample_bytes: int) -> SampleBound:
    """Joins (or makes) this process's domain `domain_id`: its bound on sample size."""
    # A Domain object fixes the configuration for every participant of that id in
    # this process, so the first node decides; it must be created before them. The
    # user's CYCLONEDDS_URI comes after our defaults (_REPAIR_CONFIG, the sample size bound),
    # which it may override, and before our other fragments, which refine it.
    with _domains_lock:
        if domain_id in _domains:
            domain, users = _domains[domain_id]
            _domains[domain_id] = (domain, users + 1)
            return _domain_bounds[domain_id]
        user = os.environ.get("CYCLONEDDS_URI", "").strip()
        capture = _new_capture()
        local = [*([_LOCALHOST_CONFIG] if localhost else []),
                 *([capture.config] if capture else [])]
        ours = [_REPAIR_CONFIG, _limits_config(max_sample_bytes)]
        before = udp_socket_inodes()
        try:
            try:
                domain = Domain(domain_id, ",".join(
                    filter(None, [*ours, user, _COMPAT_CONFIG, *local])))
            except DDSException:  # an older Cyclone without <Compatibility>: do without it
                log.warning("Cyclone DDS does not know <Compatibility>; Fast DDS 3 peers may "
                            "not match endpoints with sequences")
                domain = Domain(domain_id, ",".join(filter(None, [*ours, user, *local])))
            if capture is not None and capture.start():
                _captures[domain_id] = capture
            elif capture is not None:
                log.warning("Cyclone DDS made no packet capture: Fast DDS replies stay "
                            "unnamed")
                capture.close()
        except BaseException:
            if capture is not None:
                capture.close()
            raise
        _domains[domain_id] = (domain, 1)
        bound = _domain_bounds[domain_id] = bound_in_force(max_sample_bytes, user)
        _domain_sockets[domain_id] = made_between(before, udp_socket_inodes())
    return bound


def _release_domain(domain_id: int) -> None:
    """The last node of a domain gone: free its threads and sockets."""
    with _domains_lock:
        domain, users = _domains.get(domain_id, (None, 0))
        if domain is None:
            return
        if users > 1:
            _domains[domain_id] = (domain, users - 1)
            return
        del _domains[domain_id]
        _domain_bounds.pop(domain_id, None)
        _domain_sockets.pop(domain_id, None)
        capture = _captures.pop(domain_id, None)
    if capture is not None:  # first: it may redirect Cyclone's descriptor while it lives
        capture.close()
    domain.__del__()


def _security_properties(enclave: str, domain_id: int) -> list[Policy.Property]:
    """SROS2 from the ROS_SECURITY_* environment (ros/security/settings.py): the DDS-Security
    properties of the participant, or none to run unsecured."""
    if os.environ.get("ROS_SECURITY_ENABLE", "") != "true":  # rcl's test; spares the import
        return []
    from .security.settings import participant_security

    return [Policy.Property(key, value, False)
            for key, value in participant_security(enclave, domain_id)]


def _enclave_of(security: list[Policy.Property]) -> str:
    cert = next(p.value for p in security if p.key == "dds.sec.auth.identity_certificate")
    return str(Path(cert.removeprefix("file:")).parent)


def gid_bytes(entity: Any, size: int) -> bytes:
    """An entity's GUID as a ROS Gid of the distro's size (16, or 24 zero-padded)."""
    raw: bytes = entity.guid.bytes
    return raw[:size].ljust(size, b"\0")


class RosPublisher:
    def __init__(self, node: RosNode, topic: str, type_name: str, writer: DataWriter[Any],
                 warn_other_type: bool = True) -> None:
        self.node, self.topic, self.type_name, self.writer = node, topic, type_name, writer
        self.codec = node.codecs.of(type_name).prepare_encoders()
        self._what = f"a {type_name}"  # (in errors: made once, not at each publish)
        self.closed = False
        self.incompatible_qos_events = 0
        self.other_type_events = 0  # of them, subscriptions of another type (name or hash)
        self._warn_other_type = warn_other_type
        # The matched count is kept by the node's reader thread from PUBLICATION_MATCHED, so
        # asking it costs no DDS call (the bridge asks before every move).
        self._matched = 0
        self._watch = node.watch_writer(writer, self._on_incompatible, f"publisher {topic}",
                                        on_matched=self._on_matched)

    def _on_incompatible(self, status: Any) -> None:  # on the node's reader thread
        self.incompatible_qos_events += 1
        if status.last_policy_id == qos_mod.TYPE_CONSISTENCY_POLICY_ID:
            self.other_type_events += 1
            if self._warn_other_type:
                log.warning("publisher %s: a subscription has another type (name or "
                            "definition); no messages will be sent to it", self.topic)
            return
        # rclpy's default handler says the same (its event callbacks are optional too).
        log.warning("publisher %s: a subscription requests incompatible QoS; no messages will "
                    "be sent to it (last incompatible policy: %s)", self.topic,
                    qos_mod.policy_name(status.last_policy_id))

    def publish(self, message: IdlStruct | Mapping[str, Any]) -> None:
        """Publishes a typed message or plain values (validated; errors name the field)."""
        self.publish_cdr(self.codec.encode_value(message))

    def publish_cdr(self, data: bytes) -> None:
        """Publishes a sample given as CDR bytes (4-byte header + body) of this topic's type.
        This holds the GIL inside Cyclone, local delivery included. That is safe only
        because no Cyclone thread ever waits for the GIL: never give a reader a Listener
        (see the invariant in readers.py). Bytes Cyclone refuses as no sample of the type (a
        string without its NUL, a sequence longer than the bytes) raise CdrDecodeError."""
        try:
            self.node.write_cdr(self.writer, data, self._what)
        except DDSException as exc:
            if exc.code != DDSException.DDS_RETCODE_BAD_PARAMETER:
                raise
            raise CdrDecodeError(f"{len(data)} bytes that are not the CDR of a "
                                 f"{self.type_name} (Cyclone refused them)") from None

    def _on_matched(self, count: int) -> None:  # on the node's reader thread (first: creation)
        self._matched = count

    def matched_count(self) -> int:
        """Subscriptions matched now (as of the reader thread's last status read)."""
        return self._matched

    async def wait_for_subscribers(self, count: int = 1, timeout: float = 5.0) -> int:
        return await _wait_count(self.matched_count, count, timeout,
                                 f"no subscriber matched {self.topic}")

    async def acknowledged(self, timeout: float) -> bool:
        """Whether every matched reliable subscription acknowledged all that was published,
        within `timeout` s. What to wait for before the writer is deleted or the process
        exits: a sample dropped at a reader is sent again only while its writer lives. In a
        worker thread (the C call blocks; it invokes no listener, and no lock of ours is
        held)."""
        if self.closed:
            return False
        try:
            return await asyncio.to_thread(_acked, self.writer, int(timeout * 1e9))
        except DDSException:  # deleted meanwhile: nothing more can be acknowledged
            return False

    def close(self) -> None:
        """Deletes the writer (it leaves the graph); idempotent."""
        if self.closed:
            return
        self.closed = True
        self.node.unwatch(self._watch)
        self.node.forget_writer(self.writer)
        with contextlib.suppress(DDSException):
            self.writer.__del__()


class CdrSample(bytes):
    """A sample as it arrived: its CDR bytes (4-byte header + body), and its `sample_info`."""

    sample_info: Any


class RosSubscription:
    """Samples arrive on the node's reader thread and are handed to asyncio (or to
    `callback`, which then runs on that thread: keep it short, it may publish)."""

    def __init__(self, node: RosNode, topic: str, type_name: str, qos: QosProfile,
                 callback: Callable[[IdlStruct], None] | None, maxsize: int,
                 raw: bool = False, warn_other_type: bool = True,
                 governed: bool = False) -> None:
        self.node, self.topic, self.type_name = node, topic, type_name
        self.incompatible_qos_events = 0
        self.other_type_events = 0  # of them, publishers of another type (name or hash)
        self._warn_other_type = warn_other_type
        self._callback = callback
        self._queue: asyncio.Queue[IdlStruct] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._closed = False
        if callback is None:
            self._loop = asyncio.get_running_loop()
            self._queue = asyncio.Queue(maxsize)
        # (tracked by the node: it announces it and closes it with itself)
        self.reader = node.create_reader(mangle_topic(topic), type_name, qos,
                                         node.governed_entry if governed else "")
        # Historical (transient-local) samples already in the reader trigger the condition.
        self._watch = node.watch(self.reader, self._on_samples, f"subscription {topic}",
                                 on_incompatible_qos=self._on_incompatible,
                                 decode=CdrSample if raw else None)

    def _on_samples(self, samples: list[IdlStruct]) -> None:  # on the node's reader thread
        if self._callback is not None:
            for sample in samples:
                if self._closed:
                    return
                try:
                    self._callback(sample)
                except Exception:  # one bad sample must not silence the subscription
                    log.exception("subscription %s: callback failed", self.topic)
        elif self._loop is not None:
            try:
                self._loop.call_soon_threadsafe(self._put_all, samples)
            except RuntimeError:  # the loop closed while DDS was still delivering
                return

    def _put_all(self, samples: list[IdlStruct]) -> None:
        if not self._closed and not self.node.closed:
            for sample in samples:
                self._put(sample)

    def _put(self, sample: IdlStruct) -> None:
        assert self._queue is not None
        if self._queue.full():  # keep the newest, like a keep-last history
            self._queue.get_nowait()
        self._queue.put_nowait(sample)

    def _on_incompatible(self, status: Any) -> None:
        self.incompatible_qos_events += 1
        if status.last_policy_id == qos_mod.TYPE_CONSISTENCY_POLICY_ID:
            self.other_type_events += 1
            if self._warn_other_type:
                log.warning("subscription %s: a publisher has another type (name or "
                            "definition); it will not be heard", self.topic)
            return
        log.warning("subscription %s: a publisher offers incompatible QoS; it will not be "
                    "heard (last incompatible policy: %s)", self.topic,
                    qos_mod.policy_name(status.last_policy_id))

    async def get(self, timeout: float | None = None) -> IdlStruct:
        if self._queue is None:
            raise WireError("this subscription delivers to a callback")
        return await asyncio.wait_for(self._queue.get(), timeout)

    def __aiter__(self) -> AsyncIterator[IdlStruct]:
        return self._iterate()

    async def _iterate(self) -> AsyncIterator[IdlStruct]:
        while True:
            yield await self.get()

    def matched_count(self) -> int:
        return int(self.reader.get_subscription_matched_status().current_count)

    async def wait_for_publishers(self, count: int = 1, timeout: float = 5.0) -> int:
        return await _wait_count(self.matched_count, count, timeout,
                                 f"no publisher matched {self.topic}")

    def close(self) -> None:
        """Stops deliveries (none after this returns) and deletes the reader; idempotent."""
        if self._closed:
            return
        self._closed = True
        self.node.unwatch(self._watch)
        self.node.forget_reader(self.reader)
        with contextlib.suppress(DDSException):
            self.reader.__del__()


def _settle(done: asyncio.Future[None]) -> None:
    if not done.done():
        done.set_result(None)


async def _wait_count(current: Callable[[], int], count: int, timeout: float,
                      message: str) -> int:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while (n := current()) < count:
        if loop.time() >= deadline:
            raise GraphTimeout(f"{message} within {seconds(timeout)}")
        await asyncio.sleep(0.02)
    return n


class RosNode:
    """One ROS node on one DDS participant.

    The first node of a domain in a process sets what all its nodes share: `localhost`, and
    `max_sample_bytes`, the largest sample Cyclone takes in or sends (larger ones are dropped
    as they arrive, with Cyclone's warning; DEFAULT_MAX_SAMPLE_BYTES)."""

    def __init__(self, name: str, namespace: str = "/", *, domain_id: int | None = None,
                 localhost: bool | None = None, distro: str | None = None,
                 idl_paths: Iterable[str | Path] = (), store: TypeStore | None = None,
                 enclave: str = "/", governed_by: str = "",
                 max_sample_bytes: int = DEFAULT_MAX_SAMPLE_BYTES) -> None:
        validate_node_name(name)
        if not 0 < max_sample_bytes < 1 << 31:  # (Cyclone's bound: a 32-bit size)
            raise WireError(f"max_sample_bytes {max_sample_bytes} is outside 1..2**31-1")
        self.name = name
        # Who governs what this node commands (a bridge's robot id): its commanding writers
        # say so in their USER_DATA (`governed_by=…;`), so that a tool about to publish there
        # beside it can tell (`graph.Endpoint.governed_by`). rmw ignores keys it does not know.
        self.governed_entry = qos_mod.user_data_entry(GOVERNED_BY, governed_by)
        self.namespace = normalize_namespace(namespace)
        self.store = store or TypeStore([*idl_paths, *env_idl_paths()], distro)
        self.types = DdsTypes(self.store)
        self.values = MessageValues(self.types)
        self.codecs = CdrCodecs(self.types, self.values)
        self.domain_id = resolve_domain_id(domain_id)
        self.localhost = localhost_requested(localhost)
        security = _security_properties(enclave, self.domain_id)
        # (the domain's: read once, not at each write)
        self._sample_bound = _acquire_domain(self.domain_id, self.localhost, max_sample_bytes)
        before = udp_socket_inodes()
        try:
            self.participant = DomainParticipant(self.domain_id, qos=Qos(
                Policy.Userdata(f"enclave={enclave};".encode()), *security))
        except DDSException as e:
            _release_domain(self.domain_id)
            if not security:
                raise
            from .security.errors import SecurityError
            raise SecurityError(
                f"Cyclone DDS refused the secured participant of {self.fqn} (enclave "
                f"{_enclave_of(security)}): {e}; Cyclone's own message, on stderr, says "
                "why") from e
        except BaseException:
            _release_domain(self.domain_id)
            raise
        self.secured = bool(security)
        self._prefix = bytes(self.participant.guid.bytes[:12])
        with _domains_lock:
            _local_prefixes.setdefault(self.domain_id, set()).add(self._prefix)
        # The domain's sockets and any the participant made (<ManySocketsMode> many).
        mine = made_between(before, udp_socket_inodes())
        shared = _domain_sockets.get(self.domain_id)
        self._sockets = None if mine is None or shared is None else shared | mine
        # Request identities of Fast DDS replies, or None (capture off; see rtps_capture.py).
        self.identities = _captures.get(self.domain_id)
        self._topics: dict[str, Topic[Any]] = {}
        self._readers: list[Any] = []
        self._writers: list[Any] = []
        self._subscriptions: list[RosSubscription] = []
        self._info_refused = False  # the last announcement was past the sample size bound
        self._lock = threading.Lock()
        self.closed = False
        self.reader_thread = ReaderThread(self.participant, f"dds-read {self.fqn}")
        try:
            self.publisher = Publisher(self.participant)
            self.subscriber = Subscriber(self.participant)
            self._info_writer = self._discovery_writer()
            self.announce()
        except BaseException:  # a half-made node leaves nothing behind
            self.close()
            raise

    @property
    def fqn(self) -> str:
        return f"{self.namespace.rstrip('/')}/{self.name}"

    def resolve(self, name: str) -> str:
        """A topic/service name resolved against this node, as rcl would."""
        return expand_topic_name(name, self.name, self.namespace)

    # -- entities -------------------------------------------------------------
    def topic(self, dds_name: str, type_name: str) -> Topic[Any]:
        with self._lock:
            found = self._topics.get(dds_name)
            if found is None:
                # ros_discovery_info is read by cyclonedds' typed readers (graph.py,
                # handshake.py), on the way to a service call: its serializer stays built.
                found = make_topic(self.participant, dds_name, self.types.struct(type_name),
                                   self.types.description(type_name),
                                   keep_serializer=dds_name == DISCOVERY_TOPIC)
                self._topics[dds_name] = found
            return found

    def endpoint_user_data(self, type_name: str) -> bytes | None:
        if self.store.distro == "humble":
            return None  # type hashes exist from Iron on
        return f"typehash={self.store.hash_of(type_name)};".encode()

    def create_publisher(self, topic: str, type_name: str,
                         qos: QosProfile = qos_mod.DEFAULT, *,
                         warn_other_type: bool = True, governed: bool = False
                         ) -> RosPublisher:
        """`warn_other_type=False`: a subscription of another type is only counted
        (`other_type_events`), not logged, for an owner that reports it itself.
        `governed`: the robot obeys it (a bridge commands it): its writer carries the
        node's `governed_by`."""
        full = self.resolve(topic)
        writer = self.create_writer(mangle_topic(full), type_name, qos,
                                    self.governed_entry if governed else "")
        return RosPublisher(self, full, type_name, writer, warn_other_type)

    def create_subscription(self, topic: str, type_name: str,
                            qos: QosProfile = qos_mod.DEFAULT, *,
                            callback: Callable[[IdlStruct], None] | None = None,
                            maxsize: int = 1000, raw: bool = False,
                            warn_other_type: bool = True,
                            governed: bool = False) -> RosSubscription:
        """Samples arrive as typed messages, or with `raw` as `CdrSample` bytes undecoded.
        `warn_other_type`, `governed`: as for `create_publisher` (a governed reader: an
        action client's status, there from the start where its goal writers are made by
        the first goal)."""
        sub = RosSubscription(self, self.resolve(topic), type_name, qos, callback, maxsize,
                              raw, warn_other_type, governed)
        # The node owns its subscriptions: a dropped handle must not silence the topic.
        self._subscriptions.append(sub)
        return sub

    def create_writer(self, dds_topic: str, type_name: str, qos: QosProfile,
                      extra_user_data: str = "") -> DataWriter[Any]:
        """A raw writer (used for topics, service requests/replies, action parts)."""
        user_data = (self.endpoint_user_data(type_name) or b"") + extra_user_data.encode()
        writer = DataWriter(self.publisher, self.topic(dds_topic, type_name),
                            qos=qos.to_dds(user_data or None))
        self.track_writer(writer)
        return writer

    def create_reader(self, dds_topic: str, type_name: str, qos: QosProfile,
                      extra_user_data: str = "") -> DataReader[Any]:
        """A raw reader, without delivery: `watch` it to get its samples."""
        user_data = (self.endpoint_user_data(type_name) or b"") + extra_user_data.encode()
        reader: DataReader[Any] = DataReader(
            self.subscriber, self.topic(dds_topic, type_name),
            qos=qos.to_dds(user_data or None))
        self.track_reader(reader)
        return reader

    def watch(self, reader: DataReader[Any], deliver: Callable[[list[Any]], None], label: str,
              *, on_incompatible_qos: Callable[[Any], None] | None = None,
              decode: Decode | None = None) -> Watch:
        """Delivers `reader`'s valid samples, in batches, to `deliver` on this node's reader
        thread (never on a Cyclone thread), decoded by `decode` (bytes → sample; by default
        the generated decoder of the reader's type)."""
        decode = decode or self.decoder_for(reader.topic.data_type)
        return self.reader_thread.add(Watch(reader, deliver, label, on_incompatible_qos, decode))

    def decoder_for(self, data_type: type[Any]) -> Decode | None:
        """The generated decoder of a topic type this node made, or None for other structs
        (the Cyclone request wrappers), which decode themselves."""
        name = self.types.name_of(data_type)
        return None if name is None else self.codecs.of(name).prepare_decoder().decode

    def watch_writer(self, writer: DataWriter[Any], on_incompatible_qos: Callable[[Any], None],
                     label: str, *, on_matched: Callable[[int], None] | None = None
                     ) -> WriterWatch:
        """Calls `on_incompatible_qos(status)` on this node's reader thread when a reader
        requests QoS that `writer` does not offer, and `on_matched(count)` when the number
        of matched readers changes, first with the count now."""
        watch = WriterWatch(writer, on_incompatible_qos, label, on_matched)
        if on_matched is not None:
            # After the mask is set (a later change triggers the thread, which reads the count
            # again) and before the thread has the writer (its reads all come after this one).
            on_matched(int(writer.get_publication_matched_status().current_count))
        return self.reader_thread.add(watch)

    def unwatch(self, watch: Watch | WriterWatch) -> None:
        """No delivery to `watch` starts after this returns."""
        self.reader_thread.remove(watch)

    def udp_drops(self) -> int | None:
        """Datagrams the kernel has dropped so far at this node's DDS sockets (full receive
        buffers); None where that is not known (not Linux; see udp_drops.py)."""
        return None if not self._sockets else dropped_at(self._sockets)

    async def delivered(self) -> None:
        """Returns once every sample our readers held when it was called has been handed to
        its callback — and, for callbacks that hop to this event loop with
        `call_soon_threadsafe`, once those hops have run (they were queued before ours)."""
        loop = asyncio.get_running_loop()
        done: asyncio.Future[None] = loop.create_future()

        def wake() -> None:  # on the reader thread (or here, if it is not running)
            with contextlib.suppress(RuntimeError):  # the loop has closed
                loop.call_soon_threadsafe(_settle, done)

        self.reader_thread.after_next_pass(wake)
        await done

    def forget_reader(self, reader: Any) -> None:
        with self._lock:
            if reader in self._readers:
                self._readers.remove(reader)
            self._subscriptions = [s for s in self._subscriptions if s.reader is not reader]
        if not self.closed:
            self.announce()

    def track_reader(self, reader: Any) -> None:
        with self._lock:
            self._readers.append(reader)
        self.announce()

    def forget_writer(self, writer: Any) -> None:
        with self._lock:
            if writer in self._writers:
                self._writers.remove(writer)
        if not self.closed:
            self.announce()

    def track_writer(self, writer: Any) -> None:
        with self._lock:
            self._writers.append(writer)
        self.announce()

    # -- graph presence ---------------------------------------------------------
    def _discovery_writer(self) -> DataWriter[Any]:
        topic = self.topic(DISCOVERY_TOPIC, DISCOVERY_TYPE)
        return DataWriter(self.publisher, topic, qos=qos_mod.DISCOVERY_INFO.to_dds(
            self.endpoint_user_data(DISCOVERY_TYPE)))

    def discovery_reader(self) -> DataReader[Any]:
        """A reader of every participant's ros_discovery_info (not a node endpoint: rmw
        lists none). The type is keyless, so every participant writes the same instance: a
        deep history keeps one's update from overwriting another's unread one. It carries
        the type hash like every endpoint (rmw_cyclonedds warns about one without)."""
        qos = qos_mod.DISCOVERY_INFO.with_(depth=1000)
        return DataReader(self.subscriber, self.topic(DISCOVERY_TOPIC, DISCOVERY_TYPE),
                          qos=qos.to_dds(self.endpoint_user_data(DISCOVERY_TYPE)))

    def gid_size(self) -> int:
        return self.store.message("rmw_dds_common/msg/Gid").fields[0].type.size

    def announce(self) -> None:
        """Publishes this node's entities on ros_discovery_info (on every change)."""
        if not hasattr(self, "_info_writer"):
            return
        size = self.gid_size()
        with self._lock:
            readers = [{"data": gid_bytes(r, size)} for r in self._readers]
            writers = [{"data": gid_bytes(w, size)} for w in self._writers]
        # Through the generated codec, as every writer of ours: cyclonedds' own would rebuild
        # the Python serializer `make_topic` let go of (and is slower).
        info = self.codecs.of(DISCOVERY_TYPE).encode_plain({
            "gid": {"data": gid_bytes(self.participant, size)},
            "node_entities_info_seq": [{
                "node_namespace": self.namespace,
                "node_name": self.name,
                "reader_gid_seq": readers,
                "writer_gid_seq": writers,
            }],
        })
        try:
            self.write_cdr(self._info_writer, info, f"{self.fqn}'s {DISCOVERY_TOPIC}")
        except SampleTooLarge as too_large:
            # Its endpoints work all the same (DDS discovery matches them); only ROS's graph
            # (`ros2 node info`) misses them. Not an error of the endpoint being made, nor
            # of one being deleted: said once, until an announcement fits again.
            if not self._info_refused:
                log.warning("%s; peers do not see this node's endpoints change until its "
                            "ros_discovery_info fits again", too_large)
            self._info_refused = True
            return
        self._info_refused = False

    def write_cdr(self, writer: DataWriter[Any], data: bytes, what: str) -> None:
        """Writes one sample given as CDR bytes on `writer` (`what` names it in errors).
        SampleTooLarge past the domain's bound on sample size, checked here first: Cyclone
        drops such a sample with a warning, and its write fails only when a reader of it is
        in this process (with readers elsewhere only, it returned as if sent). Other
        DDSExceptions (a writer deleted: its node closed) are left as they are."""
        too_large = past_bound(len(data), self._sample_bound, what, self.domain_id)
        if too_large is not None:
            raise too_large
        try:
            raw_cdr.write(writer, data)
        except DDSException as exc:
            refused = refused_for_size(exc, len(data), self._sample_bound, what,
                                       self.domain_id)
            if refused is not None:
                raise refused from None
            raise

    def close(self) -> None:
        """Leaves the graph: deleting the participant withdraws every endpoint. The reader
        thread stops first, so no delivery happens after this returns. Idempotent."""
        with self._lock:
            if self.closed:
                return
            self.closed = True
        self.reader_thread.close()
        with self._lock:
            self._readers.clear()
            self._writers.clear()
            self._subscriptions.clear()
        self.__dict__.pop("_info_writer", None)  # announce() does nothing from here on
        self.participant.__del__()
        with _domains_lock:
            _local_prefixes.get(self.domain_id, set()).discard(self._prefix)
        _release_domain(self.domain_id)

    def in_process(self, guid: bytes) -> bool:
        """Whether the endpoint `guid` belongs to a participant of this process in our
        domain (Cyclone delivers its samples to us directly)."""
        with _domains_lock:
            return bytes(guid[:12]) in _local_prefixes.get(self.domain_id, ())

    def __enter__(self) -> RosNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _acked(writer: DataWriter[Any], timeout_ns: int) -> bool:
    """`writer.wait_for_acks`, False on its timeout: cyclonedds-python (11.0.1) compares a
    non-zero return code with `Exception.DDS_RETCODE_TIMEOUT`, the builtin's attribute that
    is not there, so every timeout raised AttributeError instead of returning False."""
    try:
        return bool(writer.wait_for_acks(timeout_ns))
    except AttributeError:
        return False
