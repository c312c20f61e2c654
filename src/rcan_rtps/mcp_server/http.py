"""The same tools at the bridge's own `/mcp` (streamable HTTP, the official SDK's transport).

The bridge's route (`rcan_rtps.api._mcp`) authenticates each request like any other, builds
its `Seat` — the principal's view of the bridge, the agent identity the request names, the
principal's heartbeats — and hands the request to `HttpMcp.handle` with that seat in the ASGI
scope. A session belongs to the principal that opened it: the SDK answers a request for it
with another credential as if the session did not exist (404).

Responses are plain JSON, not an event stream per call: a tool call has one answer, and an
event stream would only add framing to each reply.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Mapping
from typing import Any

import mcp_types as types
from mcp.server.auth.middleware.bearer_auth import AuthenticatedUser
from mcp.server.auth.provider import AccessToken
from mcp.server.context import ServerRequestContext
from mcp.server.streamable_http_manager import StreamableHTTPSessionManager
from mcp_types.jsonrpc import INVALID_REQUEST

from .seat import Seat
from .server import RobotTools, build_server

SEAT = "rcan.seat"  # the ASGI scope key of a request's seat
NOT_SERVED = ("a JSON-RPC batch is not served (MCP has had none since 2025-06-18): only the "
              "stops in it were run")
MAX_SESSIONS = 256
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
        self._manager = StreamableHTTPSessionManager(
            server, json_response=True, session_idle_timeout=SESSION_IDLE_S,
            max_request_body_size=max_body_bytes, max_sessions=MAX_SESSIONS)

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

    async def stop_batch(self, seat: Seat, batch: list[Any]) -> list[dict[str, Any]]:
        """A JSON-RPC batch's replies, in order: each stopping tool call run as its tool runs
        it and answered with the tool's result; every other request refused (the SDK refuses
        a batch whole, and a stop in one must still stop). A notification gets no reply,
        though a stop in one is run."""
        replies: list[dict[str, Any]] = []
        for member in batch:
            done = await self._batched_stop(seat, member)
            if not isinstance(member, dict) or "id" not in member:
                if not isinstance(member, dict):  # not even a message: JSON-RPC's -32600
                    replies.append(_error(None, NOT_SERVED))
                continue
            if done is None:
                replies.append(_error(member["id"], NOT_SERVED))
            else:
                replies.append({"jsonrpc": "2.0", "id": member["id"], "result": done.model_dump(
                    mode="json", by_alias=True, exclude_none=True)})
        return replies

    async def _batched_stop(self, seat: Seat, member: Any) -> types.CallToolResult | None:
        """The result of `member` if it is a stopping tool's call (run), else None."""
        if not isinstance(member, dict) or member.get("method") != "tools/call":
            return None
        params = member.get("params")
        if not isinstance(params, dict) or not isinstance(params.get("name"), str):
            return None
        args = params.get("arguments")
        return await self._tools.stop(seat, params["name"], args if isinstance(args, dict)
                                      else {}, "unknown")


def _error(request_id: Any, message: str) -> dict[str, Any]:
    return {"jsonrpc": "2.0", "id": request_id,
            "error": {"code": INVALID_REQUEST, "message": message}}
