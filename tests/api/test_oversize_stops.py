"""A stop larger than `max_body_bytes` (a 100 kB `reason` or `reasoning`) stops, on every door,
its size a warning: REST, WebSocket and `/mcp` (both protocols). Before, each refused it 413
unread and nothing stopped (red team 18). Read up to `STOP_ROOM` times the limit; larger is
refused unread, and an oversize body that is no stop is 413 as before."""

from __future__ import annotations

import json
from typing import Any

import pytest

from rcan_rtps.api._intake import STOP_ROOM
from tests.api.apihelpers import Api, auth
from tests.api.test_mcp_stop_intake import (
    LEGACY,
    MODERN,
    call,
    headers,
    no_traceback,
    post,
    stopped,
)
from tests.api.test_ws import _frame

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


async def test_an_oversize_rest_move_is_still_413_and_a_stop_past_the_room_too(
        api: Api) -> None:
    status, body = await api.command("planner", raw=_oversize("move"))
    assert (status, body["error_code"]) == (413, "PAYLOAD_TOO_LARGE"), body
    huge = json.dumps({"action": "stop", "ai_reasoning": "r" * (STOP_ROOM * LIMIT)}).encode()
    status, body = await api.command("viewer", raw=huge)
    assert (status, body["error_code"]) == (413, "PAYLOAD_TOO_LARGE"), body
    assert api.dispatcher.calls == []


async def test_an_oversize_websocket_stop_stops(api: Api) -> None:
    async with api.http.ws_connect("/api/ws", headers=auth("viewer")) as ws:
        await ws.send_bytes(_oversize("estop"))
        frame = await _frame(ws, "outcome")
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
