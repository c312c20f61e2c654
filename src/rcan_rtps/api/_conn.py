"""Connection deadlines aiohttp does not have: complete request headers within
`header_timeout_s` of connecting, and the next request's headers within `keepalive_timeout_s`
of the previous request's end (which is also how long an idle keep-alive connection lives).

How (and why this way): `ApiServer` serves aiohttp's public protocol factory (`runner.server`,
a `web.Server`) through `ConnectionDeadlines.wrap`, which puts a small `asyncio.Protocol`
in front of each `RequestHandler`. The wrapper forwards every protocol event unchanged and owns
one timer per connection. The `track_requests` middleware tells it when a request reached the
app (headers complete: timer off) and when its handler returned (timer on again, for the next
request). No aiohttp internals are read or patched: only its documented protocol-factory and
middleware interfaces and `request.protocol`. The wrapper never parses bytes, so a body that
happens to contain a blank line cannot fool it. A WebSocket is one long request: no deadline
applies while it is open. A timer that fires closes the transport; aiohttp sees an ordinary
disconnect. The body has its own deadline (`body_timeout_s`, in `read_limited`: 408).

The wrapper also tells a handler that asks (`ConnectionDeadlines.hung_up`) when its client
hangs up: aiohttp's server (`handler_cancellation=False`, its default) lets a handler run on
after its connection is lost and says nothing to it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable, Iterator

from aiohttp import web
from aiohttp.typedefs import Handler, Middleware

log = logging.getLogger(__name__)

ProtocolFactory = Callable[[], asyncio.BaseProtocol]


class _Watched(asyncio.Protocol):
    """One connection: aiohttp's handler behind it, and the connection's deadline."""

    def __init__(self, inner: asyncio.BaseProtocol, owner: ConnectionDeadlines) -> None:
        self._inner = inner
        self._owner = owner
        self._transport: asyncio.BaseTransport | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._timer_due = 0.0  # loop time the timer fires at
        self._deadline: float | None = None  # loop time the connection is closed at
        self._in_request = 0
        self._on_lost: list[Callable[[], None]] | None = None  # made when first asked for
        self._lost = False  # the connection is gone: no deadline is armed any more

    # -- asyncio.Protocol: forwarded as they come ------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = transport
        self._owner.watched[self._inner] = self
        self._arm(self._owner.header_timeout_s)
        self._inner.connection_made(transport)

    def connection_lost(self, exc: Exception | None) -> None:
        self._lost = True
        self._disarm()
        self._cancel_timer()
        self._owner.watched.pop(self._inner, None)
        self._inner.connection_lost(exc)
        told, self._on_lost = self._on_lost or [], None
        for hung_up in told:
            hung_up()

    def data_received(self, data: bytes) -> None:
        assert isinstance(self._inner, asyncio.Protocol)
        self._inner.data_received(data)

    def eof_received(self) -> bool | None:
        assert isinstance(self._inner, asyncio.Protocol)
        return self._inner.eof_received()

    def pause_writing(self) -> None:
        self._inner.pause_writing()

    def resume_writing(self) -> None:
        self._inner.resume_writing()

    # -- requests -------------------------------------------------------------------------

    def tell_when_lost(self, hung_up: Callable[[], None]) -> None:
        if self._on_lost is None:
            self._on_lost = []
        self._on_lost.append(hung_up)

    def forget(self, hung_up: Callable[[], None]) -> None:
        if self._on_lost is not None and hung_up in self._on_lost:
            self._on_lost.remove(hung_up)

    def request_started(self) -> None:
        self._in_request += 1
        self._disarm()

    def request_finished(self) -> None:
        self._in_request -= 1
        if self._in_request == 0:
            self._arm(self._owner.keepalive_timeout_s)

    def _arm(self, seconds: float) -> None:
        # A deadline, not a timer per request: the timer in place fires no later than any
        # deadline since it was set and re-arms itself for what is left (keep-alive requests
        # then cost no timer of their own).
        if self._lost:
            # A request that ends after its connection did (a WebSocket its client closed,
            # a handler that runs on after a hang-up): a keep-alive timer armed now would
            # hold this dead connection and aiohttp's handler (~3.5 kB) for
            # keepalive_timeout_s, as many as connections came in that time.
            return
        loop = asyncio.get_running_loop()
        self._deadline = loop.time() + seconds
        if self._timer is None or self._timer_due > self._deadline:
            self._cancel_timer()
            self._schedule(loop, self._deadline)

    def _disarm(self) -> None:
        self._deadline = None  # the timer, if any, finds nothing due and stops

    def _cancel_timer(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _schedule(self, loop: asyncio.AbstractEventLoop, when: float) -> None:
        self._timer_due = when
        self._timer = loop.call_at(when, self._expire)

    def _expire(self) -> None:
        self._timer = None
        deadline = self._deadline
        if deadline is None:
            return
        loop = asyncio.get_running_loop()
        if loop.time() < deadline:  # moved on since this timer was set
            self._schedule(loop, deadline)
            return
        self._deadline = None
        transport = self._transport
        if transport is not None and not transport.is_closing() and self._in_request == 0:
            log.debug("closing a connection that sent no complete request headers in time")
            transport.close()


class ConnectionDeadlines:
    """The deadlines of every connection of one server (see the module docstring)."""

    def __init__(self, *, header_timeout_s: float, keepalive_timeout_s: float) -> None:
        self.header_timeout_s = header_timeout_s
        self.keepalive_timeout_s = keepalive_timeout_s
        # aiohttp's handler (what `request.protocol` is) → the wrapper in front of it.
        self.watched: dict[object, _Watched] = {}

    def wrap(self, factory: ProtocolFactory) -> Callable[[], asyncio.Protocol]:
        """A protocol factory for `loop.create_server`: aiohttp's, behind deadlines."""
        return lambda: _Watched(factory(), self)

    @contextlib.contextmanager
    def hung_up(self, request: web.BaseRequest, call: Callable[[], None]) -> Iterator[None]:
        """`call` (once, from the event loop) if the request's client hangs up — its
        connection is lost — within the block; at once if it has already. Nothing for a
        connection not served through `wrap` (aiohttp's test server, which cancels the
        handler itself)."""
        watched = self.watched.get(request.protocol)
        if watched is None:
            if request.transport is None:  # lost before the block (`watched` forgot it)
                asyncio.get_running_loop().call_soon(call)
            yield
            return
        watched.tell_when_lost(call)
        try:
            yield
        finally:
            watched.forget(call)


def track_requests(deadlines: ConnectionDeadlines) -> Middleware:
    """Outermost middleware: a request that reached the app has its headers; its connection's
    deadline pauses until the handler returns. A no-op for connections not served through
    `ConnectionDeadlines.wrap` (e.g. aiohttp's test server)."""

    @web.middleware
    async def middleware(request: web.Request, handler: Handler) -> web.StreamResponse:
        watched = deadlines.watched.get(request.protocol)
        if watched is None:
            return await handler(request)
        watched.request_started()
        try:
            return await handler(request)
        finally:
            watched.request_finished()

    return middleware
