"""The console's routes (the page, `/api/whoami`, `/api/ws-ticket`; see `_console_pages`).

Registered at start; their handlers, the page's files and the modules serving them are made
by the first request for any of them: most runs are never opened in a browser (issue 27).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from aiohttp import web

from ._lazy import Handler

if TYPE_CHECKING:
    from ._console_pages import ConsolePages

PREFIX = "/console/"
WHOAMI_PATH = "/api/whoami"
TICKET_PATH = "/api/ws-ticket"


def is_console_path(path: str) -> bool:
    """The paths served without a principal: never one under `/api/`."""
    return path in ("/", PREFIX.rstrip("/")) or path.startswith(PREFIX)


def add_console(app: web.Application) -> None:
    made: list[ConsolePages] = []

    def route(pick: Callable[[ConsolePages], Handler]) -> Handler:
        async def handle(request: web.Request) -> web.StreamResponse:
            if not made:
                from ._console_pages import ConsolePages

                made.append(ConsolePages())
            return await pick(made[0])(request)

        return handle

    app.router.add_get("/", route(lambda pages: pages.to_console), allow_head=False)
    app.router.add_get(PREFIX.rstrip("/"), route(lambda pages: pages.to_console),
                       allow_head=False)
    app.router.add_get(PREFIX, route(lambda pages: pages.page), allow_head=False)
    app.router.add_get(PREFIX + "{name}", route(lambda pages: pages.file), allow_head=False)
    app.router.add_get(WHOAMI_PATH, route(lambda pages: pages.whoami), allow_head=False)
    app.router.add_post(TICKET_PATH, route(lambda pages: pages.ws_ticket))
