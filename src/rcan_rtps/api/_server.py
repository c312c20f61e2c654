"""Serving the app: an `ApiServer` that binds, reports its URL, and shuts down in order.

It listens with `loop.create_server` on aiohttp's protocol, `ApiRequestHandler` (see
`_protocol`: the API's replies to what aiohttp's parser refuses) for the runner's server,
wrapped in `ConnectionDeadlines` (see `_conn`), instead of a `TCPSite`, which offers no way
to choose or put anything in front of the protocol. The timeouts come from the app's
`ApiSettings`.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import socket
import ssl
from types import TracebackType
from typing import Any

from aiohttp import web

from ._keys import DEADLINES, KEEPALIVE_TIMEOUT_S, SETTINGS
from ._protocol import ApiRequestHandler, handler_args

_BACKLOG = 128  # what TCPSite uses


class ApiServer:
    """`async with ApiServer(app, host=..., port=0) as server: server.url` — port 0 picks one."""

    def __init__(self, app: web.Application, *, host: str, port: int,
                 ssl_context: ssl.SSLContext | None = None,
                 shutdown_timeout_s: float = 5.0, sock: socket.socket | None = None) -> None:
        """`sock`: a socket bound beforehand (see `bind`), used instead of host and port."""
        settings = app.get(SETTINGS)
        keepalive = settings.keepalive_timeout_s if settings else KEEPALIVE_TIMEOUT_S
        # aiohttp's own keep-alive timer (idle between requests) backs up the deadlines.
        self._handler_args = handler_args(keepalive)
        self._runner = web.AppRunner(app, shutdown_timeout=shutdown_timeout_s,
                                     **self._handler_args)
        self._deadlines = app.get(DEADLINES)
        self._handshake_s = settings.header_timeout_s if settings else None
        self._shutdown_s = shutdown_timeout_s
        self._host = host
        self._port = port
        self._sock = sock
        self._ssl = ssl_context
        self._listener: asyncio.Server | None = None
        self._url: str | None = None
        self._set_up = False  # the runner has something to clean up
        self._closed = False

    @property
    def url(self) -> str:
        """`http(s)://HOST:PORT` as bound; raises before `start`."""
        if self._url is None:
            raise RuntimeError("ApiServer not started")
        return self._url

    async def start(self) -> str:
        if self._closed:
            raise RuntimeError("ApiServer closed")
        self._set_up = True  # even a setup that fails half-way is cleaned up
        await self._runner.setup()
        server = self._runner.server
        assert server is not None  # setup() made it
        loop = asyncio.get_running_loop()

        def handler() -> ApiRequestHandler:  # what `server()` makes, with our error replies
            return ApiRequestHandler(server, loop=loop, **self._handler_args)

        factory = handler if self._deadlines is None else self._deadlines.wrap(handler)
        where: dict[str, Any] = (
            {"sock": self._sock} if self._sock is not None
            else {"host": self._host, "port": self._port})
        if self._ssl is None:
            self._listener = await loop.create_server(factory, backlog=_BACKLOG, **where)
        else:  # a TLS handshake that never ends is as slow as headers that never come
            self._listener = await loop.create_server(
                factory, backlog=_BACKLOG, ssl=self._ssl,
                ssl_handshake_timeout=self._handshake_s, **where)
        host, port = self._listener.sockets[0].getsockname()[:2]
        scheme = "https" if self._ssl is not None else "http"
        shown = f"[{host}]" if ":" in host else host
        self._url = f"{scheme}://{shown}:{port}"
        return self._url

    async def close(self) -> None:
        """Stops serving; idempotent, and safe after a start that failed or never came."""
        if self._closed:
            return
        self._closed = True
        if not self._set_up:
            return
        listener, self._listener = self._listener, None
        if listener is not None:
            listener.close()  # no new connections from here on
        # on_shutdown closes WebSockets, the server closes connections, cleanup_ctx unwinds.
        await self._runner.cleanup()
        if listener is not None:
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(listener.wait_closed(), self._shutdown_s)

    async def __aenter__(self) -> ApiServer:
        await self.start()
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None,
                        exc: BaseException | None, tb: TracebackType | None) -> None:
        await self.close()


def bind(host: str, port: int) -> socket.socket:
    """A listening socket for the API, bound now: a port in use fails before anything else."""
    # An ASCII host goes as bytes: for a str, getaddrinfo encodes it with the idna codec,
    # whose import (stringprep's tables) the process then keeps (~0.15 MB idle, issue 27).
    name = (host.encode("ascii") if host.isascii() else host) if host else None
    try:
        infos = socket.getaddrinfo(name, port, type=socket.SOCK_STREAM,
                                   flags=socket.AI_PASSIVE)
        family, _, _, _, address = infos[0]
        sock = socket.socket(family, socket.SOCK_STREAM)
    except OSError as exc:
        raise OSError(exc.errno, f"cannot listen on {host}:{port}: {exc.strerror}") from exc
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(1024)
    except OSError as exc:
        sock.close()
        hint = "" if exc.errno != errno.EADDRINUSE else \
            " (another `rcan-rtps run`? --port chooses another, 0 any free one)"
        raise OSError(exc.errno, f"cannot listen on {host}:{port}: {exc.strerror}{hint}") \
            from exc
    sock.setblocking(False)
    return sock
