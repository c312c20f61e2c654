"""`/mcp`: the MCP tools served by the bridge itself (streamable HTTP, bearer token).

Authenticated like every API route (the `authenticate` middleware runs first: no principal,
no MCP). The official SDK (`rcan-rtps[mcp]`) is imported on the first request to `/mcp`, so
a bridge nobody asks for MCP never loads it; without the extra, `/mcp` answers 501 saying
what to install. Each request runs as its principal (`_local.LocalApi`: the REST routes'
own functions), naming the agent's model from its `RCAN-AI-Provider` and `RCAN-AI-Model`
headers (or the `ai_provider` and `ai_model` query parameters, for clients that can set no
header but `Authorization`). A principal's timed moves and goals are held by heartbeats
while they run; a session the client closes (DELETE) stops what it left running.

A stop stops whatever else is wrong with its request (`stop_rescue`): a `tools/call` of a
stopping tool (`estop`, `stop`: the registry's ESTOP and HALT actions) whose body the SDK's
JSON parser refuses (an unpaired surrogate escape, an integer of more digits than Python
reads) is read leniently (`rcan._salvage.read_leniently`) and handed to the SDK as strict
JSON; the stops of a JSON-RPC batch (which the SDK refuses whole) are run here. Either way
the stop carries what was wrong as `warnings`, in its tool result and its audit entry. Any
other body the SDK answers as it would.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
from typing import TYPE_CHECKING, Any, NamedTuple

import msgspec
from aiohttp import web

from rcan_rtps.config import RcanConfig
from rcan_rtps.governance import Principal
from rcan_rtps.rcan._salvage import read_leniently
from rcan_rtps.rcan.actions import specs

from ._bodies import error_response, json_response
from ._commands import read_limited, too_large
from ._keys import GOVERNOR, PRINCIPAL, SETTINGS

if TYPE_CHECKING:
    from rcan_rtps.mcp_server.http import HttpMcp
    from rcan_rtps.mcp_server.keepalive import Keepalive
    from rcan_rtps.mcp_server.seat import Agent, Seat

log = logging.getLogger(__name__)
SESSION_HEADER = "Mcp-Session-Id"
IDENTITY_MAX = 256
EXTRA_HINT = "MCP needs the SDK on the bridge: pip install 'rcan-rtps[mcp]'"


def agent_of(request: web.Request) -> Agent:
    """The model the request's agent names (headers first, then the query)."""
    from rcan_rtps.mcp_server.seat import Agent

    def named(header: str, query: str) -> str | None:
        value = request.headers.get(header) or request.query.get(query)
        # Not UTF-8 (aiohttp keeps such bytes as surrogates, which no audit line can hold) or
        # unprintable: no name at all, so the command is refused as naming no model.
        usable = value and value.strip() and value.isprintable() and len(value) <= IDENTITY_MAX
        return value if usable else None

    return Agent(named("RCAN-AI-Provider", "ai_provider"), named("RCAN-AI-Model", "ai_model"))


class Rescue(NamedTuple):
    """A request that says stop though the SDK would not run it: the body to hand the SDK
    (strict JSON), what was wrong (the stops' warnings), and a batch's members (run here)."""

    body: bytes
    warnings: tuple[str, ...]
    batch: list[Any] | None = None


def stop_rescue(body: bytes) -> Rescue | None:
    """What makes the stop in `body` stop; None when the SDK runs it as it is (or it holds
    no stop, and the SDK answers it as it would: -32700 for what it cannot parse)."""
    warnings: tuple[str, ...] = ()
    try:
        message = msgspec.json.decode(body)
    except (msgspec.DecodeError, ValueError, RecursionError):  # ValueError: not UTF-8
        read = read_leniently(body)
        if read is None:
            return None
        message = read.value
        warnings = (read.problem("$: the JSON-RPC body is not strict JSON"),)
    if isinstance(message, list):
        if not any(_calls_a_stop(member) for member in message):
            return None
        return Rescue(body, (*warnings, "$: a JSON-RPC batch: only its stops were run"),
                      message)
    if not warnings or not _calls_a_stop(message):
        return None
    return Rescue(msgspec.json.encode(message), warnings)


def _calls_a_stop(message: Any) -> bool:
    """A JSON-RPC `tools/call` of a stopping tool (each registry action is its tool)."""
    if not isinstance(message, dict) or message.get("method") != "tools/call":
        return False
    params = message.get("params")
    name = params.get("name") if isinstance(params, dict) else None
    return any(spec.stopping and spec.name == name for spec in specs())


class McpEndpoint:
    """The route's handler; `close` at the bridge's shutdown."""

    def __init__(self, config: RcanConfig) -> None:
        self._config = config
        self._fixed: dict[str, Any] | None = None
        self._server: HttpMcp | None = None
        self._missing = False
        self._starting: asyncio.Lock | None = None
        self._stop = asyncio.Event()
        self._serving: asyncio.Task[None] | None = None
        self._beating: list[asyncio.Task[None]] = []
        self._keepalives: dict[str, Keepalive] = {}
        self._stopping: set[asyncio.Task[None]] = set()

    async def handle(self, request: web.Request) -> web.StreamResponse:
        # What serves MCP (here and in the SDK) is imported by the first request to /mcp:
        # a bridge nobody asks for MCP keeps its idle memory (issue 27).
        from . import _asgi

        server = await self._started(request.app)
        if server is None:
            return error_response(501, "NOT_IMPLEMENTED", reason=EXTRA_HINT)
        app, principal = request.app, request[PRINCIPAL]
        settings = app[SETTINGS]
        body = await read_limited(request, settings.max_body_bytes, settings.body_timeout_s)
        if body is None:
            status, refused = await too_large(app[GOVERNOR], principal)
            return json_response(refused, status)
        rescue = stop_rescue(body) if request.method == "POST" else None
        seat = self._seat(app, principal, agent_of(request), request.headers.get(SESSION_HEADER),
                          () if rescue is None else rescue.warnings)
        if rescue is not None:
            if rescue.batch is not None:
                replies = await server.stop_batch(seat, rescue.batch)
                return json_response(replies) if replies else web.Response(status=202)
            body = rescue.body

        async def run(scope: Any, receive: Any, send: Any) -> None:
            await server.handle(scope, receive, send, seat, principal.name, principal.role.name)

        response = await _asgi.serve(run, request, body, {})
        if response is None:
            return error_response(503, "ROBOT_UNAVAILABLE", outcome="failed",
                                  reason="mcp_no_response")
        if request.method == "DELETE" and response.status < 300 and seat.session:
            await self._session_closed(seat)
        return response

    def _seat(self, app: web.Application, principal: Principal, agent: Agent,
              session: str | None, warnings: tuple[str, ...]) -> Seat:
        from rcan_rtps.mcp_server.keepalive import Keepalive
        from rcan_rtps.mcp_server.seat import Seat

        from ._local import LocalApi

        assert self._fixed is not None
        api = LocalApi(app, principal, self._fixed, warnings)
        keepalive = self._keepalives.get(principal.name)
        if keepalive is None:  # one per principal: heartbeats are a principal's
            keepalive = self._keepalives[principal.name] = Keepalive(LocalApi(
                app, principal, self._fixed))
            self._beating.append(asyncio.create_task(keepalive.run(),
                                                     name=f"mcp-keepalive-{principal.name}"))
        return Seat(api, agent, keepalive, session)

    async def _session_closed(self, seat: Seat) -> None:
        """The client closed its session: stop what it started that still runs."""
        from rcan_rtps.mcp_server.server import stop_left_running

        assert seat.session is not None
        if seat.keepalive.release_session(seat.session):
            # A client may hang up before the DELETE is answered (the SDK's does, when its exit
            # is cancelled): the stop is the door's task, not the request's, so it goes on.
            stopping = asyncio.create_task(stop_left_running(seat, "MCP session closed"),
                                           name="mcp-session-closed-stop")
            self._stopping.add(stopping)
            stopping.add_done_callback(self._stopping.discard)
            await asyncio.shield(stopping)

    async def _started(self, app: web.Application) -> HttpMcp | None:
        if self._server is not None or self._missing:
            return self._server
        if self._starting is None:
            self._starting = asyncio.Lock()
        async with self._starting:
            if self._server is None and not self._missing:
                self._server = await self._start(app)
        return self._server

    async def _start(self, app: web.Application) -> HttpMcp | None:
        try:
            from rcan_rtps.mcp_server.http import HttpMcp
        except ModuleNotFoundError as exc:
            if exc.name is None or exc.name.split(".")[0] not in ("mcp", "mcp_types"):
                raise
            log.warning("a client asked for MCP: %s", EXTRA_HINT)
            self._missing = True
            return None
        from ._safety_manifest import static_part

        self._fixed = static_part(self._config)
        server = HttpMcp(self._fixed, max_body_bytes=app[SETTINGS].max_body_bytes)
        # The SDK's modules (pydantic's schemas: tens of thousands of objects) live as long as
        # the bridge: out of the collector's sight, like what start-up built (`run`), so that a
        # collection during a command does not scan them all (ms pauses, measured).
        gc.freeze()
        ready = asyncio.Event()
        self._serving = serving = asyncio.create_task(server.run(ready, self._stop), name="mcp")
        waiting = asyncio.create_task(ready.wait())
        await asyncio.wait([serving, waiting], return_when=asyncio.FIRST_COMPLETED)
        waiting.cancel()
        if serving.done():
            serving.result()  # it failed to start: raise why (the request is answered 503)
        return server

    async def close(self) -> None:
        """End every session (their streams close), then the heartbeats: the bridge is
        shutting down, and stops the robot itself."""
        self._stop.set()
        if self._stopping:  # a closed session's stop still on its way
            await asyncio.wait(list(self._stopping))
        if self._serving is not None:
            await asyncio.wait([self._serving])
        for task in self._beating:
            task.cancel()
        for task in self._beating:
            with contextlib.suppress(asyncio.CancelledError):
                await task
