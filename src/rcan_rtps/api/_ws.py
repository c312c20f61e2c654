"""GET /api/ws: STATUS pushed at `telemetry_rate_hz`, commands in, outcomes out.

Frames from the bridge are `{"type": "status", "body": STATUS}` and
`{"type": "outcome", "http_status": N, "body": <the REST body>}`. Client frames are COMMAND
bodies (text, or binary UTF-8 JSON), decided in order. Any client frame, ping or pong counts as a
heartbeat. When the socket closes, a control session its principal holds ends at once: the
governor stops the robot (§10.8) after the command in flight, if any, has been decided.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable

import msgspec
from aiohttp import WSMsgType, web

from rcan_rtps.governance import Governor, Principal
from rcan_rtps.rcan import ErrorCode, validate_command

from ._bodies import WsFrame, error_body
from ._commands import Reply, run_command, too_large
from ._keys import GOVERNOR, OBSERVE, PRINCIPAL, ROBOT, SETTINGS, SOCKETS
from .ports import RobotView

log = logging.getLogger(__name__)
_CLOSING = (WSMsgType.CLOSE, WSMsgType.CLOSING, WSMsgType.CLOSED, WSMsgType.ERROR)
# Hard cap on one frame; frames between the body limit and this get a 413 outcome frame,
# larger ones close the socket (1009) before they are buffered.
_FRAME_CAP_FACTOR = 4
_STOPPING = frozenset({"estop", "stop"})


async def _send(ws: web.WebSocketResponse, frame: WsFrame) -> bool:
    if ws.closed:
        return False
    try:
        await ws.send_str(msgspec.json.encode(frame).decode())
    except (ConnectionError, RuntimeError):
        return False
    return True


async def _push_status(ws: web.WebSocketResponse, governor: Governor, robot: RobotView,
                       period_s: float) -> None:
    failing = False
    while not ws.closed:
        try:
            status = robot.status(pending_auth=len(governor.pending()))
            failing = False
        except Exception:
            if not failing:  # log a broken RobotView once, not at every tick
                log.exception("STATUS for the WebSocket failed")
            failing = True
        else:
            if not await _send(ws, WsFrame(type="status", body=status)):
                return
        await asyncio.sleep(period_s)


class _Commands:
    """In-order decisions of one socket's commands, with a bounded backlog."""

    def __init__(self, ws: web.WebSocketResponse, governor: Governor, principal: Principal,
                 limit: int, backlog: int,
                 observe: Callable[[float], None] | None = None) -> None:
        self._ws = ws
        self._observe = observe
        self._governor = governor
        self._principal = principal
        self._limit = limit
        self._queue: asyncio.Queue[bytes] = asyncio.Queue(backlog)
        self._current: asyncio.Future[Reply] | None = None
        self._worker = asyncio.create_task(self._work())

    def offer(self, raw: bytes) -> bool:
        try:
            self._queue.put_nowait(raw)
        except asyncio.QueueFull:
            return False
        return True

    async def _decide(self, raw: bytes) -> Reply:
        if len(raw) > self._limit:
            return await too_large(self._governor, self._principal)
        return await run_command(self._governor, self._principal, raw, self._observe)

    async def _work(self) -> None:
        while True:
            raw = await self._queue.get()
            self._current = asyncio.ensure_future(self._decide(raw))
            status, body = await asyncio.shield(self._current)
            await _send(self._ws, WsFrame(type="outcome", http_status=status, body=body))

    async def close(self) -> None:
        """Stop taking commands; finish the one in flight; still decide queued (e-)stops."""
        self._worker.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._worker
        if self._current is not None:
            with contextlib.suppress(Exception):
                await self._current
        while not self._queue.empty():
            raw = self._queue.get_nowait()
            try:
                action = validate_command(raw).action
            except Exception:
                continue
            if action in _STOPPING:  # a stop the client sent must never be dropped
                await self._decide(raw)


async def websocket(request: web.Request) -> web.WebSocketResponse:
    app, principal = request.app, request[PRINCIPAL]
    governor, settings = app[GOVERNOR], app[SETTINGS]
    ws = web.WebSocketResponse(autoping=False, heartbeat=None,
                               max_msg_size=settings.max_body_bytes * _FRAME_CAP_FACTOR)
    await ws.prepare(request)
    app[SOCKETS].add(ws)
    commands = _Commands(ws, governor, principal, settings.max_body_bytes,
                         settings.ws_max_in_flight, app[OBSERVE])
    pusher = asyncio.create_task(
        _push_status(ws, governor, app[ROBOT], 1.0 / settings.telemetry_rate_hz))
    try:
        while True:
            msg = await ws.receive()
            if msg.type in _CLOSING:
                break
            governor.heartbeat(principal)  # any frame shows the client is there
            if msg.type is WSMsgType.PING:
                await ws.pong(msg.data)
            elif msg.type in (WSMsgType.TEXT, WSMsgType.BINARY):
                raw = msg.data.encode() if isinstance(msg.data, str) else msg.data
                if not commands.offer(raw):
                    body = error_body(ErrorCode.RATE_LIMITED, reason="too_many_in_flight")
                    await _send(ws, WsFrame(type="outcome", http_status=429, body=body))
    finally:
        pusher.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await pusher
        await _end(ws, governor, principal, commands)
        app[SOCKETS].discard(ws)
    return ws


async def _end(ws: web.WebSocketResponse, governor: Governor, principal: Principal,
               commands: _Commands) -> None:
    try:
        await commands.close()
    finally:
        try:
            stop = await governor.end_session(principal)
        except Exception:
            log.exception("safe stop after the WebSocket of %s closed failed", principal.name)
        else:
            if stop is not None:
                log.warning("WebSocket of %s closed while it held a control session: "
                            "safe stop (%s)", principal.name, stop.outcome.value)
        if not ws.closed:
            await ws.close()
