"""Red team 19: what a page on another origin, or a low role, can make the bridge do through
credentials a browser sends by itself (a client certificate), and through the console's
WebSocket tickets.

Each test here failed on main (2177b79) before its fix; see each test's docstring.
"""

from __future__ import annotations

import json
import ssl
from collections.abc import AsyncIterator
from pathlib import Path

import aiohttp
import pytest

from tests.api.apihelpers import Api, auth
from tests.api.test_tls import Pki, _serve

EVIL = "https://evil.example"
MOVE = {"action": "move", "params": {"linear_x": 0.2}}


@pytest.fixture
def pki(tmp_path: Path) -> Pki:
    (tmp_path / "pki").mkdir()
    return Pki(tmp_path / "pki")


@pytest.fixture
async def mtls_api(tmp_path: Path, pki: Pki) -> AsyncIterator[tuple[Api, str]]:
    async for served in _serve(tmp_path, pki, mutual=True):
        yield served


async def _post_as_a_form(url: str, context: ssl.SSLContext, path: str, origin: str,
                          body: object) -> int:
    """What a page's `<form enctype="text/plain">` (or a no-cors fetch) sends: no preflight,
    the browser's client certificate, and the page's `Origin`."""
    async with aiohttp.ClientSession() as session, session.post(
            url + path, ssl=context, data=json.dumps(body),
            headers={"Origin": origin, "Content-Type": "text/plain"}) as resp:
        await resp.read()
        return resp.status


async def test_a_page_on_another_origin_cannot_command_with_the_browsers_certificate(
        mtls_api: tuple[Api, str], pki: Pki) -> None:
    """A browser presents its client certificate to the bridge whichever page made the
    request, and a text/plain POST needs no preflight: a page on any site could move the
    robot, clear an e-stop or approve a held command as the certificate's principal (the
    motion below was dispatched, 200). A certificate (like a ticket) now authenticates a
    request only from no origin (not a browser) or the bridge's own."""
    api, url = mtls_api
    ops = pki.context(pki.client("ops"))
    for body in (MOVE, {"action": "clear_estop"}):
        assert await _post_as_a_form(url, ops, "/api/command", EVIL, body) == 401
    assert api.dispatcher.calls == []
    # the same request from the bridge's own origin, or from no browser, is the principal's
    assert await _post_as_a_form(url, ops, "/api/heartbeat", url, {}) == 200
    async with aiohttp.ClientSession() as session, session.post(
            url + "/api/command", ssl=ops, json=MOVE) as resp:
        assert resp.status == 200


async def test_a_page_on_another_origin_cannot_open_the_websocket_with_the_certificate(
        mtls_api: tuple[Api, str], pki: Pki) -> None:
    """A WebSocket is no CORS request: a page anywhere could open `/api/ws` with the
    browser's certificate and send commands over it (a cross-site WebSocket hijack)."""
    api, url = mtls_api
    ops = pki.context(pki.client("ops"))
    async with aiohttp.ClientSession() as session:
        with pytest.raises(aiohttp.WSServerHandshakeError) as caught:
            async with session.ws_connect(url + "/api/ws", ssl=ops,
                                          headers={"Origin": EVIL}) as ws:
                await ws.send_str(json.dumps(MOVE))
                await ws.receive(timeout=5)
        assert caught.value.status == 401
    assert api.dispatcher.calls == []


async def test_a_bearer_token_is_no_ambient_credential_and_still_counts_from_any_origin(
        mtls_api: tuple[Api, str], pki: Pki) -> None:
    """Not a regression: a bearer token is sent only by who holds it (a browser never adds
    one by itself), so a request with one is the token's, whatever its Origin says; and an
    e-stop with it stops."""
    api, url = mtls_api
    async with aiohttp.ClientSession() as session, session.post(
            url + "/api/command", ssl=pki.context(pki.client("ops")),
            headers={**auth("viewer"), "Origin": EVIL}, json={"action": "estop"}) as resp:
        assert resp.status == 200
        assert api.entry((await resp.json())["audit_id"])["principal"] == "viewer"


async def test_a_guest_asking_for_tickets_in_a_loop_leaves_the_operator_its_own(
        api: Api) -> None:
    """Tickets were bounded only in all (1024 unredeemed): a GUEST asking `POST
    /api/ws-ticket` in a loop (each lives 30 s) used them all, and every other principal's
    console got 429 and no live view, for as long as it kept asking. One principal now holds
    at most a few; the others still get theirs."""
    from rcan_rtps.api._keys import WS_TICKETS

    assert api.app is not None
    tickets = api.app[WS_TICKETS]
    tickets._max = 32  # the bound in all, made small (the test asks that many)
    answers = [await api.call("POST", "/api/ws-ticket", "viewer") for _ in range(32)]
    issued = [body["ticket"] for status, body in answers if status == 200]
    assert issued and answers[-1][0] == 429
    status, body = await api.call("POST", "/api/ws-ticket", "ops")
    assert status == 200, body
    async with api.http.ws_connect(f"/api/ws?ticket={body['ticket']}") as ws:
        assert (await ws.receive_json(timeout=5))["type"] in ("status", "approvals")
    # a ticket redeemed gives its principal room for one more
    async with api.http.ws_connect(f"/api/ws?ticket={issued[0]}") as ws:
        assert (await ws.receive_json(timeout=5))["type"] == "status"
    assert (await api.call("POST", "/api/ws-ticket", "viewer"))[0] == 200
    assert (await api.call("POST", "/api/ws-ticket", "viewer"))[0] == 429
