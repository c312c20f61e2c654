"""The same tools at the bridge's own `/mcp` (streamable HTTP, the official SDK's transport).

The bridge's route (`rcan_rtps.api._mcp`) authenticates each request like any other, builds
its `Seat` — the principal's view of the bridge, the agent identity the request names, the
principal's heartbeats — and hands the request to `HttpMcp.handle` with that seat in the ASGI
scope. A session belongs to the principal that opened it: the SDK answers a request for it
with another credential as if the session did not exist (404). A principal holds at most
`MAX_SESSIONS_PER_PRINCIPAL` sessions, all principals `MAX_SESSIONS` (`sessions`: at its cap,
a principal's session idle longest is closed for its new one; at the cap over all, the
idle longest of the principal holding the most).

Responses are plain JSON, not an event stream per call: a tool call has one answer, and an
event stream would only add framing to each reply.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Mapping
from typing import Any

from mcp.server.auth.middleware.bearer_auth import AuthenticatedUser
from mcp.server.auth.provider import AccessToken
from mcp.server.context import ServerRequestContext
from mcp_types.version import HANDSHAKE_PROTOCOL_VERSIONS

from .seat import Seat
from .server import RobotTools, build_server
from .sessions import CappedSessions

SEAT = "rcan.seat"  # the ASGI scope key of a request's seat
MAX_SESSIONS = 256  # all principals' together
# One principal's (an agent and a few tools need a handful): far enough below MAX_SESSIONS
# that no principal alone, nor a few, fill the bridge's.
MAX_SESSIONS_PER_PRINCIPAL = 16
SESSION_IDLE_S = 30 * 60.0
Asgi = Any  # the ASGI callables, typed by the caller


def seat_of(ctx: ServerRequestContext[Any]) -> Seat:
    request = ctx.request
    seat = getattr(request, "scope", {}).get(SEAT)
    if not isinstance(seat, Seat):  # only the bridge's route calls in, always with a seat
        raise RuntimeError("an MCP request reached the tools without a seat")
    return seat


class HttpMcp:
    """One bridge's MCP sessions: `run` for the bridge's lifetime, `handle` per request."""

    def __init__(self, manifest: Mapping[str, Any], *, max_body_bytes: int) -> None:
        # The SDK's INFO lines (a line per session opened or closed, with its id) are not the
        # bridge's to log: the decisions are, in rcan_rtps.decisions.
        sdk_log = logging.getLogger("mcp")
        if sdk_log.level == logging.NOTSET:
            sdk_log.setLevel(logging.WARNING)
        self._tools = RobotTools(seat_of, manifest=manifest)
        server = build_server(self._tools)
        self._manager = CappedSessions(
            server, json_response=True, session_idle_timeout=SESSION_IDLE_S,
            max_request_body_size=max_body_bytes, max_sessions=MAX_SESSIONS,
            per_principal=MAX_SESSIONS_PER_PRINCIPAL)

    async def run(self, ready: asyncio.Event, stop: asyncio.Event) -> None:
        """Serve sessions until `stop`; then end them all (their open streams close)."""
        async with self._manager.run():
            ready.set()
            await stop.wait()

    async def handle(self, scope: Asgi, receive: Asgi, send: Asgi, seat: Seat,
                     principal: str, role: str) -> None:
        # The SDK binds a session to the credential that opened it (here: the principal).
        user = AuthenticatedUser(AccessToken(token="-", client_id=principal, scopes=[role]))
        await self._manager.handle_request({**scope, "user": user, SEAT: seat}, receive, send)

    def cancelled_by_hanging_up(self, headers: list[tuple[bytes, bytes]], body: bytes) -> bool:
        """The request is a motion tool's call (`tools/call` with an id) of a sessionless
        protocol (2026-07-28 on), whose client cancels it by closing the request: that wire
        has no `notifications/cancelled`. Read as the SDK reads it (the last of a repeated
        key); what it cannot read it refuses, and is no such call."""
        if not _modern(headers):
            return False
        try:
            message = json.loads(body)
        except (ValueError, RecursionError):  # not JSON, not text, nested too deep
            return False
        if not isinstance(message, dict) or message.get("method") != "tools/call" \
                or message.get("id") is None:
            return False
        params = message.get("params")
        name = params.get("name") if isinstance(params, dict) else None
        return isinstance(name, str) and self._tools.is_motion(name)


def _modern(headers: list[tuple[bytes, bytes]]) -> bool:
    """A request of a sessionless protocol (2026-07-28 on), as the SDK routes requests."""
    version = next((v.decode("latin-1") for k, v in headers
                    if k.lower() == b"mcp-protocol-version"), None)
    return version is not None and version not in HANDSHAKE_PROTOCOL_VERSIONS
