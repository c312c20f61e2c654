"""The governed bridge as one object: start in dependency order, stop in reverse.

    prepare: credentials, TLS, audit key and the API port are checked (the port bound) before
           anything touches the robot: a start that fails here leaves no trace on the graph
           and writes no audit entry
    start: ROS node → audit log → navigation client → dispatcher → governor (BRIDGE_STARTED)
           → telemetry → HTTP API → mDNS advert
    stop:  mDNS withdrawn → API closed (no new commands) → robot halted (zero velocity,
           goals cancelled) → governor (BRIDGE_STOPPED) → audit closed → ROS node left
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import ssl
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from ..api import ApiServer, bind, build_app, cert_principals, server_ssl_context
from ..api.ports import GoalView
from ..config import RcanConfig
from ..governance import (
    AuditLog,
    Governor,
    Notifier,
    SystemClock,
    TokenAuthenticator,
    WebhookNotifier,
    load_private_key,
)
from ..rcan import Status
from ..ros.participant import RosNode
from ..ros.services import RequestMapping
from .commands import RosDispatcher
from .mdns import Advert, RcanAdvertiser
from .navigation import GoalTracker
from .notify import DiagnosticsNotifier, FanOutNotifier
from .telemetry import TelemetryState

log = logging.getLogger(__name__)


def nav_mapping(config: RcanConfig) -> RequestMapping:
    """The configured request-reply mapping of the navigation action (name override first)."""
    ros2 = config.bridge.ros2
    chosen = ros2.request_mappings.get(ros2.nav_action, ros2.request_mapping)
    return RequestMapping(chosen)


class BridgeView:
    """The `RobotView` the API reads: telemetry plus navigation goals."""

    def __init__(self, telemetry: TelemetryState, goals: GoalTracker) -> None:
        self.telemetry = telemetry
        self.goals_ = goals

    def status(self, *, pending_auth: int) -> Status:
        return self.telemetry.status(pending_auth=pending_auth)

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


class Bridge:
    def __init__(self, config: RcanConfig, options: BridgeOptions | None = None) -> None:
        self.config = config
        self.options = options or BridgeOptions()
        self.node: RosNode | None = None
        self.audit: AuditLog | None = None
        self.goals: GoalTracker | None = None
        self.dispatcher: RosDispatcher | None = None
        self.governor: Governor | None = None
        self.telemetry: TelemetryState | None = None
        self.server: ApiServer | None = None
        self.advertiser: RcanAdvertiser | None = None
        self._advert_task: asyncio.Task[None] | None = None
        self._authenticator: TokenAuthenticator | None = None
        self._ssl: ssl.SSLContext | None = None
        self._sock: socket.socket | None = None
        self.url = ""

    def prepare(self) -> None:
        """Check everything that can fail without the robot; bind the API port.

        Raises (AuthConfigError, AuditKeyError, OSError, ...) before the bridge joins the
        domain or writes an audit entry.
        """
        if self._sock is not None:
            return
        api, opts = self.config.bridge.api, self.options
        self._authenticator = TokenAuthenticator.from_config(
            api, self.config.bridge.rbac, opts.env, clock=SystemClock())
        self._ssl = server_ssl_context(api.tls) if api.tls else None
        key = Path(self.config.bridge.audit.key_path)
        if key.exists():
            load_private_key(key)  # unreadable, too open or not Ed25519: refuse now
        self._sock = bind(opts.host or api.host, api.port if opts.port is None else opts.port)

    async def start(self) -> str:
        """Brings the bridge up; returns the API's URL once it accepts commands."""
        self.prepare()
        bridge, opts = self.config.bridge, self.options
        ros2 = bridge.ros2
        self.node = RosNode(ros2.node_name, ros2.namespace or "/", domain_id=ros2.domain_id,
                            distro=ros2.distro, localhost=opts.localhost)
        self.audit = await AuditLog.open(bridge.audit.path, bridge.audit.key_path)
        self.goals = GoalTracker(self.node, ros2.nav_action, mapping=nav_mapping(self.config))
        self.dispatcher = RosDispatcher(self.node, ros2, self.goals,
                                        telemetry_age=self._telemetry_age)
        self.governor = Governor.from_config(self.config, audit=self.audit,
                                             dispatcher=self.dispatcher,
                                             notifier=self._notifier(self.node))
        self.telemetry = TelemetryState(self.node, self.config,
                                        estop_latched=lambda: self._latched(),
                                        active_goals=self.goals.active)
        self.governor.safe_stop_listeners.append(lambda _p: self._safe_stopped())
        self.dispatcher.on_command = self.telemetry.clear_safe_stop
        await self.governor.start()
        await self._serve()
        if opts.mdns:
            # Joining mDNS takes ~1 s (probing): commands are accepted meanwhile.
            self._advert_task = asyncio.create_task(self._advertise())
        return self.url

    def _telemetry_age(self) -> float | None:
        return self.telemetry.age_s() if self.telemetry is not None else None

    def _latched(self) -> bool:
        return self.governor is not None and self.governor.latch.latched

    def _safe_stopped(self) -> None:
        if self.telemetry is not None:
            self.telemetry.mark_safe_stop()

    def _notifier(self, node: RosNode) -> Notifier:
        ros2, hitl = self.config.bridge.ros2, self.config.bridge.hitl
        notifiers: list[Notifier] = [DiagnosticsNotifier(node, ros2.diagnostics_topic)]
        if hitl.notify_webhook:
            notifiers.append(WebhookNotifier(hitl.notify_webhook))
        return FanOutNotifier(notifiers)

    async def _serve(self) -> None:
        api, opts = self.config.bridge.api, self.options
        assert self.governor is not None and self.telemetry is not None and self.goals
        assert self._authenticator is not None and self._sock is not None
        app = build_app(governor=self.governor, authenticator=self._authenticator,
                        robot=BridgeView(self.telemetry, self.goals), config=self.config,
                        cert_principals=cert_principals(self.config) if api.tls else None)
        self.server = ApiServer(app, host=opts.host or api.host,
                                port=api.port if opts.port is None else opts.port,
                                ssl_context=self._ssl, sock=self._sock)
        self.url = await self.server.start()

    async def _advertise(self) -> None:
        assert self.server is not None
        api, opts = self.config.bridge.api, self.options
        host, port = opts.host or api.host, int(self.url.rsplit(":", 1)[1])
        tls = api.tls is not None

        def current() -> Advert:
            return Advert.for_server(self.config, host=host, port=port, tls=tls)

        self.advertiser = RcanAdvertiser(current(), interfaces=opts.mdns_interfaces)
        try:
            await self.advertiser.start()
        except Exception:  # no multicast here: the robot is still commandable by URL
            log.exception("mDNS advertisement failed")
            return
        self.advertiser.follow(current)  # re-announce when the address changes

    async def stop(self) -> None:
        """Graceful stop: each step runs even if an earlier one failed."""
        steps = [self._stop_mdns, self._stop_api, self._halt_robot, self._stop_governor,
                 self._stop_audit]
        for step in steps:
            try:
                await step()
            except Exception:
                log.exception("bridge shutdown: %s failed", step.__name__)
        if self.node is not None:
            self.node.close()
            self.node = None
        if self._sock is not None and self.server is None:
            self._sock.close()  # prepared but never served

    async def _stop_mdns(self) -> None:
        if self._advert_task is not None:
            await self._advert_task  # finish joining before saying goodbye
            self._advert_task = None
        if self.advertiser is not None:
            await self.advertiser.close()
            self.advertiser = None

    async def _stop_api(self) -> None:
        if self.server is not None:
            await self.server.close()
            self.server = None

    async def _halt_robot(self) -> None:
        if self.dispatcher is not None:
            await self.dispatcher.halt()
        if self.goals is not None:
            await self.goals.close()

    async def _stop_governor(self) -> None:
        if self.governor is not None:
            await self.governor.stop()

    async def _stop_audit(self) -> None:
        if self.audit is not None:
            with contextlib.suppress(Exception):
                await self.audit.close()
