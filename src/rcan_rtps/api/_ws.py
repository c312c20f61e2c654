"""GET /api/ws: STATUS pushed at `telemetry_rate_hz`, commands in, outcomes out.

Frames from the bridge are `{"type": "status", "body": STATUS}`, `{"type": "outcome",
"http_status": N, "body": <the REST body>}` and, at each change of a goal (feedback,
state, its end), `{"type": "goal", "body": <GET /api/goals/{id}>}` and, to a principal who
may list held commands, `{"type": "approvals", "body": <GET /api/hitl/pending>}` when the
socket opens and at each change of that list (`_approvals`). Client frames are COMMAND
bodies (text, or binary UTF-8 JSON). Each is validated as it arrives; a valid `stop` or `estop`
is decided at once, concurrently with the socket's queue (never refused with 429, never behind
queued commands), so its outcome frame may overtake the outcomes of commands sent before it:
match outcomes by `message_id` (every command has one; send your own to know it). So is a
valid INVOKE_CANCEL (the stop of its skill's motion; its INVOKE_RESULT's `reply_to` names the
INVOKE), unless its INVOKE still waits in this socket's queue: then it is decided right after
that INVOKE is (overtaking it, it would find nothing to cancel, and the INVOKE would run).
Other frames are decided in order, at most `ws_max_in_flight` waiting (beyond: a 429 frame);
an INVOKE whose goal is under way is answered (its INVOKE_RESULT outcome frame, `reply_to` its
msg_id) when the goal ends, while the frames behind it go on being decided. A bad frame
(invalid UTF-8, not JSON, schema, 413) gets its error outcome frame and the socket goes on; so
does a command whose decision raised (503 frame). A *text* frame that is not UTF-8 is a
protocol error (RFC 6455 §8.1): aiohttp closes the socket (1007). Any client frame, ping or
pong counts as a heartbeat. When the socket closes, the motion of its INVOKEs not answered yet
stops at once (nobody is left to answer: `_invoke`; one being decided, once it is: each is
answered in the log, INVOKE_RESULT `failure`), and a control session its principal holds
ends: the governor stops the robot (§10.8) after the command in flight and every stop sent
have been decided; queued commands are dropped.

Outcome frames go out through the socket's outbox (`_Outbox`), never awaited by what reads
frames: a client that sends and does not read cannot hold up its own later stop. A client that
leaves more than `OUTBOX_BYTES` of outcomes unread is not reading: its outcomes are dropped,
only its stops are taken from then on, and once its frames pause (`DEAF_QUIET_S`) its socket
is closed with 1008 ("outcome frames not read").

A socket lasts longer than the credential that opened it may: one whose JWT has run out, or
whose client certificate's notAfter has passed (`Principal.expires_at`), is closed with 1008
("credential expired") at its next frame, or when its time is up while it is idle. A stop in
that frame is still taken; nothing else is.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
from collections import Counter, deque
from collections.abc import Callable
from typing import Literal, Protocol

import msgspec
from aiohttp import WSCloseCode, WSMsgType, web

from rcan_rtps._counts import count_down
from rcan_rtps.governance import Governor, Principal
from rcan_rtps.rcan import ErrorCode, Invoke, InvokeCancel

from ._bodies import WsFrame, error_body, error_response, failure_reply
from ._intake import (
    NO_CHECKS,
    STOP_ROOM,
    Checks,
    Intake,
    Observe,
    Reply,
    StopLane,
    decide_safely,
    give_back_id,
    intake,
)
from ._keys import (
    APPROVALS,
    CHECKS,
    CREDENTIAL_LEFT,
    GOAL_EVENTS,
    GOVERNOR,
    INVOCATIONS,
    OBSERVE,
    PRINCIPAL,
    SETTINGS,
    SOCKETS,
    SOCKETS_OF,
    STATUS,
    ApiSettings,
)
from ._skills import Skills

log = logging.getLogger(__name__)
_CLOSING = (WSMsgType.CLOSE, WSMsgType.CLOSING, WSMsgType.CLOSED, WSMsgType.ERROR)
# Hard cap on one frame (`_intake.STOP_ROOM` times the body limit); frames between the body
# limit and this get a 413 outcome frame unless they say stop (a stop always stops), larger
# ones close the socket (1009) before they are buffered.
OUTBOX_BYTES = 1 << 20  # outcome frames a client may leave unread before it counts as deaf
DEAF_QUIET_S = 1.0  # a deaf client's frames paused this long: every stop it sent is read
CLOSE_S = 5.0  # closing a deaf client's socket (it reads no close frame either)
NOT_READING = b"outcome frames not read"
CREDENTIAL_EXPIRED = b"credential expired"
MIN_WAIT_S = 0.01  # the shortest wait for a frame (`_wait_s`)
# Sockets one principal may hold at once (beyond: 429 before the handshake). A console, an
# agent and a few tools need a handful; hundreds are an attack on the file descriptors.
MAX_SOCKETS_PER_PRINCIPAL = 32


async def _send(ws: web.WebSocketResponse, frame: WsFrame) -> bool:
    if ws.closed:
        return False
    try:
        await ws.send_str(msgspec.json.encode(frame).decode())
    except (ConnectionError, RuntimeError):
        return False
    return True


class _Outbox:
    """One socket's outcome frames, sent in order by their own task: whoever has an outcome
    (the receive loop's 429, the command worker, the stop lane) puts it and goes on, never
    waiting for the client to read. Beyond `limit` bytes unsent the client is `deaf`: what is
    queued and whatever comes after is dropped."""

    def __init__(self, ws: web.WebSocketResponse, limit: int = OUTBOX_BYTES) -> None:
        self._ws = ws
        self._limit = limit
        self._frames: deque[str | bytes] = deque()  # bytes: a pong's payload
        self._size = 0
        self._ready = asyncio.Event()
        self.deaf = False
        self._writer = asyncio.create_task(self._write())

    def put(self, frame: WsFrame) -> None:
        self._put(msgspec.json.encode(frame).decode())

    def pong(self, payload: bytes) -> None:
        """A pong, in its turn: a client that pings and does not read is as deaf."""
        self._put(bytes(payload))  # the ping's payload may come as a bytearray

    def _put(self, text: str | bytes) -> None:
        if self.deaf or self._ws.closed:
            return
        if self._size + len(text) > self._limit:
            self.deaf = True
            self._frames.clear()
            return
        self._frames.append(text)
        self._size += len(text)
        self._ready.set()

    async def _write(self) -> None:
        while True:
            await self._ready.wait()
            self._ready.clear()
            while self._frames:
                text = self._frames.popleft()
                self._size -= len(text)
                try:
                    if isinstance(text, bytes):
                        await self._ws.pong(text)
                    else:
                        await self._ws.send_str(text)
                except (ConnectionError, RuntimeError):  # the socket is closing: nobody reads
                    return
                except Exception:  # the log has it; what is left is dropped (deaf, in time)
                    log.exception("sending a WebSocket frame failed")
                    return

    async def close(self) -> None:
        """Send what is queued, if the client takes it within `CLOSE_S`; then stop."""
        if not self.deaf and self._frames:
            self._ready.set()
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._flushed(), CLOSE_S)
        self._writer.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._writer

    async def _flushed(self) -> None:
        while self._frames and not self._writer.done():
            await asyncio.sleep(0.01)


class _Feed(Protocol):
    """A hub's subscription: `StatusHub.subscribe()`, `GoalEvents.subscribe()`."""

    async def next(self) -> object: ...

    def close(self) -> None: ...


async def _push(ws: web.WebSocketResponse, subscribe: Callable[[], _Feed],
                kind: Literal["status", "goal", "approvals"]) -> None:
    """Sends what a feed yields as it comes: STATUS on change at the telemetry rate, every
    goal change (newest view per goal if the socket falls behind). Subscribes inside the task:
    one cancelled before it starts has then nothing to close."""
    subscription = subscribe()
    try:
        while not ws.closed:
            if not await _send(ws, WsFrame(type=kind, body=await subscription.next())):
                return
    finally:
        subscription.close()


class _Commands:
    """One socket's commands: valid stops through the lane at once, the rest decided in order
    with a bounded backlog. Nothing that goes wrong deciding one command stops the next."""

    def __init__(self, ws: web.WebSocketResponse, governor: Governor, principal: Principal,
                 settings: ApiSettings, observe: Observe | None = None,
                 checks: Checks = NO_CHECKS, invocations: Skills | None = None) -> None:
        self._outbox = _Outbox(ws)
        self._checks = checks
        self._invocations = invocations
        # The answers of INVOKEs under way (a goal, a stream, a trajectory): each cancelled
        # as the socket closes, which stops that INVOKE's motion (`Started.finish`).
        self._invoking: set[asyncio.Future[Reply]] = set()
        # INVOKEs queued here, not started yet (by msg_id), and the INVOKE_CANCELs of them
        # that came meanwhile: each goes to the lane once its INVOKE is decided (`_work`).
        self._queued: Counter[str] = Counter()
        self._cancels: dict[str, list[Intake]] = {}
        self._observe = observe
        self._governor = governor
        self._principal = principal
        self._limit = settings.max_body_bytes
        self._queue: asyncio.Queue[Intake] = asyncio.Queue(settings.ws_max_in_flight)
        self._lane = StopLane(governor, principal, self._deliver, observe=observe,
                              width=settings.stop_lane_width)
        # INVOKE_CANCELs have a lane of their own: one waits for its INVOKE's answer (a goal
        # winding down, up to its cancel_timeout_ms) and must not take a stop's room.
        self._cancel_lane = StopLane(governor, principal, self._deliver, observe=observe,
                                     width=settings.ws_max_in_flight, invocations=invocations)
        self._cancel_room = settings.ws_max_in_flight  # cancels held for queued INVOKEs
        self._current: asyncio.Future[Reply] | None = None
        self._worker = asyncio.create_task(self._work())

    @property
    def deaf(self) -> bool:
        """Whether the client has left more outcomes unread than its outbox holds."""
        return self._outbox.deaf

    def pong(self, payload: bytes) -> None:
        self._outbox.pong(payload)

    async def take(self, raw: bytes) -> None:
        """Validate now; a stop is decided at once (never 429), so is an INVOKE_CANCEL (429
        only past `ws_max_in_flight` of them), anything else queues. A deaf client's other
        commands are not taken: it would never learn their outcomes."""
        item = intake(raw, self._limit, self._checks, self._principal.name)
        if isinstance(item.message3, InvokeCancel):
            await self._invoke_cancel(item, item.message3)
            return
        if item.stopping:
            await self._lane.submit(item)
            return
        if self.deaf:
            return
        try:
            self._queue.put_nowait(item)
        except asyncio.QueueFull:
            await self._too_many(item)
            return
        if isinstance(item.message3, Invoke) and self._invocations is not None:
            self._queued[item.message3.msg_id] += 1

    async def take_stop(self, raw: bytes) -> None:
        """A frame that came once the socket's credential had run out: a stop still stops
        (it can only make the robot safer); anything else is not taken."""
        item = intake(raw, self._limit, self._checks, self._principal.name)
        if item.stopping:
            await self._lane.submit(item)
        else:  # not taken: its id is not spent
            give_back_id(item, self._checks, self._principal.name)

    async def _invoke_cancel(self, item: Intake, cancel: InvokeCancel) -> None:
        """An INVOKE_CANCEL stops its skill's motion: through its lane, never behind this
        socket's queue; 429 only when `ws_max_in_flight` are already being decided. One whose
        INVOKE is still queued here waits for it to be decided (then there is motion to stop,
        or a hold to withdraw; before, it would be `not_found` and the INVOKE would run after
        it), at most `ws_max_in_flight` held so."""
        held = sum(map(len, self._cancels.values()))  # at most _cancel_room: a short sum
        if self._queued[cancel.invoke_id] > 0 and held < self._cancel_room:
            self._cancels.setdefault(cancel.invoke_id, []).append(item)
            return
        # Full: refused, not waited for — waiting here would hold up this socket's reader,
        # and with it the stops behind (a client with that many cancels out can send `stop`).
        if not await self._cancel_lane.try_submit(item):
            await self._too_many(item)

    async def _too_many(self, item: Intake) -> None:
        """429: not taken, so its id is not spent (a retry of it is not a replay)."""
        give_back_id(item, self._checks, self._principal.name)
        body = error_body(ErrorCode.RATE_LIMITED, reason="too_many_in_flight",
                          message_id=item.message_id)
        await self._deliver((429, body))

    async def _deliver(self, reply: Reply) -> None:
        self._put(reply)

    def _put(self, reply: Reply) -> None:
        status, body = reply
        self._outbox.put(WsFrame(type="outcome", http_status=status, body=body))

    async def _work(self) -> None:
        while True:
            item = await self._queue.get()
            try:
                if isinstance(item.message3, Invoke) and self._invocations is not None:
                    await self._invoked(item.message3, self._invocations)
                    continue
                self._current = asyncio.ensure_future(
                    decide_safely(self._governor, self._principal, item, self._observe,
                                  self._invocations))
                await self._deliver(await asyncio.shield(self._current))
            except Exception:  # never the end of this socket's commands
                log.exception("WebSocket command of %s failed", self._principal.name,
                              extra={"principal": self._principal.name})

    async def _invoked(self, invoke: Invoke, skills: Skills) -> None:
        """An INVOKE in its turn; then the INVOKE_CANCELs of it that came while it was queued
        go to the lane."""
        count_down(self._queued, invoke.msg_id)
        try:
            await self._invoke(invoke, skills)
        finally:
            for cancel in self._cancels.pop(invoke.msg_id, ()):
                await self._cancel_lane.submit(cancel)  # the worker waits, not the reader

    async def _invoke(self, invoke: Invoke, skills: Skills) -> None:
        """Decided in order like any command; an INVOKE whose goal is under way is answered
        when it ends, one held for a human when its hold ends (after its 202 frame), while
        the frames behind it go on being decided."""
        try:
            started = await skills.invocations().start(self._governor, self._principal,
                                                       invoke)
        except Exception as exc:  # answered as REST would (503), never the socket's end
            log.exception("an INVOKE of %s failed", self._principal.name,
                          extra={"principal": self._principal.name})
            await self._deliver(failure_reply(exc))
            return
        if started.reply is not None:  # (held for a human: 202 now, its answer later)
            await self._deliver(started.reply)
        if started.finish is None:
            return
        answer = started.finish()  # now: a close from here on finds it (no task to start)
        self._invoking.add(answer)
        answer.add_done_callback(self._answered)

    def _answered(self, answer: asyncio.Future[Reply]) -> None:
        """An INVOKE's answer, once its skill is done: its outcome frame."""
        self._invoking.discard(answer)
        if answer.cancelled():  # the socket closed: answered in the log alone
            return
        error = answer.exception()
        if error is not None:
            log.error("answering an INVOKE of %s failed", self._principal.name,
                      exc_info=error, extra={"principal": self._principal.name})
            return
        self._put(answer.result())

    async def close(self) -> None:
        """Stop taking commands; stop the motion of the INVOKEs under way (nobody is left to
        answer: `_invoke`) at once; finish the command in flight and every stop; drop the
        rest."""
        self._worker.cancel()  # an INVOKE being decided is left once decided (`_invoke`)
        for answer in list(self._invoking):  # now, not once the command in flight is decided
            answer.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._worker
        if self._current is not None:
            with contextlib.suppress(Exception):
                await self._current
        for cancels in self._cancels.values():  # their INVOKEs are dropped: answered so
            for cancel in cancels:
                await self._cancel_lane.submit(cancel)
        self._cancels.clear()
        await self._lane.drain()  # a stop the client sent must never be dropped
        await self._cancel_lane.drain()
        await self._outbox.close()


async def websocket(request: web.Request) -> web.StreamResponse:
    app, principal = request.app, request[PRINCIPAL]
    settings = app[SETTINGS]
    held = app[SOCKETS_OF]
    if held[principal.name] >= MAX_SOCKETS_PER_PRINCIPAL:
        return _too_many_sockets(principal)
    ws = web.WebSocketResponse(autoping=False, heartbeat=None,
                               max_msg_size=settings.max_body_bytes * STOP_ROOM)
    transport = request.transport  # cut off if its client does not read (`_cut_off`)
    held[principal.name] += 1  # (before the handshake's await: sockets opened at once count)
    try:
        await ws.prepare(request)
    except BaseException:
        count_down(held, principal.name)
        raise
    app[SOCKETS].add(ws)
    try:
        return await _serve(ws, request, principal, transport)
    finally:
        count_down(held, principal.name)


def _too_many_sockets(principal: Principal) -> web.Response:
    """One principal's sockets are bounded: a GUEST holding hundreds would use up the process's
    file descriptors, and then nobody's e-stop — REST or WebSocket — could connect. That
    principal keeps its e-stop over the sockets it has and over REST."""
    log.warning("WebSocket of %s refused: it holds %d already", principal.name,
                MAX_SOCKETS_PER_PRINCIPAL, extra={"principal": principal.name})
    return error_response(429, ErrorCode.RATE_LIMITED, reason="too_many_sockets")


async def _serve(ws: web.WebSocketResponse, request: web.Request, principal: Principal,
                 transport: asyncio.Transport | None) -> web.WebSocketResponse:
    app = request.app
    governor, settings = app[GOVERNOR], app[SETTINGS]
    commands = _Commands(ws, governor, principal, settings, app[OBSERVE], app[CHECKS],
                         app[INVOCATIONS])
    pushers = [asyncio.create_task(_push(ws, app[STATUS].subscribe, "status")),
               asyncio.create_task(_push(ws, app[GOAL_EVENTS].subscribe, "goal"))]
    if principal.role >= settings.hitl_list_role:  # who may list what waits for a human
        pushers.append(asyncio.create_task(_push(
            ws, functools.partial(app[APPROVALS].subscribe, principal), "approvals")))
    left = app[CREDENTIAL_LEFT]
    expired = False
    try:
        while True:
            try:  # a deaf client's socket is read until its frames pause: its stops count
                msg = await ws.receive(timeout=_wait_s(commands.deaf, left(principal)))
            except asyncio.TimeoutError:
                if commands.deaf:
                    log.warning("WebSocket of %s does not read its outcome frames: closed "
                                "(1008)", principal.name, extra={"principal": principal.name})
                    break
                expired = _expired(left(principal))
                if expired:
                    break
                continue  # (the wall clock was set back meanwhile: its time is not up)
            if msg.type in _CLOSING:
                break
            if _expired(left(principal)):  # its credential ran out while this frame came
                expired = True
                if msg.type in (WSMsgType.TEXT, WSMsgType.BINARY):
                    await commands.take_stop(_raw(msg.data))  # nothing else of it
                break
            governor.heartbeat(principal)  # any frame shows the client is there
            if msg.type is WSMsgType.PING:
                commands.pong(msg.data)
            elif msg.type in (WSMsgType.TEXT, WSMsgType.BINARY):
                await commands.take(_raw(msg.data))
    finally:
        for pusher in pushers:
            pusher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await pusher
        if expired:
            log.warning("WebSocket of %s closed (1008): its credential expired",
                        principal.name, extra={"principal": principal.name})
        await _end(ws, governor, principal, commands,
                   transport if commands.deaf else None, expired=expired)
        app[SOCKETS].discard(ws)
    return ws


def _raw(data: str | bytes) -> bytes:
    return data.encode() if isinstance(data, str) else data


def _wait_s(deaf: bool, credential_left: float | None) -> float | None:
    """How long to wait for a frame: a deaf client's until its frames pause, anyone's no
    longer than its credential has left (None: for ever). Never 0: aiohttp takes a timeout
    of 0 as none at all, and a credential that ran out while a frame was handled left the
    socket open for good (review of red team 25); a frame already come is still read (its
    stop taken) before the socket closes."""
    waits = [w for w in (DEAF_QUIET_S if deaf else None, credential_left) if w is not None]
    return max(MIN_WAIT_S, min(waits)) if waits else None


def _expired(credential_left: float | None) -> bool:
    return credential_left is not None and credential_left <= 0


def _cut_off(transport: asyncio.Transport | None) -> None:
    """End the connection of a client that does not read: its close frame (1008) written
    straight to the transport (the socket's own writer would wait for a drain that never
    comes), the connection closed once that is sent, cut off if it is not within CLOSE_S."""
    if transport is None or transport.is_closing():
        return
    payload = WSCloseCode.POLICY_VIOLATION.to_bytes(2, "big") + NOT_READING
    transport.write(bytes([0x88, len(payload)]) + payload)  # FIN + close; server: unmasked
    transport.close()
    asyncio.get_running_loop().call_later(CLOSE_S, transport.abort)


async def _end(ws: web.WebSocketResponse, governor: Governor, principal: Principal,
               commands: _Commands, deaf: asyncio.Transport | None, *,
               expired: bool = False) -> None:
    """The socket's end: its stops decided, its principal's control session ended, the socket
    closed (`deaf`: the transport of a client that does not read, cut off; `expired`: its
    credential ran out, closed 1008)."""
    # First, before its command in flight is awaited: motion that has not started by now
    # never does (it would start after its connection is gone, with nobody to stop it).
    on_its_way = governor.connection_closed(principal)
    try:
        await commands.close()
    finally:
        try:
            stop = await governor.end_session(principal, on_its_way=on_its_way)
        except Exception:
            log.exception("safe stop after the WebSocket of %s closed failed", principal.name,
                          extra={"principal": principal.name})
        else:
            if stop is not None:
                log.warning("WebSocket of %s closed while it held a control session: "
                            "safe stop (%s)", principal.name, stop.outcome.value,
                            extra={"principal": principal.name, "audit_id": stop.audit_id})
        if deaf is not None:
            _cut_off(deaf)
        elif not ws.closed and expired:
            await ws.close(code=WSCloseCode.POLICY_VIOLATION, message=CREDENTIAL_EXPIRED)
        elif not ws.closed:
            await ws.close()
