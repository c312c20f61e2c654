"""An MCP request at `/mcp` does not outlive its credential. A JWT (or a client certificate)
is checked when its request comes; the 2025 protocol's event stream (GET) is one request that
stays open for the whole session, and a tool call may be answered long after it was asked
(`wait_for_approval` waits up to 10 min). Before, an event stream opened with a token that
then ran out stayed open for good (its keep-alive pings every 15 s, and whatever the server
pushed on it), and held its session out of the idle cap's reach; a call's answer went to a
credential the bridge refuses. Now the stream ends when the credential runs out, and a call
answered after that is answered 401, the answer dropped. A session is its principal's, not
its token's: a fresh token of the same principal goes on in it; the expired one is refused.
Driven by the official SDK's client (and raw HTTP where the client hides the stream) against
the API in process."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

import aiohttp
import httpx2
import pytest
from aiohttp import web
from aiohttp.test_utils import TestClient, TestServer
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from jwthelpers import expiring_jwt, jwt_issuer
from mcp import Client
from mcp.client.streamable_http import streamable_http_client
from mcp.shared._httpx_utils import create_mcp_http_client
from mcp.shared.exceptions import MCPError
from waiting import eventually

from tests.api.apihelpers import Api
from tests.api.test_hitl_reviews import review
from tests.api.test_mcp_http import AGENT, CLIENT, _endpoint, data
from tests.api.test_redteam26_cert_expiry import _soon
from tests.api.test_tls import Pki, mtls_api, pki  # noqa: F401 (fixtures)

INITIALIZE = {"jsonrpc": "2.0", "id": 1, "method": "initialize", "params": {
    "protocolVersion": "2025-06-18", "capabilities": {},
    "clientInfo": {"name": "raw", "version": "1"}}}
INITIALIZED = {"jsonrpc": "2.0", "method": "notifications/initialized"}


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[Api]:
    harness = await Api(tmp_path).start()
    yield harness
    await harness.close()


@pytest.fixture
async def jwt_api(tmp_path: Path) -> AsyncIterator[tuple[Api, Ed25519PrivateKey]]:
    key, trusted = jwt_issuer(tmp_path)
    api = await Api(tmp_path, api_extra=trusted).start()
    yield api, key
    await api.close()


def token(api: Api, key: Ed25519PrivateKey, left_s: float) -> str:
    """An OPERATOR's JWT (agent-7) taken for `left_s` more seconds (its exp, plus the
    leeway)."""
    return expiring_jwt(key, api.clock.time(), left_s, sub="agent-7", role="OPERATOR")


def headers_with(jwt: str, session: str | None = None) -> dict[str, str]:
    sent = {"Authorization": f"Bearer {jwt}", "Accept": "application/json, text/event-stream",
            "Mcp-Protocol-Version": "2025-06-18", **AGENT}
    return sent | ({"Mcp-Session-Id": session} if session else {})


async def raw_session(api: Api, jwt: str) -> str:
    """A 2025 session opened over plain HTTP: its id."""
    async with api.http.post("/mcp", json=INITIALIZE, headers=headers_with(jwt)) as resp:
        assert resp.status == 200, await resp.text()
        session = resp.headers["Mcp-Session-Id"]
    async with api.http.post("/mcp", json=INITIALIZED,
                             headers=headers_with(jwt, session)) as resp:
        assert resp.status == 202, await resp.text()
    return session


async def test_the_event_stream_ends_when_its_jwt_runs_out(
        jwt_api: tuple[Api, Ed25519PrivateKey]) -> None:
    api, key = jwt_api
    jwt = token(api, key, 0.5)
    session = await raw_session(api, jwt)
    get = {**headers_with(jwt, session), "Accept": "text/event-stream"}
    async with api.http.get("/mcp", headers=get) as stream:
        assert stream.status == 200 and stream.content_type == "text/event-stream"
        api.clock.advance(5)  # the token has run out; the stream was open before
        # It ends (the SDK's pings come every 15 s, for as long as it is open: 30 s of
        # waiting is a stream left open).
        rest = await asyncio.wait_for(stream.content.read(), timeout=30)
    assert b"event: message" not in rest, rest  # nothing was pushed on it
    async with api.http.get("/mcp", headers=get) as again:  # and it opens no more
        assert again.status == 401


async def test_a_configured_tokens_event_stream_stays_open(api: Api) -> None:
    """A credential that does not expire keeps its stream, whatever the clock says."""
    session = await raw_session(api, "planner-token-0123456789abcdef")
    get = {**headers_with("planner-token-0123456789abcdef", session),
           "Accept": "text/event-stream"}
    async with api.http.get("/mcp", headers=get) as stream:
        assert stream.status == 200
        api.clock.advance(10 * 24 * 3600)
        with pytest.raises(asyncio.TimeoutError):
            await asyncio.wait_for(stream.content.read(), timeout=2)


@contextlib.asynccontextmanager
async def sdk_agent(api: Api, jwt: str) -> AsyncIterator[tuple[Client, httpx2.AsyncClient]]:
    """The SDK's client in a 2025 session, and its HTTP client (whose token a test swaps)."""
    url = str(api.http.make_url("/mcp"))
    async with create_mcp_http_client(headers={"Authorization": f"Bearer {jwt}", **AGENT}
                                      ) as web, \
            Client(streamable_http_client(url, http_client=web), client_info=CLIENT,
                   mode="legacy") as client:
        yield client, web


async def test_a_session_is_the_principals_not_its_tokens(
        jwt_api: tuple[Api, Ed25519PrivateKey]) -> None:
    api, key = jwt_api
    first = token(api, key, 60)
    async with sdk_agent(api, first) as (client, web):
        statuses: list[int] = []

        async def note(response: httpx2.Response) -> None:
            if response.request.method == "POST":
                statuses.append(response.status_code)

        web.event_hooks = {"response": [note]}
        assert not (await client.call_tool("get_status", {})).is_error
        api.clock.advance(120)  # the first token has run out
        fresh = f"Bearer {token(api, key, 60)}"
        web.headers["Authorization"] = fresh
        renewed = await client.call_tool("move", {"linear_x": 0.2, "duration_s": 1.0,
                                                  "confidence": 0.9})
        assert data(renewed)["outcome"] == "executed", renewed
        web.headers["Authorization"] = f"Bearer {first}"
        with pytest.raises(MCPError):  # (the SDK's client says no more of a 401)
            await asyncio.wait_for(client.call_tool("get_status", {}), timeout=30)
        assert statuses[-1] == 401, statuses
        web.headers["Authorization"] = fresh  # (its DELETE, as it leaves)
    moved = [e for e in api.entries if e.get("action_type") == "move"
             and e["event"] == "COMMAND_DISPATCHED"]
    assert [e["principal"] for e in moved] == ["jwt:/agent-7"]


async def test_a_call_answered_after_its_jwt_ran_out_is_refused(
        jwt_api: tuple[Api, Ed25519PrivateKey]) -> None:
    """`wait_for_approval`, asked while the token held, answered once it had run out: the
    decision is not sent to the expired credential (401). The held command does not outlive
    that credential either (red team 30): an approval is refused, and it is withdrawn."""
    api, key = jwt_api
    jwt = token(api, key, 60)
    session = await raw_session(api, jwt)
    held = {"jsonrpc": "2.0", "id": 2, "method": "tools/call", "params": {
        "name": "arm_joint", "arguments": {"joints": ["elbow"], "positions": [0.5],
                                           "duration_s": 1.0, "confidence": 0.9}}}
    async with api.http.post("/mcp", json=held, headers=headers_with(jwt, session)) as resp:
        reply = await resp.json()
    pending_id = reply["result"]["structuredContent"]["pending_id"]
    wait = {"jsonrpc": "2.0", "id": 3, "method": "tools/call", "params": {
        "name": "wait_for_approval", "arguments": {"pending_id": pending_id,
                                                   "timeout_s": 60}}}

    async def waiting() -> tuple[int, str]:
        async with api.http.post("/mcp", json=wait,
                                 headers=headers_with(jwt, session)) as resp:
            return resp.status, await resp.text()

    answer = asyncio.create_task(waiting())
    await asyncio.sleep(0.3)
    assert not answer.done()
    api.clock.advance(120)  # the token runs out while the call waits
    status, approved = await review(api, "authorize", "ops", pending_id)
    assert (status, approved.get("reason")) == (409, "issuer_credential_expired"), approved
    status, text = await asyncio.wait_for(answer, 30)
    assert status == 401, text
    assert "CREDENTIAL_EXPIRED" in text and "withdrawn" not in text and pending_id not in text
    assert [c for c in api.dispatcher.calls if c[0] == "arm_joint"] == []


MOVE_30S = {"linear_x": 0.2, "duration_s": 30.0, "confidence": 0.9}  # the harness's longest


def heard_at(api: Api) -> float | None:
    """When the governor last heard the agent's control session (its clock's monotonic)."""
    last = api.gov._sessions._last.get("jwt:/agent-7")
    return None if last is None else last[1]


async def test_a_moves_heartbeats_end_with_its_jwt(
        jwt_api: tuple[Api, Ed25519PrivateKey]) -> None:
    """The session's server heartbeats the principal's timed move while it runs: as the
    principal, so no longer than its credential holds (REST would refuse those heartbeats).
    Before, they went on to the move's end (a goal's: to the goal's end) after the token had
    run out. Now the move is not held any more: its control session lapses by the bridge's
    rules (`safety.session_timeout_s`), and the bridge stops it."""
    api, key = jwt_api
    async with sdk_agent(api, token(api, key, 40)) as (client, _):
        moving = await client.call_tool("move", MOVE_30S)
        assert data(moving)["outcome"] == "executed", moving
        keepalive = _endpoint(api)._keepalives["jwt:/agent-7"]
        assert keepalive.holding
        api.clock.advance(45)  # the token has run out; the session (60 s) has not lapsed
        # (held for the move's 30 s otherwise: 10 s of waiting is a move still held)
        await eventually(lambda: not keepalive.holding, what="the move no longer held")
        expired_at = api.clock.monotonic()
        assert (heard_at(api) or 0) < expired_at  # no heartbeat after the token ran out
        api.clock.advance(61)  # the session's silence: the bridge stops the move
        await api.gov.sweep()
    assert [action for action, _ in api.dispatcher.calls] == ["move", "stop"]
    lost = [e for e in api.entries if e["event"] == "NETWORK_LOSS_SAFE_STOP"]
    assert [e["principal"] for e in lost] == ["jwt:/agent-7"]


async def test_a_fresh_jwt_keeps_its_principals_move_held(
        jwt_api: tuple[Api, Ed25519PrivateKey]) -> None:
    api, key = jwt_api
    async with sdk_agent(api, token(api, key, 40)) as (client, web):
        moving = await client.call_tool("move", MOVE_30S)
        assert data(moving)["outcome"] == "executed", moving
        api.clock.advance(30)
        web.headers["Authorization"] = f"Bearer {token(api, key, 600)}"
        assert not (await client.call_tool("get_status", {})).is_error  # the fresh token
        api.clock.advance(20)  # the first token has run out, the fresh one has not
        now = api.clock.monotonic()
        await eventually(lambda: heard_at(api) == now, what="a heartbeat after the renewal")
        assert _endpoint(api)._keepalives["jwt:/agent-7"].holding


async def test_the_event_stream_ends_at_its_client_certificates_not_after(
        mtls_api: tuple[Api, str], pki: Pki) -> None:  # noqa: F811
    """The same for a client certificate's principal (its credential ends at the notAfter)."""
    api, url = mtls_api
    ops = pki.context(pki.client("ops", not_after=_soon(api, 5)))
    sent = {k: v for k, v in headers_with("-").items() if k != "Authorization"}
    async with aiohttp.ClientSession() as web:
        async with web.post(url + "/mcp", json=INITIALIZE, headers=sent, ssl=ops) as resp:
            assert resp.status == 200, await resp.text()
            session = resp.headers["Mcp-Session-Id"]
        sent["Mcp-Session-Id"] = session
        async with web.post(url + "/mcp", json=INITIALIZED, headers=sent, ssl=ops) as resp:
            assert resp.status == 202
        async with web.get(url + "/mcp", headers={**sent, "Accept": "text/event-stream"},
                           ssl=ops) as stream:
            assert stream.status == 200
            api.clock.advance(10)  # past the notAfter; the connection stays open
            rest = await asyncio.wait_for(stream.content.read(), timeout=30)
    assert b"event: message" not in rest, rest


async def test_an_answer_begun_as_its_jwt_runs_out_does_not_leave_the_client_waiting(
        tmp_path: Path) -> None:
    """(red team 29) The credential ran out as an answer's head (its Content-Length) was
    written: its body was then dropped and the response ended on a connection kept alive,
    so the SDK's client waited for the bytes the head promised (its read timeout: 5 min).
    Now an answer of a known length goes whole, head and body together, or is answered 401
    whole (as a call answered after the expiry is): here it was on its way, so it goes."""
    key, trusted = jwt_issuer(tmp_path)
    api = Api(tmp_path, api_extra=trusted)
    app = await api.build()
    armed: list[bool] = []

    async def time_passes(request: web.Request, response: web.StreamResponse) -> None:
        answer = request.method == "POST" and response.status == 200  # (no stream's head)
        if armed and answer and request.path == "/mcp":
            armed.clear()
            api.clock.advance(120)  # as the head is written: the token has run out

    app.on_response_prepare.append(time_passes)
    api.client = TestClient(TestServer(app, host="127.0.0.1"))
    await api.client.start_server()
    try:
        async with sdk_agent(api, token(api, key, 60)) as (client, web_client):
            await client.list_tools()  # (the SDK's client asks before its first call's end)
            armed.append(True)
            # (30 s of waiting is a client left waiting: its read timeout is 300 s)
            status = await asyncio.wait_for(client.call_tool("get_status", {}), timeout=30)
            assert not armed and not status.is_error, status  # begun as it ran out: whole
            web_client.headers["Authorization"] = f"Bearer {token(api, key, 60)}"  # (DELETE)
    finally:
        await api.close()
