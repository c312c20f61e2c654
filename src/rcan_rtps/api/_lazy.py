"""Routes whose handlers, and the modules they need, are made by their first request.

Most runs are never asked for the console, the WebSocket, MCP, the manifests or an audit
export: a module not imported is idle memory not spent (issue 27). The first request pays
the import (a few ms, on the loop, once); every later one finds the handler made.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Generic, TypeVar

from aiohttp import web

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]
T = TypeVar("T")


class FirstUse(Generic[T]):
    """An object its first user makes (`get`), with the modules `make` imports; `made` is
    None until then (so a shutdown closes only what was made)."""

    def __init__(self, make: Callable[[], T]) -> None:
        self._make = make
        self.made: T | None = None

    def get(self) -> T:
        if self.made is None:
            self.made = self._make()
        return self.made


def on_first_request(build: Callable[[], Handler]) -> Handler:
    """A handler that calls `build` on its first request (on the loop, once) and hands that
    request, and every later one, to the handler `build` made."""
    built: list[Handler] = []

    async def handle(request: web.Request) -> web.StreamResponse:
        if not built:
            built.append(build())
        return await built[0](request)

    return handle
