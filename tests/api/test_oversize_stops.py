"""A stop larger than `max_body_bytes` (a 100 kB `reason` or `reasoning`) stops, on every door,
its size a warning: REST, WebSocket and `/mcp` (both protocols). Before, each refused it 413
unread and nothing stopped (red team 18). Read up to `STOP_ROOM` times the limit; larger is
refused unread, and an oversize body that is no stop is 413 as before."""

from __future__ import annotations

import gzip
import hashlib
import json
import zlib
from typing import Any

import pytest

from rcan_rtps.api._intake import STOP_ROOM
from tests.api.apihelpers import Api, auth, next_frame
from tests.api.test_mcp_stop_intake import (
    LEGACY,
    MODERN,
    call,
    headers,
    no_traceback,
    post,
    stopped,
)

LIMIT = 64 * 1024  # the default max_body_bytes
BIG = "r" * (100 * 1024)


def _oversize(action: str) -> bytes:
    """`action` with 100 kB of reasoning: over the limit, within STOP_ROOM times it."""
    return json.dumps({"action": action, "ai_reasoning": BIG}).encode()


def _said_large(warnings: list[str]) -> None:
    assert any(f"over the {LIMIT} taken: stopped all the same" in w for w in warnings), warnings


@pytest.mark.parametrize("action", ["stop", "estop"])
async def test_an_oversize_rest_stop_stops(api: Api, action: str,
                                           caplog: pytest.LogCaptureFixture) -> None:
    status, body = await api.command("planner", raw=_oversize(action))
    assert (status, body["outcome"]) == (200, "executed"), body
    _said_large(body["warnings"])
    assert [a for a, _ in api.dispatcher.calls] == [action]
    assert api.entry(body["audit_id"])["warnings"] == body["warnings"]
    no_traceback(caplog)


async def test_an_oversize_rest_move_is_still_413(api: Api) -> None:
    status, body = await api.command("planner", raw=_oversize("move"))
    assert (status, body["error_code"]) == (413, "PAYLOAD_TOO_LARGE"), body
    assert api.dispatcher.calls == []


@pytest.mark.parametrize("action", ["stop", "estop"])
async def test_a_stop_past_the_room_stops_read_through_its_skeleton(
        api: Api, action: str, caplog: pytest.LogCaptureFixture) -> None:
    """Past STOP_ROOM times the limit (here 8 MB of reasoning) a body is read on through its
    skeleton (`_skim`): a stop of any size stops. Before, refused 413 unread."""
    reasoning = "r" * (8 * 1024 * 1024)
    huge = json.dumps({"action": action, "ai_reasoning": reasoning}).encode()
    status, body = await api.command("planner", raw=huge)
    assert (status, body["outcome"]) == (200, "executed"), body
    assert any(f"{len(huge)} bytes, over the {LIMIT} taken (1 of its strings kept only in "
               "part): stopped all the same" in w for w in body["warnings"]), body["warnings"]
    assert [a for a, _ in api.dispatcher.calls] == [action]
    # what it said is kept in part: its first `limit` / 16 bytes
    kept = reasoning[:LIMIT // 16].encode()
    assert api.entry(body["audit_id"])["ai"]["reasoning_sha256"] == \
        hashlib.sha256(kept).hexdigest()
    no_traceback(caplog)


async def test_a_body_past_the_room_by_its_shape_or_no_stop_is_413(api: Api) -> None:
    """Only a stop is taken past the limit, and only a body large by its text (the skeleton
    keeps the shape: a huge array stays huge, and is refused)."""
    move = json.dumps({"action": "move", "ai_reasoning": "r" * (STOP_ROOM * LIMIT)}).encode()
    shaped = json.dumps({"action": "stop", "params": {"x": [0] * (STOP_ROOM * LIMIT)}})
    for raw in (move, shaped.encode()):
        status, body = await api.command("planner", raw=raw)
        assert (status, body["error_code"]) == (413, "PAYLOAD_TOO_LARGE"), body
    assert api.dispatcher.calls == []


async def test_an_oversize_websocket_stop_stops(api: Api) -> None:
    async with api.http.ws_connect("/api/ws", headers=auth("viewer")) as ws:
        await ws.send_bytes(_oversize("estop"))
        frame = await next_frame(ws, "outcome")
        assert (frame["http_status"], frame["body"]["outcome"]) == (200, "executed"), frame
        _said_large(frame["body"]["warnings"])
    assert api.gov.latch.latched


@pytest.mark.parametrize("protocol", [LEGACY, MODERN])
async def test_an_oversize_mcp_estop_stops(api: Api, protocol: str,
                                           caplog: pytest.LogCaptureFixture) -> None:
    arguments = b'"reasoning": "%s"' % BIG.encode()
    status, reply = await post(api, call("estop", arguments, protocol),
                               await headers(api, "viewer", protocol))
    assert status == 200, reply
    data: dict[str, Any] = stopped(reply)
    assert api.gov.latch.latched
    _said_large(data["warnings"])
    # decided once, as it came: not refused first and sent again without its arguments
    assert "COMMAND_REJECTED" not in [e["event"] for e in api.entries]
    no_traceback(caplog)


def _past_room(action: str) -> bytes:
    return json.dumps({"action": action, "ai_reasoning": "r" * (2 * STOP_ROOM * LIMIT)}).encode()


async def _post(api: Api, raw: bytes, coding: str) -> tuple[int, Any]:
    sent = {**auth("planner"), "Content-Type": "application/json", "Content-Encoding": coding}
    async with api.http.post("/api/command", data=raw, headers=sent) as resp:
        return resp.status, await resp.json()


@pytest.mark.parametrize("coding", ["gzip", "deflate"])
async def test_a_compressed_stop_past_the_room_stops(api: Api, coding: str) -> None:
    """Inflated a piece at a time into its skeleton (a gzip bomb of a stop is never held)."""
    raw = _past_room("stop")
    packed = gzip.compress(raw) if coding == "gzip" else zlib.compress(raw)
    assert len(packed) < LIMIT  # small as sent: large only once inflated
    status, body = await _post(api, packed, coding)
    assert (status, body["outcome"]) == (200, "executed"), body
    assert f"{len(raw)} bytes, over the {LIMIT} taken (1 of" in body["warnings"][0], body
    status, body = await _post(api, gzip.compress(_past_room("move")), "gzip")
    assert (status, body["error_code"]) == (413, "PAYLOAD_TOO_LARGE"), body
    assert [a for a, _ in api.dispatcher.calls] == ["stop"]


async def test_a_stop_past_the_room_its_header_misnames_stops(api: Api) -> None:
    status, body = await _post(api, _past_room("stop"), "gzip")
    assert (status, body["outcome"]) == (200, "executed"), body
    assert "$: the body is not gzip data, as its Content-Encoding says: read as sent" in \
        body["warnings"], body["warnings"]
    assert [a for a, _ in api.dispatcher.calls] == ["stop"]


async def test_a_body_past_the_room_with_damaged_compression_is_a_clear_400(api: Api) -> None:
    packed = bytearray(gzip.compress(_past_room("stop")))
    packed[len(packed) // 2] ^= 0xFF  # (deflate blocks of 'r's: a flipped byte breaks one)
    status, body = await _post(api, bytes(packed[:-4]), "gzip")
    assert status == 400 and "compressed data" in json.dumps(body), body
    status, body = await _post(api, _past_room("stop"), "gzip, gzip")
    assert status == 415 and "one Content-Encoding" in json.dumps(body), body


@pytest.mark.parametrize("protocol", [LEGACY, MODERN])
async def test_an_mcp_estop_past_the_room_stops(api: Api, protocol: str,
                                                caplog: pytest.LogCaptureFixture) -> None:
    arguments = b'"reasoning": "%s"' % (b"r" * (2 * STOP_ROOM * LIMIT))
    status, reply = await post(api, call("estop", arguments, protocol),
                               await headers(api, "viewer", protocol))
    assert status == 200, reply
    data: dict[str, Any] = stopped(reply)
    assert api.gov.latch.latched
    assert any("kept only in part): stopped all the same" in w for w in data["warnings"]), data
    assert "COMMAND_REJECTED" not in [e["event"] for e in api.entries]
    no_traceback(caplog)
