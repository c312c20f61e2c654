"""`build_app`: the aiohttp application in front of the governor."""

from __future__ import annotations

from collections import Counter
from collections.abc import AsyncIterator, Callable, Mapping
from typing import TYPE_CHECKING

import msgspec
from aiohttp import WSCloseCode, web

from rcan_rtps.config import RcanConfig
from rcan_rtps.governance import Clock, Governor, Principal, SystemClock
from rcan_rtps.governance.clock import latest_wall
from rcan_rtps.governance.replay import ReplayWindow
from rcan_rtps.governance.signatures import Signatures
from rcan_rtps.rcan import Role

from . import _node_manifest
from . import _routes as r
from ._approvals import ApprovalsFeed
from ._conn import ConnectionDeadlines, track_requests
from ._console import add_console, is_console_path
from ._goal_events import GoalEvents
from ._images import NO_IMAGES
from ._intake import Checks
from ._keys import (
    APPROVALS,
    AUTHENTICATOR,
    CERT_PRINCIPALS,
    CHECKS,
    CREDENTIAL_LEFT,
    DEADLINES,
    GOAL_EVENTS,
    GOVERNOR,
    IMAGES,
    INVOCATIONS,
    OBSERVE,
    READS,
    ROBOT,
    SETTINGS,
    SOCKETS,
    SOCKETS_OF,
    STATUS,
    WS_TICKETS,
    ApiSettings,
    Authenticator,
)
from ._lazy import FirstUse, Handler, on_first_request
from ._metrics import Metrics
from ._middlewares import authenticate, last_resort, safe_headers
from ._skills import Skills
from ._status import StatusHub
from ._tickets import WsTickets
from ._tls import cert_principals as config_cert_principals
from .ports import ImageSource, RobotView

if TYPE_CHECKING:
    from ._mcp import McpEndpoint
    from ._reads import AuditReads

MCP_PATH = "/mcp"  # the MCP streamable-HTTP door (`_mcp`)
# Routes an idle bridge is rarely asked for, and that no command or stop takes: their
# handlers (`_rare_routes`) are loaded by the first request to any of them (issue 27).
RARE_ROUTES = (
    ("GET", "/api/skills", "get_skills"),
    ("GET", "/api/images", "get_images"),
    ("GET", "/api/images/{name}", "get_image"),
    ("GET", "/api/thoughts/{thought_id}", "get_thought"),
    ("GET", "/api/hitl/pending", "get_pending"),
    ("GET", "/api/hitl/pending/{pending_id}", "get_pending_one"),
    ("POST", "/api/hitl/authorize", "post_authorize"),
    ("POST", "/api/hitl/deny", "post_deny"),
    ("POST", "/api/hitl/withdraw", "post_withdraw"),
    ("GET", "/api/audit", "get_audit"),
    ("GET", "/api/audit/verify", "get_audit_verify"),
    ("GET", "/api/audit/mine", "get_my_audit"),
)


def settings_from_config(config: RcanConfig) -> ApiSettings:
    bridge = config.bridge
    approver = Role[bridge.rbac.hitl_approver_role]
    gate_roles = [Role[name] for g in bridge.hitl.gates for name in g.authorized_roles]
    return ApiSettings(
        max_body_bytes=bridge.api.max_body_bytes,
        header_timeout_s=bridge.api.header_timeout_s,
        body_timeout_s=bridge.api.body_timeout_s,
        keepalive_timeout_s=bridge.api.keepalive_timeout_s,
        telemetry_rate_hz=bridge.ros2.telemetry_rate_hz,
        audit_read_role=Role[bridge.rbac.audit_read_role],
        # Pending commands are for whoever could approve one of them.
        hitl_list_role=min([approver, *gate_roles]),
    )


def credential_left(clock: Clock) -> Callable[[Principal], float | None]:
    """`CREDENTIAL_LEFT`: judged as the JWT verifier judges `exp`, by the latest wall time."""
    latest = latest_wall(clock)

    def left(principal: Principal) -> float | None:
        expires = principal.expires_at
        return None if expires is None else expires - latest.time()

    return left


def message_checks(config: RcanConfig, clock: Clock,
                   signatures: Signatures | None = None) -> Checks:
    """§8.3's window, and the principals' signature keys and policies (loaded from the config
    unless given: raises AuthConfigError for a key that does not load)."""
    security = config.bridge.security
    return Checks(replay=ReplayWindow(clock, window_s=security.replay_window_s,
                                      ahead_s=security.clock_ahead_s,
                                      max_entries=security.msg_id_cache_size),
                  signatures=signatures or Signatures.from_config(config.bridge.api))


def build_app(*, governor: Governor, authenticator: Authenticator, robot: RobotView,
              config: RcanConfig, cert_principals: Mapping[str, Principal] | None = None,
              settings: ApiSettings | None = None, clock: Clock | None = None,
              signatures: Signatures | None = None,
              images: ImageSource | None = None) -> web.Application:
    """The API. It never starts or stops the governor: whoever built that owns its lifetime.

    `cert_principals` maps a client certificate's subject CN to a principal (mTLS); by default
    the configured principals, by name, when `api.tls.client_ca` is set. `clock` is the wall
    clock RCAN 3.x message timestamps are held against (§8.3). `signatures`: the principals'
    signing keys, already loaded (else loaded from `config`). `images`: the configured camera
    topics (`bridge.ros2.images`), if any.
    """
    settings = settings or settings_from_config(config)
    # aiohttp's own limit backs ours up for any body read outside `read_limited`.
    deadlines = ConnectionDeadlines(header_timeout_s=settings.header_timeout_s,
                                    keepalive_timeout_s=settings.keepalive_timeout_s)
    app = web.Application(middlewares=[track_requests(deadlines), last_resort(),
                                       authenticate(frozenset({_node_manifest.PATH}),
                                                    static=is_console_path)],
                          client_max_size=settings.max_body_bytes,
                          # Bodies are decoded by `read_limited`, which answers a bad one.
                          handler_args={"auto_decompress": False})
    app.on_response_prepare.append(safe_headers)
    app[DEADLINES] = deadlines  # ApiServer serves connections through it
    app[GOVERNOR] = governor
    app[AUTHENTICATOR] = authenticator
    app[CHECKS] = checks = message_checks(config, clock or SystemClock(), signatures)
    if checks.replay is not None:  # a restart must not forget what could be replayed
        checks.replay.remember_logged(governor.audit.path)
    app[ROBOT] = robot
    app[SETTINGS] = settings
    app[CERT_PRINCIPALS] = dict(config_cert_principals(config) if cert_principals is None
                                else cert_principals)
    sockets: set[web.WebSocketResponse] = set()
    app[SOCKETS] = sockets
    app[SOCKETS_OF] = Counter()
    app[READS] = reads = FirstUse(lambda: _audit_reads(governor, settings))
    app[STATUS] = status = StatusHub(
        lambda: robot.status(pending_auth=len(governor.pending())),
        period_s=1.0 / settings.telemetry_rate_hz)
    app.cleanup_ctx.append(_status_owner(status, governor, robot))
    app[GOAL_EVENTS] = goal_events = GoalEvents()
    robot.watch_goals(goal_events.offer)
    app[INVOCATIONS] = Skills(config.bridge.skills, robot, governor.events)
    app[IMAGES] = images or NO_IMAGES
    app[WS_TICKETS] = WsTickets((clock or SystemClock()).monotonic)
    app[CREDENTIAL_LEFT] = credential_left(clock or SystemClock())
    app[APPROVALS] = approvals = ApprovalsFeed(governor.pending)
    app.cleanup_ctx.append(_approvals_feed(approvals, governor))
    metrics = Metrics(governor, status)
    app[OBSERVE] = metrics.command_seconds.observe

    async def get_metrics(request: web.Request) -> web.Response:
        # Prometheus text format; scrape with the bearer token of any principal.
        return web.Response(body=metrics.render(),
                            headers={"Content-Type": metrics.content_type})

    document: list[bytes] = []  # built on the first request: most runs are never asked

    async def get_openapi(request: web.Request) -> web.Response:
        if not document:
            from ._openapi import openapi_document  # with the document: a run may never need it

            document.append(msgspec.json.encode(openapi_document()))
        return web.Response(body=document[0], content_type="application/json")

    app.router.add_post("/api/command", r.post_command)
    app.router.add_post("/api/command/cancel", r.post_command_cancel)
    app.router.add_get("/api/status", r.get_status, allow_head=False)
    app.router.add_post("/api/heartbeat", r.post_heartbeat)
    app.router.add_get("/api/goals", r.get_goals, allow_head=False)
    app.router.add_get("/api/goals/{goal_id}", r.get_goal, allow_head=False)
    for method, path, name in RARE_ROUTES:
        app.router.add_route(method, path, _rare(name))
    app.router.add_get("/api/openapi.json", get_openapi, allow_head=False)
    app.router.add_get("/api/ws", on_first_request(_websocket_handler), allow_head=False)
    app.router.add_get("/api/metrics", get_metrics, allow_head=False)
    # RCAN 3.x: §17 node manifest (public), Protocol 66 safety manifest, §20 audit export.
    app.router.add_get(_node_manifest.PATH, _node_manifest.handler(
        config, governor.audit.public_key), allow_head=False)
    app.router.add_get(_node_manifest.SAFETY_MANIFEST, on_first_request(
        lambda: _safety_manifest_handler(config)), allow_head=False)
    app.router.add_get(_node_manifest.AUDIT_EXPORT, on_first_request(
        lambda: _audit_export_handler(governor, settings.audit_read_role)), allow_head=False)
    mcp = McpDoor(config)
    for method in ("POST", "GET", "DELETE"):  # streamable HTTP's three
        app.router.add_route(method, MCP_PATH, mcp.handle)

    async def close_mcp(app: web.Application) -> None:
        await mcp.close()

    add_console(app)  # the operator console (/, /console/) and what it asks the API
    app.on_shutdown.append(_close_sockets)
    app.on_shutdown.append(close_mcp)

    async def close_reads(app: web.Application) -> None:
        if reads.made is not None:
            await reads.made.close()

    app.on_cleanup.append(close_reads)
    return app


class McpDoor:
    """/mcp: its endpoint (`_mcp`), and the modules serving it, are made by the first request
    (most runs are never asked for MCP); `close` at shutdown closes it if it was."""

    def __init__(self, config: RcanConfig) -> None:
        self._config = config
        self.endpoint: McpEndpoint | None = None

    async def handle(self, request: web.Request) -> web.StreamResponse:
        if self.endpoint is None:
            from ._mcp import McpEndpoint

            self.endpoint = McpEndpoint(self._config)
        return await self.endpoint.handle(request)

    async def close(self) -> None:
        if self.endpoint is not None:
            await self.endpoint.close()


def _audit_reads(governor: Governor, settings: ApiSettings) -> AuditReads:
    from ._reads import AuditReads

    return AuditReads(governor.audit.path, governor.audit.public_key,
                      backlog=settings.audit_read_backlog,
                      page_bytes=settings.audit_page_bytes)


def _rare(name: str) -> Handler:
    """The handler `name` of `_rare_routes`, made by its first request."""
    def build() -> Handler:
        from . import _rare_routes

        handler: Handler = getattr(_rare_routes, name)
        return handler

    return on_first_request(build)


def _websocket_handler() -> Handler:
    from ._ws import websocket  # most runs never open a WebSocket

    return websocket


def _safety_manifest_handler(config: RcanConfig) -> Handler:
    from . import _safety_manifest

    return _safety_manifest.handler(config)


def _audit_export_handler(governor: Governor, read_role: Role) -> Handler:
    from . import _audit_export  # and csv

    return _audit_export.handler(governor, read_role)


def _status_owner(status: StatusHub, governor: Governor, robot: RobotView
                  ) -> Callable[[web.Application], AsyncIterator[None]]:
    async def owner(app: web.Application) -> AsyncIterator[None]:
        await status.start()
        governor.events.governance.subscribe(status.changed)  # a no-op once it closed
        robot.watch(status.changed)
        yield
        await status.close()

    return owner


def _approvals_feed(approvals: ApprovalsFeed, governor: Governor
                    ) -> Callable[[web.Application], AsyncIterator[None]]:
    async def feed(app: web.Application) -> AsyncIterator[None]:
        approvals.start()
        governor.events.governance.subscribe(approvals.changed)  # a no-op once it closed
        yield
        approvals.close()

    return feed


async def _close_sockets(app: web.Application) -> None:
    sockets = app[SOCKETS]
    for ws in list(sockets):
        await ws.close(code=WSCloseCode.GOING_AWAY, message=b"bridge shutting down")
