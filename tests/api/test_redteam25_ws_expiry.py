"""Red team 25: a WebSocket does not outlive its JWT.

A JWT is checked when its request comes; a WebSocket is one request that lasts. A socket
opened with a token that then expired went on commanding the robot, heartbeating its control
session and receiving the held commands, for as long as it stayed open (hours, after a token
of minutes). Now it is closed (1008 "credential expired") once the token has run out: at its
first frame after that, or when its time is up while it is idle. A stop sent on it then still
stops; nothing else of it is taken."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from jwthelpers import expiring_jwt, jwt_issuer

from tests.api.apihelpers import Api


@pytest.fixture
async def jwt_api(tmp_path: Path) -> AsyncIterator[tuple[Api, Ed25519PrivateKey]]:
    key, trusted = jwt_issuer(tmp_path)
    api = await Api(tmp_path, api_extra=trusted).start()
    yield api, key
    await api.close()


def token(api: Api, key: Ed25519PrivateKey, left_s: float) -> str:
    """A USER's JWT taken for `left_s` more seconds (its exp, plus the leeway)."""
    return expiring_jwt(key, api.clock.time(), left_s, sub="planner-7", role="USER")


async def outcome(ws: aiohttp.ClientWebSocketResponse) -> dict[str, Any]:
    while True:
        msg = await asyncio.wait_for(ws.receive(), timeout=30)
        assert msg.type is aiohttp.WSMsgType.TEXT, msg
        frame = json.loads(msg.data)
        if frame["type"] == "outcome":
            return dict(frame)


async def closed(ws: aiohttp.ClientWebSocketResponse) -> list[dict[str, Any]]:
    """The outcome frames before the socket closed, once it has (status frames go on for as
    long as it is open: 30 s of them is a socket left open)."""
    return await asyncio.wait_for(_closed(ws), timeout=30)


async def _closed(ws: aiohttp.ClientWebSocketResponse) -> list[dict[str, Any]]:
    outcomes = []
    while True:
        msg = await ws.receive()
        if msg.type is not aiohttp.WSMsgType.TEXT:
            break
        frame = json.loads(msg.data)
        if frame["type"] == "outcome":
            outcomes.append(frame)
    assert msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED), msg
    return outcomes


MOVE = json.dumps({"action": "move", "params": {"linear_x": 0.2, "duration_s": 1.0}})


async def test_a_socket_whose_jwt_expired_commands_nothing(
        jwt_api: tuple[Api, Ed25519PrivateKey]) -> None:
    api, key = jwt_api
    headers = {"Authorization": f"Bearer {token(api, key, 600)}"}
    async with api.http.ws_connect("/api/ws", headers=headers) as ws:
        await ws.send_str(MOVE)
        assert (await outcome(ws))["http_status"] == 200  # while the token holds
        api.clock.advance(601)
        await ws.send_str(MOVE)
        assert await closed(ws) == []
        assert ws.close_code == aiohttp.WSCloseCode.POLICY_VIOLATION
    assert [a for a, _ in api.dispatcher.calls].count("move") == 1
    # (A REST request with the same token is refused alike.)
    async with api.http.post("/api/command", data=MOVE, headers=headers) as resp:
        assert resp.status == 401


async def test_a_stop_on_an_expired_socket_still_stops(
        jwt_api: tuple[Api, Ed25519PrivateKey]) -> None:
    api, key = jwt_api
    headers = {"Authorization": f"Bearer {token(api, key, 600)}"}
    async with api.http.ws_connect("/api/ws", headers=headers) as ws:
        api.clock.advance(601)
        await ws.send_str(json.dumps({"action": "stop"}))
        [stopped] = await closed(ws)
        assert (stopped["http_status"], stopped["body"]["outcome"]) == (200, "executed")
    assert [a for a, _ in api.dispatcher.calls] == ["stop"]


async def test_an_idle_socket_is_closed_when_its_jwt_runs_out(
        jwt_api: tuple[Api, Ed25519PrivateKey]) -> None:
    api, key = jwt_api
    headers = {"Authorization": f"Bearer {token(api, key, 0.2)}"}
    async with api.http.ws_connect("/api/ws", headers=headers) as ws:
        api.clock.advance(1)  # its time is up; the socket sends nothing
        await closed(ws)
        assert ws.close_code == aiohttp.WSCloseCode.POLICY_VIOLATION


async def test_a_configured_token_s_socket_stays_open(api: Api) -> None:
    """A configured token does not expire: nothing changes for its sockets."""
    async with api.http.ws_connect("/api/ws", headers={
            "Authorization": "Bearer planner-token-0123456789abcdef"}) as ws:
        api.clock.advance(10 * 24 * 3600)
        await ws.send_str(MOVE)
        assert (await outcome(ws))["http_status"] == 200


@pytest.mark.parametrize("deaf", [False, True])
async def test_a_credential_run_out_before_the_wait_still_times_the_wait_out(
        deaf: bool) -> None:
    """The credential may run out while a frame is handled (a stop waiting for room in its
    lane): the next wait is then for a credential with no time left. aiohttp takes a receive
    timeout of 0 as none at all, so a wait of 0 left the socket open for good — pushed the
    held commands, status and goals as long as its client kept it (review of red team 25).
    Here a real aiohttp socket waits as `_serve` would: its wait ends, and nothing is lost
    of a frame already come (it is read first)."""
    from aiohttp import web
    from aiohttp.test_utils import TestClient, TestServer

    from rcan_rtps.api._ws import _wait_s

    ended: asyncio.Queue[str] = asyncio.Queue()

    async def handler(request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse()
        await ws.prepare(request)
        for _ in range(2):  # the frame already come, then the wait that must end
            try:
                msg = await ws.receive(timeout=_wait_s(deaf, -1.0))
                await ended.put(f"frame {msg.data}")
            except asyncio.TimeoutError:
                await ended.put("timed out")
        await ws.close()
        return ws

    app = web.Application()
    app.router.add_get("/ws", handler)
    async with TestClient(TestServer(app)) as client, client.ws_connect("/ws") as ws:
        await ws.send_str("stop")
        assert await asyncio.wait_for(ended.get(), timeout=10) == "frame stop"
        assert await asyncio.wait_for(ended.get(), timeout=10) == "timed out"
