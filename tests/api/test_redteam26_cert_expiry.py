"""Red team 26: a client certificate's principal does not outlive the certificate.

Python's `ssl` refuses an expired certificate at the handshake, and only there: a connection
opened before its notAfter (kept alive, resumed, or a WebSocket) went on acting as its
principal, which had no expiry, for as long as it stayed open. Now the principal's credential
ends at the certificate's notAfter, read at every request and judged by the latest wall time
(as a JWT's `exp`): a request after it is refused 401 `certificate_expired`, a WebSocket is
closed 1008 "credential expired", and so is one a ticket asked for over it opened.

Real TLS on 127.0.0.1 with certificates made here; the handshake judges them by the real clock,
the app by its own (`api.clock`), which the tests move past the notAfter."""

from __future__ import annotations

import asyncio
import datetime as dt
import ssl
from types import SimpleNamespace
from typing import Any

import aiohttp

from tests.api.apihelpers import Api, auth
from tests.api.test_tls import Pki, mtls_api, pki  # noqa: F401 (fixtures)

EXPIRED = "certificate_expired"


def _soon(api: Api, seconds: float) -> dt.datetime:
    """A notAfter `seconds` ahead of the app's clock (and, as that is, of the real one)."""
    return dt.datetime.fromtimestamp(api.clock.time() + seconds, dt.timezone.utc)


def _session(reused: list[bool]) -> aiohttp.ClientSession:
    """A keep-alive client that notes, for each request, whether it reused a connection."""
    trace = aiohttp.TraceConfig()

    async def created(session: Any, context: SimpleNamespace, params: Any) -> None:
        reused.append(False)

    async def again(session: Any, context: SimpleNamespace, params: Any) -> None:
        reused.append(True)

    trace.on_connection_create_end.append(created)
    trace.on_connection_reuseconn.append(again)
    return aiohttp.ClientSession(connector=aiohttp.TCPConnector(limit=1),
                                 trace_configs=[trace])


async def _post(session: aiohttp.ClientSession, url: str, context: ssl.SSLContext,
                path: str, headers: dict[str, str] | None = None) -> tuple[int, Any]:
    async with session.post(url + path, ssl=context, headers=headers) as resp:
        return resp.status, await resp.json()


async def test_a_kept_alive_connection_is_refused_once_its_certificate_expired(
        mtls_api: tuple[Api, str], pki: Pki) -> None:  # noqa: F811
    api, url = mtls_api
    ops = pki.context(pki.client("ops", not_after=_soon(api, 5)))
    reused: list[bool] = []
    async with _session(reused) as session:
        status, body = await _post(session, url, ops, "/api/heartbeat")
        assert (status, body["principal"]) == (200, "ops")
        api.clock.advance(10)  # past the notAfter; the connection stays open
        status, body = await _post(session, url, ops, "/api/heartbeat")
        assert (status, body["error_code"], body["reason"]) == (401, "UNAUTHENTICATED",
                                                                EXPIRED), body
        api.clock.advance(-20)  # a step back of the clock gives it no more time
        status, body = await _post(session, url, ops, "/api/command")
        assert (status, body.get("reason")) == (401, EXPIRED), body
        # A bearer token on that connection is the token's, as ever.
        status, body = await _post(session, url, ops, "/api/heartbeat", auth("planner"))
        assert (status, body["principal"]) == (200, "planner")
    assert reused == [False, True, True, True]  # one connection, handshaken once
    assert api.dispatcher.calls == []


async def _closed(ws: aiohttp.ClientWebSocketResponse) -> aiohttp.WSMessage:
    """The socket's close (status frames before it are read past)."""
    async def wait() -> aiohttp.WSMessage:
        while True:
            msg = await ws.receive()
            if msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED):
                return msg

    return await asyncio.wait_for(wait(), timeout=30)


async def test_a_websocket_opened_with_a_certificate_closes_at_its_notafter(
        mtls_api: tuple[Api, str], pki: Pki) -> None:  # noqa: F811
    api, url = mtls_api
    ops = pki.context(pki.client("ops", not_after=_soon(api, 2)))
    async with aiohttp.ClientSession() as session, session.ws_connect(
            url + "/api/ws", ssl=ops) as ws:
        first = await asyncio.wait_for(ws.receive_json(), timeout=30)
        assert first["type"] == "status"  # open, as ops
        api.clock.advance(10)
        msg = await _closed(ws)
        assert (ws.close_code, msg.extra) == (1008, "credential expired")


async def test_a_ticket_asked_for_with_a_certificate_ends_with_it(
        mtls_api: tuple[Api, str], pki: Pki) -> None:  # noqa: F811
    """Redeemed over another certificate's connection: the expiry is the ticket's asker's."""
    api, url = mtls_api
    ops = pki.context(pki.client("ops", not_after=_soon(api, 2)))
    stranger = pki.context(pki.client("stranger"))  # valid, and names no one
    async with aiohttp.ClientSession() as session:
        tickets = []
        for _ in range(2):
            status, body = await _post(session, url, ops, "/api/ws-ticket")
            assert status == 200, body
            tickets.append(body["ticket"])
        async with session.ws_connect(f"{url}/api/ws?ticket={tickets[0]}",
                                      ssl=stranger) as ws:
            assert (await asyncio.wait_for(ws.receive_json(), timeout=30))["type"] == "status"
            api.clock.advance(10)
            await ws.ping()  # its next frame finds the credential run out
            msg = await _closed(ws)
            assert (ws.close_code, msg.extra) == (1008, "credential expired")
        async with session.get(f"{url}/api/ws?ticket={tickets[1]}", ssl=stranger) as resp:
            assert (resp.status, (await resp.json())["reason"]) == (401, EXPIRED)


async def test_a_certificate_is_its_principal_until_its_notafter(
        mtls_api: tuple[Api, str], pki: Pki) -> None:  # noqa: F811
    api, url = mtls_api
    ops = pki.context(pki.client("ops", not_after=_soon(api, 5)))
    async with aiohttp.ClientSession() as session:
        api.clock.advance(4)
        status, body = await _post(session, url, ops, "/api/heartbeat")
        assert (status, body["principal"]) == (200, "ops")
