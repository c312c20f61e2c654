"""Every response says `nosniff`, and is not stored unless it says how it may be cached.

Before, only the console's files said `nosniff` (red team 19); JSON answers, errors and the
WebSocket ticket said nothing of caching, so a browser could keep an audit page or a ticket
on disk.
"""

from __future__ import annotations

import pytest

from tests.api.apihelpers import Api, auth

NOT_STORED = ("nosniff", "no-store")


@pytest.mark.parametrize(("method", "path", "who", "status"), [
    ("GET", "/api/status", "planner", 200),
    ("GET", "/api/status", None, 401),
    ("GET", "/api/audit?since=0", "root", 200),
    ("POST", "/api/ws-ticket", "viewer", 200),
    ("GET", "/api/no-such-route", "planner", 404),
    ("POST", "/api/status", "planner", 405),
    ("POST", "/api/command", "planner", 400),  # no body: a refusal from the intake
])
async def test_api_answers_are_not_sniffed_or_stored(api: Api, method: str, path: str,
                                                     who: str | None, status: int) -> None:
    async with api.http.request(method, path, headers=auth(who) if who else {}) as resp:
        assert resp.status == status, (resp.status, await resp.text())
        said = (resp.headers.get("X-Content-Type-Options"), resp.headers.get("Cache-Control"))
        assert said == NOT_STORED, (path, said)


async def test_answers_that_say_how_they_are_cached_keep_it(api: Api) -> None:
    for path in ("/", "/.well-known/rcan-node.json"):
        async with api.http.get(path) as resp:
            assert resp.status == 200, path
            assert resp.headers.getall("X-Content-Type-Options") == ["nosniff"], path
            assert resp.headers.getall("Cache-Control") == ["no-cache"], path
