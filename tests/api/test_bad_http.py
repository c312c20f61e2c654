"""Issue 23, item 8: what aiohttp's HTTP parser refuses, and clients that go away.

A real ApiServer on 127.0.0.1, spoken to over raw sockets, its log captured. A request head
over the limits is answered with the API's JSON error body (431), a request that is not HTTP
with a JSON 400, and neither logs an ERROR or a traceback (aiohttp's parser refuses them
before any middleware runs; before the fix: ERROR with a traceback, a text/plain 400). A
client that resets its connection mid-body (before: ERROR with a traceback) or mid-response
is no error either; a ConnectionError of the bridge's own, the client still there, still is.
"""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import struct
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from waiting import eventually

from rcan_rtps.api import ApiServer
from rcan_rtps.api._keys import DEADLINES
from rcan_rtps.governance import AuditEvent, AuditRecord
from tests.api.apihelpers import TOKENS, Api

HANG_S = 60  # against a hang only


@dataclass
class Served:
    api: Api
    host: str
    port: int


@pytest.fixture
async def served(tmp_path: Path) -> AsyncIterator[Served]:
    api = Api(tmp_path)
    app = await api.build()
    async with ApiServer(app, host="127.0.0.1", port=0) as server:
        host, port = server.url.removeprefix("http://").split(":")
        yield Served(api, host, int(port))
    await api.close()


@pytest.fixture
def log(caplog: pytest.LogCaptureFixture) -> pytest.LogCaptureFixture:
    caplog.set_level(logging.DEBUG)
    return caplog


def _assert_quiet(log: pytest.LogCaptureFixture) -> None:
    """No ERROR (or worse) and no traceback at any level."""
    loud = [f"{r.levelname} {r.name}: {r.getMessage()}" for r in log.records
            if r.levelno >= logging.ERROR or r.exc_info or r.exc_text]
    assert not loud, loud


async def _exchange(served: Served, head: bytes) -> tuple[int, dict[str, str], bytes]:
    """Sends `head` and reads until the server closes (after a refused head it must, as
    where the next request would begin is unknown): (status, headers, body)."""
    reader, writer = await asyncio.open_connection(served.host, served.port)
    try:
        writer.write(head)
        await writer.drain()
        data = await asyncio.wait_for(reader.read(), HANG_S)
    finally:
        writer.close()
    top, _, body = data.partition(b"\r\n\r\n")
    status_line, *fields = top.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, _, v in (f.partition(":") for f in fields)}
    return int(status_line.split()[1]), headers, body


def _json(headers: dict[str, str], body: bytes) -> Any:
    assert headers.get("content-type", "").startswith("application/json"), (headers, body)
    return json.loads(body)


def _request(*fields: bytes, target: bytes = b"/api/status") -> bytes:
    viewer = f"Authorization: Bearer {TOKENS['viewer']}\r\n".encode()
    return (b"GET " + target + b" HTTP/1.1\r\nHost: x\r\n" + viewer
            + b"".join(f + b"\r\n" for f in fields) + b"\r\n")


BIG = 9000  # over aiohttp's 8190-byte limit of a line or a field

HEADS = {
    "field value over 8 KB": _request(b"X-Big: " + b"a" * BIG),
    "field name over 8 KB": _request(b"X-" + b"n" * BIG + b": 1"),
    "cookie over 8 KB": _request(b"Cookie: c=" + b"c" * BIG),
    "200 fields": _request(*(b"X-F%d: 1" % i for i in range(200))),
    "request line over 8 KB": _request(target=b"/api/status?q=" + b"q" * BIG),
}


@pytest.mark.parametrize("head", list(HEADS.values()), ids=list(HEADS))
async def test_oversized_request_heads_get_a_json_431(
        served: Served, log: pytest.LogCaptureFixture, head: bytes) -> None:
    status, headers, body = await _exchange(served, head)
    assert status == 431, (status, body)
    reply = _json(headers, body)
    assert reply["outcome"] == "denied", reply
    assert reply["error_code"] == "REQUEST_HEADER_FIELDS_TOO_LARGE", reply
    _assert_quiet(log)
    assert any("431" in r.getMessage() for r in log.records), "no line says what was refused"


async def test_a_header_just_under_the_limit_is_served(served: Served) -> None:
    status, headers, body = await _exchange(
        served, _request(b"X-Big: " + b"a" * 8000, b"Connection: close"))
    assert status == 200, body
    assert _json(headers, body)["ruri"]


@pytest.mark.parametrize("head", [b"HELLO\r\n\r\n", b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\r\n\r\n",
                                  b"GET /api/status HTTP/1.1\r\nBad Header\r\n\r\n"],
                         ids=["not HTTP", "TLS to the HTTP port", "field without a colon"])
async def test_a_request_that_is_not_http_gets_a_json_400(
        served: Served, log: pytest.LogCaptureFixture, head: bytes) -> None:
    status, headers, body = await _exchange(served, head)
    assert status == 400, (status, body)
    reply = _json(headers, body)
    assert (reply["outcome"], reply["error_code"]) == ("denied", "BAD_REQUEST"), reply
    _assert_quiet(log)


def _reset(writer: asyncio.StreamWriter) -> None:
    """Close with an RST (SO_LINGER 0), as a crashed or killed client does."""
    sock = writer.get_extra_info("socket")
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    writer.transport.abort()


async def _still_serving(served: Served) -> None:
    status, headers, body = await _exchange(served, _request(b"Connection: close"))
    assert status == 200 and _json(headers, body)["ruri"], (status, body)


@pytest.mark.parametrize("path", ["/api/command", "/api/hitl/authorize"])
async def test_a_reset_mid_body_is_no_error(served: Served, log: pytest.LogCaptureFixture,
                                            path: str) -> None:
    audited = len(served.api.entries)
    reader, writer = await asyncio.open_connection(served.host, served.port)
    try:
        writer.write(f"POST {path} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer "
                     f"{TOKENS['ops']}\r\nContent-Type: application/json\r\n"
                     "Expect: 100-continue\r\nContent-Length: 1000\r\n\r\n"
                     '{"action"'.encode())
        # "100 Continue": the request reached the app, whose handler now reads the body.
        interim = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HANG_S)
        assert interim.startswith(b"HTTP/1.1 100"), interim
    finally:
        _reset(writer)
    await eventually(lambda: any(f"POST {path}" in r.getMessage() for r in log.records),
                     timeout=HANG_S, what="a log line about the request cut off")
    await _still_serving(served)
    _assert_quiet(log)
    assert len(served.api.entries) == audited  # no request was ever complete: nothing decided


async def test_a_reset_mid_response_is_no_error(served: Served,
                                                log: pytest.LogCaptureFixture) -> None:
    """A client that asked for a large audit page and resets while it comes."""
    assert served.api.log is not None
    audit = served.api.log
    await asyncio.gather(*(audit.append(AuditRecord(
        event=AuditEvent.COMMAND_DISPATCHED, principal="planner", role="USER",
        action_type="move", params={"linear_x": 0.1, "pad": "p" * 8000}, outcome="executed"))
        for _ in range(1000)))  # an 8 MB page: more than the socket buffers hold
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # the page cannot fit
    sock.setblocking(False)
    await asyncio.get_running_loop().sock_connect(sock, (served.host, served.port))
    reader, writer = await asyncio.open_connection(sock=sock)
    try:
        root = f"Authorization: Bearer {TOKENS['root']}".encode()
        writer.write(b"GET /api/audit?since=0 HTTP/1.1\r\nHost: x\r\n" + root + b"\r\n\r\n")
        started = await asyncio.wait_for(reader.readexactly(12), HANG_S)
        assert started == b"HTTP/1.1 200", started
    finally:
        _reset(writer)
    deadlines = served.api.app[DEADLINES] if served.api.app is not None else None
    assert deadlines is not None
    await eventually(lambda: not deadlines.watched, timeout=HANG_S,
                     what="the server noticing the reset")
    await _still_serving(served)
    _assert_quiet(log)


@pytest.mark.logs_traceback  # (a fault injected on purpose)
async def test_a_connection_error_of_the_bridge_itself_is_still_an_error(
        api: Api, log: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    """Only a client that went away is quiet: a ConnectionError with the client still there
    (here from the governor, as a failing outbound call would raise) is a fault: 503, logged."""
    def refused(principal: Any) -> None:
        raise ConnectionRefusedError("the bridge's own connection")

    monkeypatch.setattr(api.gov, "heartbeat", refused)
    status, body = await api.call("POST", "/api/heartbeat", "planner")
    assert (status, body["reason"]) == (503, "internal_error"), body
    assert any(r.levelno == logging.ERROR and r.exc_info for r in log.records)


# -- header bytes that are not UTF-8 (aiohttp keeps them as surrogate escapes) -----------------


def _post(target: bytes, body: bytes, *fields: bytes) -> bytes:
    return (b"POST " + target + b" HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            + b"".join(f + b"\r\n" for f in fields)
            + b"Content-Length: %d\r\nConnection: close\r\n\r\n" % len(body) + body)


async def test_a_token_that_is_not_utf8_is_a_401(served: Served,
                                                 log: pytest.LogCaptureFixture) -> None:
    """On 9523eb7: 503 internal_error, an ERROR with a traceback (the digest's encode)."""
    token = b"\xff\xfe" + TOKENS["viewer"].encode()
    status, headers, body = await _exchange(
        served, _post(b"/api/command", b'{"action": "estop"}', b"Authorization: Bearer " + token))
    assert (status, _json(headers, body)["error_code"]) == (401, "UNAUTHENTICATED"), body
    assert not served.api.gov.latch.latched
    _assert_quiet(log)


async def test_an_mcp_estop_with_a_model_header_that_is_not_utf8_latches(
        served: Served, log: pytest.LogCaptureFixture) -> None:
    """On 9523eb7 the tool failed (INTERNAL_ERROR, a traceback): the model's surrogate escape
    could not be encoded into the command. A name that is not text is no name: stops are
    exempt from naming one."""
    fields = (f"Authorization: Bearer {TOKENS['viewer']}".encode(),
              b"Accept: application/json, text/event-stream",
              b"MCP-Protocol-Version: 2025-06-18", b"RCAN-AI-Model: planner-\xff")
    init = json.dumps({"jsonrpc": "2.0", "id": 1, "method": "initialize", "params": {
        "protocolVersion": "2025-06-18", "capabilities": {},
        "clientInfo": {"name": "agent", "version": "1"}}}).encode()
    status, headers, body = await _exchange(served, _post(b"/mcp", init, *fields))
    assert status == 200, body
    session = b"Mcp-Session-Id: " + headers["mcp-session-id"].encode()
    await _exchange(served, _post(b"/mcp", json.dumps(
        {"jsonrpc": "2.0", "method": "notifications/initialized"}).encode(), *fields, session))
    call = json.dumps({"jsonrpc": "2.0", "id": 2, "method": "tools/call", "params": {
        "name": "estop", "arguments": {"reason": "person"}}}).encode()
    status, headers, body = await _exchange(served, _post(b"/mcp", call, *fields, session))
    assert status == 200, body
    result = _json(headers, body)["result"]
    assert not result["isError"] and result["structuredContent"]["outcome"] == "executed", result
    assert served.api.gov.latch.latched
    _assert_quiet(log)
