"""The governed bridge as one object: start in dependency order, stop in reverse.

    prepare: credentials, TLS, audit key and the API port are checked (the port bound) before
           anything touches the robot: a start that fails here leaves no trace on the graph
           and writes no audit entry
    start: ROS node → audit log → goal action clients → dispatcher → governor → telemetry
           → governor started (BRIDGE_STARTED; after a run that did not end with
           BRIDGE_STOPPED, the motion it left taken back first: docs/governance.md) → watch
           for other publishers on the command topics → HTTP API → mDNS advert
    stop:  mDNS withdrawn → held commands withdrawn (HITL_WITHDRAWN; their issuers told while
           still connected) → API closed (no new commands) → watch ended → velocity streams
           ended → robot halted (zero velocity, goals cancelled) → telemetry → governor
           (any held since withdrawn, then BRIDGE_STOPPED)
           → goal action clients → audit closed → ROS node left → API port released

Each resource's cleanup goes on an `AsyncExitStack` as soon as the resource exists, so stop
runs exactly the list above, and a start that fails at any step unwinds what it had acquired
(in the same order) before the error propagates.

    NEW → PREPARED → STARTING → RUNNING → STOPPING → STOPPED
    prepare or start raising: FAILED (once unwound). stop() from NEW, FAILED or STOPPED does
    nothing; a second start() raises BridgeStateError. A bridge is not restarted: make a new one.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import gc
import inspect
import logging
import os
import socket
import ssl
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from .._modules import START_ONLY, let_go
from ..api import ApiServer, bind, build_app, cert_principals, server_ssl_context
from ..api.ports import GoalView, ImageSource
from ..config import RcanConfig, plaintext_problem
from ..events import Events
from ..governance import (
    AuditLog,
    Governor,
    Notifier,
    SystemClock,
    TokenAuthenticator,
    WebhookNotifier,
)
from ..governance.decision_log import log_entry
from ..governance.entry_bound import request_bytes_limit
from ..governance.signatures import Signatures
from ..governance.start_files import start_file_problems
from ..rcan import Status
from ..ros.participant import RosNode
from .commanders import CommanderWatch
from .commands import RosDispatcher
from .errors import BridgeStateError
from .goals import GoalRoutes, route_mapping
from .joint_positions import JointPositions
from .notify import DiagnosticsNotifier, FanOutNotifier
from .open_files import raise_open_file_limit
from .telemetry import TelemetryState

if TYPE_CHECKING:
    from ..ros.services import RequestMapping
    from .mdns import Advert, RcanAdvertiser  # imported when advertising: zeroconf is large

log = logging.getLogger(__name__)


def nav_mapping(config: RcanConfig) -> RequestMapping:
    """The configured request-reply mapping of the navigation action (name override first)."""
    return route_mapping(config.bridge.ros2, "nav_action")


def audit_goal_outcomes(events: Events, governor: Governor) -> None:
    """Each goal's end (succeeded, aborted, canceled, …), on any goal server, becomes a
    GOAL_FINISHED entry."""
    events.goal_finished.subscribe(lambda end: governor.goal_finished(
        end.view.goal_id, end.view.state, server=end.view.action,
        message_id=end.message_id, detail=end.view.detail))


def wire_robot_side(events: Events, governor: Governor, telemetry: TelemetryState,
                    goals: GoalRoutes | None, diagnostics: DiagnosticsNotifier | None) -> None:
    """What the robot side listens to: STATUS's `safe_stop` follows lost sessions and sent
    commands, goal ends are audited, pending approvals are published as diagnostics."""
    events.safe_stop.subscribe(lambda _p: telemetry.mark_safe_stop())
    events.command_sent.subscribe(telemetry.clear_safe_stop)
    if goals is not None:
        audit_goal_outcomes(events, governor)
        events.session_lost.subscribe(
            lambda p: goals.warn_cancelling(f"control session of '{p.name}' lost"))
    if diagnostics is not None:
        events.governance.subscribe(lambda: diagnostics.pending_changed(len(governor.pending())))


def watch_commanders(node: RosNode, governor: Governor, dispatcher: RosDispatcher,
                     telemetry: TelemetryState, interval: float | None = None) -> CommanderWatch:
    """Other publishers on the topics the dispatcher commands the robot on: shown in STATUS,
    logged, audited; started (on the running loop). Polled every `interval` seconds
    (default: `bridge.ros2.foreign_publishers.poll_s`)."""
    ros2 = dispatcher.ros2
    every = ros2.foreign_publishers.poll_s if interval is None else interval
    watch = CommanderWatch(node, dispatcher.command_topics(), show=telemetry.foreign_publishers,
                           audit=governor.foreign_publisher, interval=every,
                           expected=ros2.expected_publishers())
    watch.start()
    return watch


class BridgeView:
    """The `RobotView` the API reads: telemetry plus every goal action's goals."""

    def __init__(self, telemetry: TelemetryState, goals: GoalRoutes) -> None:
        self.telemetry = telemetry
        self.goals_ = goals

    def status(self, *, pending_auth: int) -> Status:
        return self.telemetry.status(pending_auth=pending_auth)

    def watch(self, changed: Callable[[], None]) -> None:
        self.telemetry.events.robot.subscribe(changed)  # telemetry and goals tell `robot`

    def watch_goals(self, changed: Callable[[GoalView], None]) -> None:
        self.goals_.events.goal.subscribe(changed)

    def goal(self, goal_id: str) -> GoalView | None:
        return self.goals_.goal(goal_id)

    def goals(self) -> list[GoalView]:
        return self.goals_.goals()


@dataclass
class BridgeOptions:
    localhost: bool | None = None  # None: from ROS_AUTOMATIC_DISCOVERY_RANGE/ROS_LOCALHOST_ONLY
    host: str | None = None  # override api.host
    port: int | None = None  # override api.port (0: any free port)
    mdns: bool = True
    mdns_interfaces: list[str] | None = None
    env: Mapping[str, str] = field(default_factory=lambda: dict(os.environ))


class BridgeState(enum.Enum):
    NEW = "new"
    PREPARED = "prepared"  # checked; the API port is bound
    STARTING = "starting"
    RUNNING = "running"
    STOPPING = "stopping"
    STOPPED = "stopped"
    FAILED = "failed"  # prepare or start raised; whatever it had acquired is released


Cleanup = Callable[[], object]  # returns None or an awaitable


class Bridge:
    # Set by prepare().
    _authenticator: TokenAuthenticator
    _signatures: Signatures
    _ssl: ssl.SSLContext | None
    _sock: socket.socket

    def __init__(self, config: RcanConfig, options: BridgeOptions | None = None) -> None:
        self.config = config
        self.options = options or BridgeOptions()
        self.state = BridgeState.NEW
        self._stack = contextlib.AsyncExitStack()  # every cleanup, in acquisition order
        self._started = asyncio.Event()  # start finished (RUNNING or FAILED)
        self._stopped = asyncio.Event()
        # What the API and tests look at; the lifecycle itself only needs the stack.
        self.node: RosNode | None = None
        self.audit: AuditLog | None = None
        self.goals: GoalRoutes | None = None
        self.dispatcher: RosDispatcher | None = None
        self.governor: Governor | None = None
        self.events = Events()  # who is told what; frozen once the API serves
        self._diagnostics: DiagnosticsNotifier | None = None
        self.telemetry: TelemetryState | None = None
        # Heard by the telemetry's JointState reader, read by a stop holding an arm.
        self._joint_positions = JointPositions()
        self.commanders: CommanderWatch | None = None
        self.images: ImageSource | None = None  # bridge.ros2.images, when any
        self.server: ApiServer | None = None
        self.advertiser: RcanAdvertiser | None = None
        self.url = ""

    # -- lifecycle -----------------------------------------------------------------------
    def prepare(self) -> None:
        """Check everything that can fail without the robot; bind the API port.

        Raises (AuthConfigError, AuditKeyError, OSError, ...) before the bridge joins the
        domain or writes an audit entry. Again once prepared: nothing to do.
        """
        if self.state is BridgeState.PREPARED:
            return
        self._expect("prepare", BridgeState.NEW)
        try:
            self._check_and_bind()
        except BaseException:
            self.state = BridgeState.FAILED
            raise
        self.state = BridgeState.PREPARED

    async def start(self) -> str:
        """Brings the bridge up; returns the API's URL once it accepts commands.

        A failure at any step releases what the earlier steps acquired, then propagates.
        """
        if self.state is BridgeState.NEW:
            self.prepare()
        self._expect("start", BridgeState.PREPARED)
        self.state = BridgeState.STARTING
        try:
            await self._acquire()
            self.state = BridgeState.RUNNING
            ros2 = self.config.bridge.ros2
            log.info("bridge running: api %s, node %s on domain %d, audit %s", self.url,
                     self.node.fqn if self.node else ros2.node_name,
                     ros2.domain_id, self.config.bridge.audit.path)
        except BaseException:
            log.info("bridge start failed; releasing what it had acquired")
            await self._stack.aclose()
            self.state = BridgeState.FAILED
            raise
        finally:
            self._started.set()
        return self.url

    async def stop(self) -> None:
        """Graceful stop, in reverse order of start; each step runs even if an earlier one
        failed. A no-op before start, after a failed start and once stopped."""
        if self.state is BridgeState.STARTING:  # let the start finish, then undo it
            await self._started.wait()
        if self.state is BridgeState.STOPPING:
            await self._stopped.wait()
            return
        if self.state not in (BridgeState.PREPARED, BridgeState.RUNNING):
            return
        self.state = BridgeState.STOPPING
        log.info("bridge stopping")
        try:
            await self._stack.aclose()
        finally:
            self.state = BridgeState.STOPPED
            self._stopped.set()
            log.info("bridge stopped")

    def _expect(self, call: str, state: BridgeState) -> None:
        if self.state is not state:
            raise BridgeStateError(f"cannot {call} a bridge that is {self.state.value} "
                                   f"(only one that is {state.value})")

    def _on_stop(self, step: str, cleanup: Cleanup) -> None:
        """Registers `cleanup` to run on stop or on a failed start, after every cleanup
        registered later. A failing cleanup is logged, never raised: the rest still run."""

        async def run() -> None:
            try:
                result = cleanup()
                if inspect.isawaitable(result):
                    await result
            except Exception:
                log.exception("bridge shutdown: %s failed", step)

        self._stack.push_async_callback(run)

    # -- start, step by step (each registers its cleanup as soon as it has acquired) -----
    def _check_and_bind(self) -> None:
        api, opts = self.config.bridge.api, self.options
        self._authenticator = TokenAuthenticator.from_config(
            api, self.config.bridge.rbac, opts.env, clock=SystemClock())
        self._ssl = server_ssl_context(api.tls) if api.tls else None
        self._signatures = Signatures.from_config(api)  # a key that does not load: refuse now
        # A key unreadable, too open or not Ed25519, a log, latch or witness at a device:
        # refuse now, with the first (`config check` lists them all, from the same list).
        problems = start_file_problems(self.config.bridge)
        if problems:
            raise problems[0].error
        host = opts.host or api.host
        plaintext = plaintext_problem(api, host)  # --host may point a loopback config outward
        if plaintext is not None:
            raise ValueError(f"api: {plaintext}")
        self._sock = bind(host, api.port if opts.port is None else opts.port)
        # Last out: the server closes it too, but a bridge that never served must as well.
        self._on_stop("API port", self._sock.close)

    async def _acquire(self) -> None:
        node = self._join_domain()
        audit = await self._open_audit()
        goals, dispatcher = self._robot_side(node)
        governor, telemetry = self._governance(node, audit, goals, dispatcher)
        await self._start_governor(governor, dispatcher)
        self._watch_commanders(node, governor, dispatcher, telemetry)
        self._let_go_of_start_only()
        await self._serve(governor, telemetry, goals)
        self.events.freeze()  # every listener is wired: none may be added from now on
        if self.options.mdns:
            self._advertise_soon()

    @staticmethod
    def _let_go_of_start_only() -> None:
        """The robot side is built and the governor started (a crash's motion taken back):
        the modules only that needed are let go of, now, so that the rest of the start (the
        API, mDNS) fills the memory they leave (idle memory, issue 27)."""
        let_go(START_ONLY)
        gc.collect()  # a module's functions and its namespace are a reference cycle

    def _join_domain(self) -> RosNode:
        ros2 = self.config.bridge.ros2
        node = self.node = RosNode(ros2.node_name, ros2.namespace or "/",
                                   domain_id=ros2.domain_id, distro=ros2.distro,
                                   localhost=self.options.localhost,
                                   governed_by=self.config.robot.ruri,
                                   max_sample_bytes=ros2.max_sample_bytes)
        self._on_stop("leaving the ROS graph", node.close)
        return node

    async def _open_audit(self) -> AuditLog:
        audit = self.config.bridge.audit
        # Every entry names the robot it governs (§6): a log read apart from its robot says whose.
        self.audit = await AuditLog.open(
            audit.path, audit.key_path, ruri=self.config.robot.ruri, witness=audit.witness,
            audited=self.events.audited,
            request_bytes=request_bytes_limit(self.config.bridge.api.max_body_bytes))
        self.events.audited.subscribe(log_entry)  # one log line per decision and safety event
        self._on_stop("closing the audit log", self.audit.close)
        return self.audit

    def _robot_side(self, node: RosNode) -> tuple[GoalRoutes, RosDispatcher]:
        ros2 = self.config.bridge.ros2
        goals = self.goals = GoalRoutes(node, ros2, events=self.events)  # a client per route
        self._on_stop("goal action clients", goals.close)
        goals.start()
        self.dispatcher = RosDispatcher(node, ros2, goals, telemetry_age=self._telemetry_age,
                                        events=self.events,
                                        joint_positions=self._joint_positions)
        return goals, self.dispatcher

    def _governance(self, node: RosNode, audit: AuditLog, goals: GoalRoutes,
                    dispatcher: RosDispatcher) -> tuple[Governor, TelemetryState]:
        governor = self.governor = Governor.from_config(
            self.config, audit=audit, dispatcher=dispatcher, notifier=self._notifier(node),
            events=self.events)
        # BRIDGE_STOPPED answers a BRIDGE_STARTED; before that, only the latch file's thread.
        self._on_stop("governor", lambda: governor.stop() if governor.started
                      else governor.latch.close())
        telemetry = self.telemetry = TelemetryState(
            node, self.config, estop_latched=lambda: governor.latch.latched,
            active_goals=goals.active, navigation=goals.navigation, events=self.events,
            joint_positions=self._joint_positions)
        self._on_stop("telemetry", telemetry.close)
        if self.config.bridge.ros2.images:
            from .images import ImageFeeds  # only where a camera is configured

            images = self.images = ImageFeeds(node, self.config.bridge.ros2.images)
            self._on_stop("image feeds", images.close)
        wire_robot_side(self.events, governor, telemetry, goals, self._diagnostics)
        return governor, telemetry

    async def _start_governor(self, governor: Governor, dispatcher: RosDispatcher) -> None:
        await governor.start()
        # Before the governor's BRIDGE_STOPPED: the robot is halted while it is audited.
        self._on_stop("halting the robot", dispatcher.halt_before_leaving)
        # Before the halt: a velocity stream still sending would undo its zero.
        self._on_stop("ending velocity streams", governor.end_streams)

    def _watch_commanders(self, node: RosNode, governor: Governor, dispatcher: RosDispatcher,
                          telemetry: TelemetryState) -> None:
        watch = self.commanders = watch_commanders(node, governor, dispatcher, telemetry)
        self._on_stop("watching the command topics", watch.close)

    def _telemetry_age(self) -> float | None:
        return self.telemetry.age_s() if self.telemetry is not None else None

    def _notifier(self, node: RosNode) -> Notifier:
        ros2, hitl = self.config.bridge.ros2, self.config.bridge.hitl
        self._diagnostics = DiagnosticsNotifier(node, ros2.diagnostics_topic)
        self._on_stop("diagnostics", self._diagnostics.close)
        notifiers: list[Notifier] = [self._diagnostics]
        if hitl.notify_webhook:
            notifiers.append(WebhookNotifier(hitl.notify_webhook))
        return FanOutNotifier(notifiers)

    async def _serve(self, governor: Governor, telemetry: TelemetryState,
                     goals: GoalRoutes) -> None:
        api, opts = self.config.bridge.api, self.options
        raise_open_file_limit()  # before the first client: each connection is a descriptor
        app = build_app(governor=governor, authenticator=self._authenticator,
                        robot=BridgeView(telemetry, goals), config=self.config,
                        cert_principals=cert_principals(self.config) if api.tls else None,
                        signatures=self._signatures, images=self.images)
        server = self.server = ApiServer(app, host=opts.host or api.host,
                                         port=api.port if opts.port is None else opts.port,
                                         ssl_context=self._ssl, sock=self._sock)
        self._on_stop("closing the API", server.close)  # first: start may fail half-way
        self.url = await server.start()
        # Before the API closes: an issuer still connected hears of it (`withdraw_all_held`).
        self._on_stop("withdrawing held commands", governor.withdraw_all_held)

    def _advertise_soon(self) -> None:
        # Joining mDNS takes ~1 s (probing): commands are accepted meanwhile.
        task = asyncio.create_task(self._advertise())

        async def withdraw() -> None:
            await task  # finish joining before saying goodbye
            if self.advertiser is not None:
                await self.advertiser.close()

        self._on_stop("withdrawing the mDNS advert", withdraw)

    async def _advertise(self) -> None:
        from .mdns import Advert, RcanAdvertiser, live_records

        api, opts = self.config.bridge.api, self.options
        host, port = opts.host or api.host, int(self.url.rsplit(":", 1)[1])
        tls = api.tls is not None

        def current() -> Advert:
            telemetry = self.telemetry
            live = None if telemetry is None else live_records(
                telemetry.status(pending_auth=0, counted=False))
            return Advert.for_server(self.config, host=host, port=port, tls=tls, live=live)

        self.advertiser = RcanAdvertiser(current(), interfaces=opts.mdns_interfaces)
        try:
            await self.advertiser.start()
        except Exception as exc:  # no multicast here: the robot is still commandable by URL
            log.warning("mDNS advertisement failed (%s: %s): the API is still at %s",
                        type(exc).__name__, exc, self.url)
            log.debug("mDNS advertisement failure", exc_info=True)
            return
        # Re-announce when the address, or what STATUS says in the advert, changes.
        self.advertiser.follow(current)
