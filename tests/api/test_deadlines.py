"""Issue 9, slow peers: a real ApiServer on 127.0.0.1, spoken to over raw sockets.

Timeouts are configured short; the tests assert *what* happens (the server closes, answers
408), never how fast — each wait has only a generous bound against a hang. Where a deadline
must be the cause, the other timers are configured far longer than that bound.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import aiohttp
import msgspec
import pytest

from rcan_rtps.api import ApiServer, settings_from_config
from rcan_rtps.config import ConfigError
from tests.api.apihelpers import TOKENS, Api, auth, make_config

HANG_S = 120  # against a hang only; every other timer below is configured longer than this
LONG = 3000.0


@dataclass
class Served:
    api: Api
    host: str
    port: int
    url: str


async def _serve(tmp_path: Path, **timeouts: float) -> AsyncIterator[Served]:
    extra = "\n    ".join(f"{key}: {value}" for key, value in timeouts.items())
    api = Api(tmp_path, api_extra=extra)
    app = await api.build()
    async with ApiServer(app, host="127.0.0.1", port=0) as server:
        host, port = server.url.removeprefix("http://").split(":")
        yield Served(api, host, int(port), server.url)
    await api.close()


@pytest.fixture
async def short_headers(tmp_path: Path) -> AsyncIterator[Served]:
    async for served in _serve(tmp_path, header_timeout_s=0.5, body_timeout_s=LONG,
                               keepalive_timeout_s=LONG):
        yield served


@pytest.fixture
async def short_body(tmp_path: Path) -> AsyncIterator[Served]:
    async for served in _serve(tmp_path, header_timeout_s=LONG, body_timeout_s=0.5,
                               keepalive_timeout_s=LONG):
        yield served


async def _closed_by_server(reader: asyncio.StreamReader) -> bytes:
    """Everything the server sent until it closed (or reset) the connection. A server that
    closes while the peer is still sending resets it (TCP: unread data at close), and the
    reset can come right behind the answer: what arrived before it counts."""
    received = b""

    async def until_closed() -> None:
        nonlocal received
        while chunk := await reader.read(65536):
            received += chunk

    with contextlib.suppress(ConnectionResetError):
        await asyncio.wait_for(until_closed(), HANG_S)
    return received


async def _status(served: Served) -> int:
    async with aiohttp.ClientSession() as session, session.get(
            served.url + "/api/status", headers=auth("viewer")) as resp:
        return resp.status


async def test_200_connections_with_incomplete_headers_are_closed(short_headers: Served) -> None:
    partial = (f"GET /api/status HTTP/1.1\r\nHost: x\r\n"
               f"Authorization: Bearer {TOKENS['viewer']}\r\n").encode()  # no blank line

    async def slowloris() -> bytes:
        reader, writer = await asyncio.open_connection(short_headers.host, short_headers.port)
        writer.write(partial)
        await writer.drain()
        try:
            return await _closed_by_server(reader)
        finally:
            writer.close()

    answers = await asyncio.gather(*(slowloris() for _ in range(200)))
    assert answers == [b""] * 200  # closed, and no request was ever served
    assert await _status(short_headers) == 200  # the server itself is fine


async def test_silent_connection_is_closed(short_headers: Served) -> None:
    reader, writer = await asyncio.open_connection(short_headers.host, short_headers.port)
    assert await _closed_by_server(reader) == b""
    writer.close()


async def test_a_websocket_outlives_the_header_deadline(short_headers: Served) -> None:
    async with aiohttp.ClientSession() as session, session.ws_connect(
            short_headers.url + "/api/ws", headers=auth("planner")) as ws:
        await asyncio.sleep(1.5)  # three header deadlines: none applies to an open socket
        await ws.send_str(json.dumps({"action": "estop"}))
        while True:
            msg = await asyncio.wait_for(ws.receive(), HANG_S)
            assert msg.type is aiohttp.WSMsgType.TEXT, msg
            frame = json.loads(msg.data)
            if frame["type"] == "outcome":
                break
    assert (frame["http_status"], frame["body"]["outcome"]) == (200, "executed")


async def test_idle_keepalive_connection_is_closed(tmp_path: Path) -> None:
    async for served in _serve(tmp_path, header_timeout_s=LONG, body_timeout_s=LONG,
                               keepalive_timeout_s=0.5):
        reader, writer = await asyncio.open_connection(served.host, served.port)
        writer.write((f"GET /api/status HTTP/1.1\r\nHost: x\r\n"
                      f"Authorization: Bearer {TOKENS['viewer']}\r\n\r\n").encode())
        await writer.drain()
        # One complete response, then (idle) the server closes the kept-alive connection.
        answer = await _closed_by_server(reader)
        writer.close()
        assert answer.startswith(b"HTTP/1.1 200 ")
        assert answer.count(b"HTTP/1.1 ") == 1


def _post_head(length: int) -> bytes:
    return (f"POST /api/command HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            f"Authorization: Bearer {TOKENS['planner']}\r\nContent-Length: {length}\r\n\r\n"
            ).encode()


def _json_body(answer: bytes) -> dict[str, object]:
    body = answer.partition(b"\r\n\r\n")[2]
    decoded: dict[str, object] = msgspec.json.decode(body)
    return decoded


async def test_stalled_body_is_408(short_body: Served) -> None:
    before = len(short_body.api.entries)
    reader, writer = await asyncio.open_connection(short_body.host, short_body.port)
    writer.write(_post_head(100) + b'{"action": "estop"')  # 18 of 100 bytes, then nothing
    await writer.drain()
    answer = await _closed_by_server(reader)
    writer.close()
    assert answer.startswith(b"HTTP/1.1 408 ")
    body = _json_body(answer)
    assert (body["outcome"], body["error_code"], body["reason"]) == (
        "denied", "REQUEST_TIMEOUT", "body_timeout")
    assert len(short_body.api.entries) == before  # no request was complete: nothing audited
    assert short_body.api.dispatcher.calls == []


async def test_trickled_body_is_408(short_body: Served) -> None:
    reader, writer = await asyncio.open_connection(short_body.host, short_body.port)
    writer.write(_post_head(10_000))
    await writer.drain()

    async def trickle() -> None:  # a byte every 50 ms: always sending, never done in time
        while not writer.is_closing():
            writer.write(b" ")
            await writer.drain()
            await asyncio.sleep(0.05)

    sender = asyncio.create_task(trickle())
    try:
        answer = await _closed_by_server(reader)
    finally:
        sender.cancel()
        await asyncio.gather(sender, return_exceptions=True)
        writer.close()
    assert answer.startswith(b"HTTP/1.1 408 ")


async def test_a_prompt_body_still_works(short_body: Served) -> None:
    async with aiohttp.ClientSession() as session, session.post(
            short_body.url + "/api/command", json={"action": "move"},
            headers=auth("planner")) as resp:
        assert resp.status == 200


def test_timeouts_are_configured_under_bridge_api(tmp_path: Path) -> None:
    defaults = settings_from_config(make_config(tmp_path))
    assert (defaults.header_timeout_s, defaults.body_timeout_s,
            defaults.keepalive_timeout_s) == (10.0, 30.0, 30.0)
    config = make_config(tmp_path, api_extra="header_timeout_s: 2.5\n    body_timeout_s: 4\n"
                                             "    keepalive_timeout_s: 7")
    settings = settings_from_config(config)
    assert (settings.header_timeout_s, settings.body_timeout_s,
            settings.keepalive_timeout_s) == (2.5, 4.0, 7.0)
    with pytest.raises(ConfigError):
        make_config(tmp_path, api_extra="header_timeout_s: 0")
