"""An ASGI application behind one aiohttp route (the MCP SDK's streamable HTTP transport).

aiohttp has already read and authenticated the request: the body is read whole before the
application runs (bounded like any other body), and what the route adds to the scope (who
asked) goes in as extra scope keys. The application's response is streamed as it comes
(a Server-Sent Events stream stays open as long as the application writes to it). When the
client goes away, the application's `receive()` says so (`http.disconnect`), and writes to
the gone client raise `ConnectionResetError`, which ASGI applications take as a disconnect
(but for a response's end, which is dropped: there is nothing left to tell that client).

A request may be served for as long as its credential holds (`left`: the seconds it has;
None: it does not expire), no longer. A stream open when the credential runs out (an MCP
session's event stream) is ended: the application's `receive()` says the client left, and
what it writes after is dropped, the response ended. A response not yet begun by then (a
tool call still being answered) is answered 401 instead, once the application answers:
nothing the application says after the credential ran out reaches its holder. An answer of
a known length is begun with its body, never its head alone (a head whose body was then cut
left its client waiting for bytes that never came).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any, NamedTuple

from aiohttp import web

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
AsgiApp = Callable[[Scope, Receive, Send], Awaitable[None]]
GONE_POLL_S = 1.0  # how often a waiting `receive()` looks whether the client is still there
FRAMING = ("content-length", "transfer-encoding")
MIN_WAIT_S = 0.01  # the shortest wait for a credential's end (its clock may be set back)
Left = Callable[[], float | None]
EXPIRED_BODY = (b'{"jsonrpc": "2.0", "id": null, "error": {"code": -32600, "message": '
                b'"CREDENTIAL_EXPIRED: the credential this request was sent with ran out '
                b'while it was served: nothing more of it is sent; send the next request '
                b'with a valid one (a stop too)"}}')


def scope_of(request: web.Request, extra: dict[str, Any]) -> Scope:
    peer = request.transport.get_extra_info("peername") if request.transport else None
    host = request.transport.get_extra_info("sockname") if request.transport else None
    return {
        "type": "http", "asgi": {"version": "3.0", "spec_version": "2.3"},
        "http_version": f"{request.version.major}.{request.version.minor}",
        "method": request.method, "scheme": request.scheme,
        "path": request.path, "raw_path": request.raw_path.split("?", 1)[0].encode(),
        "query_string": request.query_string.encode(), "root_path": "",
        "headers": [(k.lower(), v) for k, v in request.raw_headers],
        "client": tuple(peer[:2]) if isinstance(peer, tuple) else None,
        "server": tuple(host[:2]) if isinstance(host, tuple) else None,
        **extra,
    }


class _Exchange:
    """One request's `receive` and `send`, and the aiohttp response they build."""

    def __init__(self, request: web.Request, body: bytes, left: Left | None = None) -> None:
        self._request = request
        self._body: bytes | None = body
        self._done = asyncio.Event()
        self._left = left
        self.expired = False  # the credential ran out while the request was served
        # A sized answer's head waits for its body (`_sized`): cut between the two, it is
        # answered 401 whole, not a head whose promised body never comes.
        self._head: Message | None = None
        self.response: web.StreamResponse | None = None

    async def receive(self) -> Message:
        if self._body is not None:
            body, self._body = self._body, None
            return {"type": "http.request", "body": body, "more_body": False}
        while not self._done.is_set() and not self._gone() and not self._expired():
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._done.wait(), self._wait_s())
        return {"type": "http.disconnect"}

    def _wait_s(self) -> float:
        """How long to wait before looking again: the poll, or less if the credential runs
        out sooner (never 0: looked at again after a clock set back, it may hold on)."""
        left = self._left() if self._left is not None else None
        return GONE_POLL_S if left is None else max(MIN_WAIT_S, min(GONE_POLL_S, left))

    def _expired(self) -> bool:
        if not self.expired and self._left is not None:
            left = self._left()
            self.expired = left is not None and left <= 0
        return self.expired

    def _gone(self) -> bool:
        transport = self._request.transport
        return transport is None or transport.is_closing()

    async def send(self, message: Message) -> None:
        if self._expired():
            await self._cut()
            return
        kind = message["type"]
        if kind == "http.response.start":
            self._head = message
            if not _sized(message):  # a stream: its head goes now
                await self._begin(message)
        elif kind == "http.response.body":
            if self.response is None:
                if self._head is None:
                    raise RuntimeError("ASGI body before its start")
                await self._begin(self._head)
            assert self.response is not None
            body = message.get("body", b"")
            if body:
                await self.response.write(body)
            if not message.get("more_body", False):
                try:
                    await self.response.write_eof()
                except ConnectionResetError:
                    # The client left first (the SDK's client closes its session and its
                    # event stream together): nobody reads this end, and the SDK would log
                    # its failure as an error with two tracebacks.
                    pass
                finally:
                    self._done.set()

    async def _begin(self, head: Message) -> None:
        response = web.StreamResponse(status=int(head["status"]))
        for name, value in head.get("headers", ()):
            response.headers.add(name.decode("latin-1"), value.decode("latin-1"))
        self.response = response
        await response.prepare(self._request)

    async def _cut(self) -> None:
        """The credential ran out: a response begun is ended, one not begun is a 401; what
        the application sends after either is dropped."""
        if self._done.is_set():
            return
        self._done.set()
        try:
            if self.response is None:
                self.response = web.Response(status=401, body=EXPIRED_BODY,
                                             content_type="application/json")
            else:  # (a stream, chunked: its end is said; a sized answer is not begun yet)
                await self.response.write_eof()
        except ConnectionResetError:  # the client left too
            pass

    def finish(self) -> None:
        self._done.set()


async def serve(app: AsgiApp, request: web.Request, body: bytes,
                extra: dict[str, Any], left: Left | None = None
                ) -> web.StreamResponse | None:
    """Run `app` on this request, no longer than `left` says its credential holds; its
    response, or None if it sent none."""
    exchange = _Exchange(request, body, left)
    await _run(app, request, extra, exchange)
    return exchange.response


def _sized(head: Message) -> bool:
    """Whether a response's head says its body's length (an answer, not a stream)."""
    return any(name.lower() == b"content-length" for name, _ in head.get("headers", ()))


async def _run(app: AsgiApp, request: web.Request, extra: dict[str, Any],
               exchange: _Exchange) -> None:
    """`app` on this request, talking through `exchange` (finished, whatever happens)."""
    try:
        await app(scope_of(request, extra), exchange.receive, exchange.send)
    finally:
        exchange.finish()


class Answer(NamedTuple):
    """An application's whole response, held back from the client."""

    status: int
    headers: list[tuple[str, str]]
    body: bytes

    def response(self) -> web.Response:
        response = web.Response(status=self.status, body=self.body)
        response.headers.clear()  # the application's own, not aiohttp's defaults
        for name, value in self.headers:
            if name.lower() not in FRAMING:  # aiohttp frames the body it sends
                response.headers.add(name, value)
        return response


class _Holding(_Exchange):
    """An exchange whose response is kept (`answer`) instead of sent."""

    def __init__(self, request: web.Request, body: bytes) -> None:
        super().__init__(request, body)
        self.answer: Answer | None = None

    async def send(self, message: Message) -> None:
        if message["type"] == "http.response.start":
            headers = [(k.decode("latin-1"), v.decode("latin-1"))
                       for k, v in message.get("headers", ())]
            self.answer = Answer(int(message["status"]), headers, b"")
        elif message["type"] == "http.response.body":
            if self.answer is None:
                raise RuntimeError("ASGI body before its start")
            self.answer = self.answer._replace(body=self.answer.body + message.get("body", b""))
            if not message.get("more_body", False):
                self._done.set()


async def answer(app: AsgiApp, request: web.Request, body: bytes,
                 extra: dict[str, Any]) -> Answer | None:
    """Run `app` on this request to the end of its response, and return that response
    unsent (for a response of one body: never an event stream that stays open); None if it
    sent none."""
    exchange = _Holding(request, body)
    await _run(app, request, extra, exchange)
    return exchange.answer
