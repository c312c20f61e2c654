"""Serving the app: an `ApiServer` that binds, reports its URL, and shuts down in order."""

from __future__ import annotations

import socket
import ssl
from types import TracebackType

from aiohttp import web


class ApiServer:
    """`async with ApiServer(app, host=..., port=0) as server: server.url` — port 0 picks one."""

    def __init__(self, app: web.Application, *, host: str, port: int,
                 ssl_context: ssl.SSLContext | None = None,
                 shutdown_timeout_s: float = 5.0, sock: socket.socket | None = None) -> None:
        """`sock`: a socket bound beforehand (see `bind`), used instead of host and port."""
        self._runner = web.AppRunner(app, access_log=None,
                                     shutdown_timeout=shutdown_timeout_s)
        self._host = host
        self._port = port
        self._sock = sock
        self._ssl = ssl_context
        self._url: str | None = None

    @property
    def url(self) -> str:
        """`http(s)://HOST:PORT` as bound; raises before `start`."""
        if self._url is None:
            raise RuntimeError("ApiServer not started")
        return self._url

    async def start(self) -> str:
        await self._runner.setup()
        site: web.BaseSite
        if self._sock is not None:
            site = web.SockSite(self._runner, self._sock, ssl_context=self._ssl)
        else:
            site = web.TCPSite(self._runner, self._host, self._port, ssl_context=self._ssl)
        await site.start()
        host, port = self._runner.addresses[0][:2]
        scheme = "https" if self._ssl is not None else "http"
        shown = f"[{host}]" if ":" in host else host
        self._url = f"{scheme}://{shown}:{port}"
        return self._url

    async def close(self) -> None:
        await self._runner.cleanup()  # on_shutdown closes WebSockets, then cleanup_ctx unwinds

    async def __aenter__(self) -> ApiServer:
        await self.start()
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None,
                        exc: BaseException | None, tb: TracebackType | None) -> None:
        await self.close()


def bind(host: str, port: int) -> socket.socket:
    """A listening socket for the API, bound now: a port in use fails before anything else."""
    try:
        infos = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM,
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
        raise OSError(exc.errno, f"cannot listen on {host}:{port}: {exc.strerror}") from exc
    sock.setblocking(False)
    return sock
