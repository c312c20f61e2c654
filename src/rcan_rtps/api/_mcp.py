"""`/mcp`: the MCP tools served by the bridge itself (streamable HTTP, bearer token).

Authenticated like every API route (the `authenticate` middleware runs first: no principal,
no MCP). The official SDK (`rcan-rtps[mcp]`) is imported on the first request to `/mcp`, so
a bridge nobody asks for MCP never loads it; without the extra, `/mcp` answers 501 saying
what to install (a stop excepted: see below). Each request runs as its principal
(`_local.LocalApi`: the REST routes' own functions), naming the agent's model from its
`RCAN-AI-Provider` and `RCAN-AI-Model` headers (or the `ai_provider` and `ai_model` query
parameters, for clients that can set no header but `Authorization`). A principal's timed
moves and goals are held by heartbeats while they run (and while its latest credential
holds); a session the client closes (DELETE) stops what it left running. No request is served
past its credential (`_asgi.serve`'s `left`): an event stream open when it runs out ends, a
call answered after that is answered 401.

A stop stops whatever else is wrong with its request (`mcp_server.stops.stop_rescue`, which
the stdio door shares): a `tools/call` that says stop (`estop`, `stop`: the registry's ESTOP
and HALT actions, spelt as REST forgives) is handed to the SDK as it takes it — strict JSON
(`rcan._salvage.read_leniently` reads what its parser refuses), the tool's own name, object
arguments — and its answer held back: if the stop did not reach the bridge (the SDK refused
it: no valid session over the 2025 protocol, a header that disagrees with the body, ...), it
is run here, as the authenticated principal, and answered with its tool result. A
notification's stop and the stops of a JSON-RPC batch (which the SDK refuses whole) are run
here too, and so is every stop while the SDK is not installed, fails to start or fails the
call (`mcp_server.stop_tool`: no SDK import). A server of the SDK's that ends before the
bridge does is said once in the log and started again by the next request. The stop carries
what was wrong as `warnings`, in its tool result and its audit entry. Any other body the SDK
answers as it would, its session checks included. A body too large (over `max_body_bytes`,
or a stop over `STOP_ROOM` times it) is refused 413 as a JSON-RPC error, which an MCP client
shows.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import gc
import importlib
import importlib.util
import json
import logging
from typing import TYPE_CHECKING, Any

from aiohttp import web

from rcan_rtps.config import RcanConfig
from rcan_rtps.governance import Principal
from rcan_rtps.mcp_server.stops import (
    INVALID_REQUEST,
    Rescue,
    StopCall,
    not_served,
    stop_call,
    stop_rescue,
)

from ._bodies import error_response, json_response
from ._commands import read_command, too_large
from ._errors import BodyEncoding
from ._intake import CLIENT_CLOSED, STOP_ROOM, oversize_warning
from ._keys import CREDENTIAL_LEFT, DEADLINES, GOVERNOR, PRINCIPAL, SETTINGS

if TYPE_CHECKING:
    from rcan_rtps.mcp_server.http import HttpMcp
    from rcan_rtps.mcp_server.keepalive import Keepalive
    from rcan_rtps.mcp_server.seat import Agent, Seat

    from . import _asgi
    from ._local import LocalApi

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


def _failure(exc: BaseException) -> str:
    """An exception of the SDK's, in one line (the log keeps no traceback of a library's
    failure it recovers from; a group names its first)."""
    inner = getattr(exc, "exceptions", None)
    if inner:
        return _failure(inner[0])
    said = str(exc).splitlines()[0][:200] if str(exc) else ""
    return f"{type(exc).__name__}: {said}" if said else type(exc).__name__


def _named(request: web.Request, name: str) -> list[tuple[bytes, bytes]]:
    """The request's headers (as ASGI has them) with `Mcp-Name`, if sent, naming the tool as
    the body now does (the SDK refuses a call whose header and body disagree)."""
    return [(k.lower(), name.encode() if k.lower() == b"mcp-name" else v)
            for k, v in request.raw_headers]


def _too_large_error(refused: Any, limit: int) -> dict[str, Any]:
    """A body too large, answered as a JSON-RPC error (the request's id unread), the bridge's
    refusal its `data`: an MCP client shows its message (the SDK's client says only "Server
    returned an error response" of a 413 that is no JSON-RPC error) — an agent whose e-stop
    was refused learns that nothing stopped, and how to send it."""
    message = (f"PAYLOAD_TOO_LARGE: the request is over what the bridge takes ({limit} bytes, "
               "its max_body_bytes) and is no stop it could read (an estop or stop is taken "
               "at any size, unless its shape alone, a huge list, is over "
               f"{limit * STOP_ROOM}): nothing was done (no stop either): send it smaller "
               "(a stop without its arguments)")
    return {"jsonrpc": "2.0", "id": None,
            "error": {"code": INVALID_REQUEST, "message": message, "data": refused}}


def _refusal(answered: Any) -> str:
    """What the SDK answered a stop it did not run, as the stop's warning."""
    if answered is None:
        return "$: the MCP server did not answer the call: the bridge ran the stop"
    error = None
    with contextlib.suppress(ValueError):
        error = json.loads(answered.body).get("error")
    said = f": {error.get('message')}" if isinstance(error, dict) else ""
    return (f"$: the MCP server refused the call (HTTP {answered.status}{said}): the bridge "
            "ran the stop")


class McpEndpoint:
    """The route's handler; `close` at the bridge's shutdown."""

    def __init__(self, config: RcanConfig) -> None:
        self._config = config
        self._fixed: dict[str, Any] | None = None
        self._server: HttpMcp | None = None
        self._missing = False
        self._starting: asyncio.Task[HttpMcp | None] | None = None
        self._stop = asyncio.Event()
        self._serving: asyncio.Task[None] | None = None
        self._beating: list[asyncio.Task[None]] = []
        self._keepalives: dict[str, Keepalive] = {}
        self._heartbeats: dict[str, LocalApi] = {}  # what each keepalive heartbeats through
        self._stopping: set[asyncio.Task[None]] = set()

    async def handle(self, request: web.Request) -> web.StreamResponse:
        # What serves MCP (here and in the SDK) is imported by the first request to /mcp:
        # a bridge nobody asks for MCP keeps its idle memory (issue 27).
        from . import _asgi

        app, principal = request.app, request[PRINCIPAL]
        settings = app[SETTINGS]
        limit = settings.max_body_bytes
        try:  # (held up to STOP_ROOM times the limit, skimmed past it: only a stop may be)
            read = await read_command(request, limit, settings.body_timeout_s)
        except BodyEncoding as exc:  # a stop in bytes its header misnames still stops
            found = stop_rescue(exc.raw) if request.method == "POST" else None
            if found is None:
                raise
            said = f"$: {exc.reason}: read as sent"
            return await self._stopping_call(request, found._replace(
                warnings=(said, *found.warnings)))
        rescue = stop_rescue(read.data) if read is not None and request.method == "POST" \
            else None
        oversize = read is not None and (read.skimmed is not None or len(read.data) > limit)
        if read is None or (oversize and rescue is None):
            status, refused = await too_large(app[GOVERNOR], principal)
            return json_response(_too_large_error(refused, limit), status)
        body = read.data
        if rescue is not None and oversize:  # a stop always stops
            rescue = rescue._replace(warnings=(oversize_warning(body, limit, read.skimmed),
                                               *read.warnings, *rescue.warnings))
        if rescue is not None:
            return await self._stopping_call(request, rescue, oversize=oversize)
        try:
            server = await self._started(app)
        except Exception:  # said in the log once, by `_start_ended`
            return error_response(503, "ROBOT_UNAVAILABLE", outcome="failed",
                                  reason="the MCP server did not start (see the bridge's log)")
        if server is None:
            return error_response(501, "NOT_IMPLEMENTED", reason=EXTRA_HINT)
        seat = self._seat(app, principal, agent_of(request), request.headers.get(SESSION_HEADER))

        async def run(scope: Any, receive: Any, send: Any) -> None:
            await server.handle(scope, receive, send, seat, principal.name, principal.role.name)

        left = functools.partial(app[CREDENTIAL_LEFT], principal)
        if request.method == "POST" and server.cancelled_by_hanging_up(
                list(request.raw_headers), body):
            response = await self._served_till_hang_up(run, request, body, left)
        else:
            response = await _asgi.serve(run, request, body, {}, left)
        if response is None:
            return error_response(503, "ROBOT_UNAVAILABLE", outcome="failed",
                                  reason="mcp_no_response")
        if request.method == "DELETE" and response.status < 300 and seat.session:
            await self._session_closed(seat)
        return response

    async def _served_till_hang_up(self, run: Any, request: web.Request, body: bytes,
                                   left: _asgi.Left) -> web.StreamResponse | None:
        """A motion call whose client cancels it by hanging up (the 2026-07-28 protocol),
        cancelled when it does, as the SDK cancels a call a `notifications/cancelled` names:
        its `motion` withdraws the principal's motion. aiohttp's server lets a handler run on
        after its client left (the bridge keeps its default, `handler_cancellation=False`: a
        stop is never to be cut off midway), so the door cancels this call alone."""
        from . import _asgi

        serving = asyncio.ensure_future(_asgi.serve(run, request, body, {}, left))
        hung_up = False

        def cancel() -> None:
            nonlocal hung_up
            hung_up = True
            serving.cancel()

        deadlines = request.app.get(DEADLINES)  # what tells of a hang-up (`_conn`)
        watching = deadlines.hung_up(request, cancel) if deadlines else contextlib.nullcontext()
        with watching:
            try:
                return await serving  # the handler cancelled (at shutdown) cancels it too
            except asyncio.CancelledError:
                if not hung_up:
                    raise
        log.info("an MCP client hung up on its motion call (its cancel): the call is "
                 "cancelled")
        return web.Response(status=CLIENT_CLOSED)  # nobody reads it

    async def _stopping_call(self, request: web.Request, rescue: Rescue, *,
                             oversize: bool = False) -> web.StreamResponse:
        """A body that says stop: it stops, whatever the SDK would make of it. A stop the SDK
        can run (in a valid session, or sessionless) it runs and answers; one it refuses,
        cannot take (a notification) or fails, and every stop while it is not installed or
        not running, the door runs as its tool runs it, why as its warning; a batch's stops
        and an `oversize` one (over what the SDK takes: its size is the warning) the door
        runs."""
        if rescue.batch is not None:
            return await self._stop_batch(request, rescue.warnings, rescue.batch)
        call = rescue.call
        assert call is not None
        warnings = (*rescue.warnings, *call.warnings)
        if call.notification:  # the SDK would take it as an unknown notification: no stop
            await self._stop_at_door(request, call, (
                *warnings, "$: a notification (no id): run, and not answered"))
            return web.Response(status=202)
        if oversize:  # over what the SDK takes (the bridge's limit): it would refuse it 413
            return json_response(await self._stop_at_door(request, call, warnings))
        server, why_not = self._server_for_stop(request.app)
        if server is None:
            said = () if why_not is None else (f"$: {why_not}: the bridge ran the stop",)
            return json_response(await self._stop_at_door(request, call, (*warnings, *said)))
        from . import _asgi
        from ._local import LocalApi

        principal = request[PRINCIPAL]
        seat = self._seat(request.app, principal, agent_of(request),
                          request.headers.get(SESSION_HEADER), warnings)

        async def run(scope: Any, receive: Any, send: Any) -> None:
            await server.handle(scope, receive, send, seat, principal.name, principal.role.name)

        # A body rewritten (the tool's own name, a repeated key resolved) names its tool anew.
        rewritten = call.warnings or rescue.warnings
        extra = {"headers": _named(request, call.name)} if rewritten else {}
        try:
            answered = await _asgi.answer(run, request, rescue.body, extra)
            refusal = _refusal(answered)
        except Exception as exc:  # the SDK's fault, not the stop's: the door runs it
            log.warning("the MCP server failed a stop's call (%s): the bridge runs it",
                        _failure(exc))
            answered, refusal = None, f"$: the MCP server failed ({_failure(exc)}): the " \
                                      "bridge ran the stop"
        if isinstance(seat.api, LocalApi) and seat.api.commanded:  # the SDK ran it
            if answered is None:
                return error_response(503, "ROBOT_UNAVAILABLE", outcome="failed",
                                      reason="mcp_no_response")
            return answered.response()
        reply = await self._stop_at_door(request, call, (*warnings, refusal))
        return json_response(reply)

    def _server_for_stop(self, app: web.Application) -> tuple[HttpMcp | None, str | None]:
        """The SDK's server if it runs, else None and why, if the client should know (a
        stop's warning): a stop never waits for the SDK to start (the requests after it
        will), nor fails with it."""
        if self._server is not None:
            return self._server, None
        if self._missing or importlib.util.find_spec("mcp") is None:
            self._missing = True
            return None, EXTRA_HINT
        self._start_task(app)
        return None, None

    async def _stop_batch(self, request: web.Request, warnings: tuple[str, ...],
                          batch: list[Any]) -> web.Response:
        """A JSON-RPC batch's replies, in order: each stop's call run and answered with its
        tool result, every other request refused; a notification gets no reply, though a
        stop in one is run."""
        replies = []
        for member in batch:
            call = stop_call(member)
            if call is None:
                reply = not_served(member)
            else:
                reply = await self._stop_at_door(request, call, (*warnings, *call.warnings))
                reply = None if call.notification else reply
            if reply is not None:
                replies.append(reply)
        return json_response(replies) if replies else web.Response(status=202)

    async def _stop_at_door(self, request: web.Request, call: StopCall,
                            warnings: tuple[str, ...]) -> dict[str, Any]:
        """`call` run by the bridge, as the authenticated principal (no MCP session, no SDK):
        `warnings` go with it to its audit entry."""
        from rcan_rtps.mcp_server.stop_tool import stop_reply

        seat = self._seat(request.app, request[PRINCIPAL], agent_of(request), None, warnings,
                          measured=True)  # (the client's body: its size is warned of here)
        return await stop_reply(seat, call)

    def _seat(self, app: web.Application, principal: Principal, agent: Agent,
              session: str | None, warnings: tuple[str, ...] = (), *,
              measured: bool = False) -> Seat:
        from rcan_rtps.mcp_server.keepalive import Keepalive
        from rcan_rtps.mcp_server.seat import Seat

        from ._local import LocalApi

        fixed = self._fixed_part()
        api = LocalApi(app, principal, fixed, warnings, measured=measured)
        keepalive = self._keepalives.get(principal.name)
        if keepalive is not None:  # heartbeats as long as its latest credential holds
            self._heartbeats[principal.name].renewed(principal)
        else:  # one per principal: heartbeats are a principal's
            beats = self._heartbeats[principal.name] = LocalApi(app, principal, fixed)
            keepalive = self._keepalives[principal.name] = Keepalive(beats)
            self._beating.append(asyncio.create_task(keepalive.run(),
                                                     name=f"mcp-keepalive-{principal.name}"))
        return Seat(api, agent, keepalive, session)

    def _fixed_part(self) -> dict[str, Any]:
        """The safety manifest's static part, which the tools describe the robot with."""
        if self._fixed is None:
            from ._safety_manifest import static_part

            self._fixed = static_part(self._config)
        return self._fixed

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
        """The SDK's server, started by the first request that needs it (None: the SDK is not
        installed); a start that fails raises, and the next request tries again."""
        if self._server is not None or self._missing:
            return self._server
        # Shielded: the start is every waiting request's, not the one that began it.
        return await asyncio.shield(self._start_task(app))

    def _start_task(self, app: web.Application) -> asyncio.Task[HttpMcp | None]:
        if self._starting is None or self._starting.done():
            self._starting = asyncio.create_task(self._start(app), name="mcp-start")
            self._starting.add_done_callback(self._start_ended)
        return self._starting

    def _start_ended(self, starting: asyncio.Task[HttpMcp | None]) -> None:
        """Its outcome kept (or said, when it failed: each waiting request raises it too)."""
        if starting.cancelled():
            return
        failed = starting.exception()
        if failed is not None:
            log.warning("the MCP server did not start: %s", _failure(failed))
        else:
            self._server = starting.result()

    async def _start(self, app: web.Application) -> HttpMcp | None:
        # The SDK's modules take ~1 s of CPU to import (pydantic's schemas): imported on a
        # thread, the loop runs on meanwhile (a stop is never held up behind an import; the
        # interpreter hands the thread and the loop turns every few ms).
        try:
            http = await asyncio.to_thread(importlib.import_module, "rcan_rtps.mcp_server.http")
        except ModuleNotFoundError as exc:
            if exc.name is None or exc.name.split(".")[0] not in ("mcp", "mcp_types"):
                raise
            log.warning("a client asked for MCP: %s", EXTRA_HINT)
            self._missing = True
            return None
        server: HttpMcp = http.HttpMcp(self._fixed_part(),
                                       max_body_bytes=app[SETTINGS].max_body_bytes)
        # The SDK's modules (pydantic's schemas: tens of thousands of objects) live as long as
        # the bridge: out of the collector's sight, like what start-up built (`run`), so that a
        # collection during a command does not scan them all (ms pauses, measured).
        gc.freeze()
        ready = asyncio.Event()
        self._serving = serving = asyncio.create_task(server.run(ready, self._stop), name="mcp")
        serving.add_done_callback(self._ended)
        waiting = asyncio.create_task(ready.wait())
        await asyncio.wait([serving, waiting], return_when=asyncio.FIRST_COMPLETED)
        waiting.cancel()
        if serving.done():
            serving.result()  # it failed to start: raise why (the request is answered 503)
        return server

    def _ended(self, serving: asyncio.Task[None]) -> None:
        """The SDK's server ended: at `close`, as asked; before, it failed, and the next
        request to `/mcp` starts another (its sessions are gone: clients open new ones; stops
        run meanwhile, at the door). Said once, its exception retrieved: never "never
        retrieved"."""
        failed = None if serving.cancelled() else serving.exception()
        if self._stop.is_set() or self._serving is not serving or self._server is None:
            if failed is not None and self._server is not None:  # (a start's failure: raised)
                log.warning("the MCP server failed while closing: %s", _failure(failed))
            return
        self._server = self._serving = None
        log.warning("the MCP server stopped (%s): the next request to /mcp starts it again",
                    "cancelled" if failed is None else _failure(failed))

    async def close(self) -> None:
        """End every session (their streams close), then the heartbeats: the bridge is
        shutting down, and stops the robot itself."""
        self._stop.set()
        if self._stopping:  # a closed session's stop still on its way
            await asyncio.wait(list(self._stopping))
        if self._starting is not None:  # (an import on its thread cannot be cut short)
            await asyncio.wait([self._starting])
        if self._serving is not None:
            await asyncio.wait([self._serving])
        for task in self._beating:
            task.cancel()
        for task in self._beating:
            with contextlib.suppress(asyncio.CancelledError):
                await task
