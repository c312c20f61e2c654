"""Typed application and request state of the API (aiohttp `AppKey` / `RequestKey`)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Protocol

import msgspec
from aiohttp import web

from rcan_rtps.governance import Governor, Principal
from rcan_rtps.rcan import Role

from ._approvals import ApprovalsFeed
from ._conn import ConnectionDeadlines
from ._goal_events import GoalEvents
from ._intake import Checks
from ._lazy import FirstUse
from ._skills import Skills
from ._status import StatusHub
from ._tickets import WsTickets
from .ports import ImageSource, RobotView

if TYPE_CHECKING:
    from ._reads import AuditReads


class Authenticator(Protocol):
    """Bearer credential → principal; raises `AuthenticationError` (TokenAuthenticator does)."""

    def authenticate(self, bearer: str | None) -> Principal: ...


HEADER_TIMEOUT_S = 10.0
BODY_TIMEOUT_S = 30.0
KEEPALIVE_TIMEOUT_S = 30.0


class ApiSettings(msgspec.Struct, frozen=True, kw_only=True):
    """What the handlers need from the config, resolved once when the app is built."""

    max_body_bytes: int
    telemetry_rate_hz: float
    audit_read_role: Role
    hitl_list_role: Role
    ws_max_in_flight: int = 32
    audit_page_max: int = 1000
    audit_page_bytes: int = 4 * 1024 * 1024  # entries together (`_reads.PAGE_BYTES`)
    # Slow or silent peers (see `_conn` and `read_limited`); config: bridge.api.*_timeout_s.
    header_timeout_s: float = HEADER_TIMEOUT_S
    body_timeout_s: float = BODY_TIMEOUT_S
    keepalive_timeout_s: float = KEEPALIVE_TIMEOUT_S
    # Stops of one WebSocket decided at once; beyond this the socket's reader waits.
    stop_lane_width: int = 4
    # GET /api/audit pages waiting for the reader thread; beyond this: 429 `reads_busy`.
    audit_read_backlog: int = 8


GOVERNOR = web.AppKey("governor", Governor)
ROBOT = web.AppKey("robot", RobotView)
STATUS = web.AppKey("status", StatusHub)  # the one STATUS owner of every transport
GOAL_EVENTS = web.AppKey("goal_events", GoalEvents)  # goal changes, for the WebSocket
AUTHENTICATOR = web.AppKey("authenticator", Authenticator)
CERT_PRINCIPALS = web.AppKey("cert_principals", Mapping[str, Principal])
SETTINGS = web.AppKey("settings", ApiSettings)
SOCKETS = web.AppKey("sockets", set[web.WebSocketResponse])
SOCKETS_OF = web.AppKey("sockets_of", Counter[str])  # open WebSockets per principal (`_ws`)
DEADLINES = web.AppKey("connection_deadlines", ConnectionDeadlines)
# The audit log's readers (`_reads`), made by the first read: most runs are never asked.
READS: web.AppKey[FirstUse[AuditReads]] = web.AppKey("audit_reads")
CHECKS = web.AppKey("message_checks", Checks)  # §8.3 (and signatures) of RCAN 3.x messages
IMAGES = web.AppKey("images", ImageSource)  # bridge.ros2.images (none: an empty source)
INVOCATIONS = web.AppKey("invocations", Skills)  # bridge.skills and INVOKEs under way
WS_TICKETS = web.AppKey("ws_tickets", WsTickets)  # how a browser opens the WebSocket
APPROVALS = web.AppKey("approvals", ApprovalsFeed)  # held commands, for approvers' sockets
# Seconds left on a principal's credential (`Principal.expires_at`), by the latest wall time
# read (a step back gives an expired JWT no more time); None: it does not expire.
CREDENTIAL_LEFT: web.AppKey[Callable[[Principal], float | None]] = web.AppKey(
    "credential_left")
# Seconds per decided command, reported to the metrics (a no-op where there are none).
OBSERVE: web.AppKey[Callable[[float], None]] = web.AppKey("observe_command_seconds")

PRINCIPAL = web.RequestKey("principal", Principal)
