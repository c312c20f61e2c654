"""A local HTTP endpoint on 127.0.0.1 for tests that give the bridge a URL to call (webhooks)."""

from __future__ import annotations

from collections.abc import Awaitable, Callable

from aiohttp import web


async def serve_post(path: str, handler: Callable[[web.Request], Awaitable[web.Response]]
                     ) -> tuple[web.AppRunner, str]:
    """`handler` serving POSTs to `path` on a free port: (runner, its URL). Clean up the
    runner after."""
    app = web.Application()
    app.router.add_post(path, handler)
    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    await web.TCPSite(runner, "127.0.0.1", 0).start()
    host, port = runner.addresses[0][:2]
    return runner, f"http://{host}:{port}{path}"
