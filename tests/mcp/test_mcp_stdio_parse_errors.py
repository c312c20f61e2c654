"""`rcan-rtps mcp` (stdio) given a line it cannot read: JSON-RPC 2.0's error reply (-32700
for what is not JSON, -32600 for JSON that is no JSON-RPC message), and the next line served.
The SDK's stdio transport passed over such a line without a word: the client waited for a
reply that never came."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from tests.mcp.test_mcp_stdio_stops import CALL, _reply, _send, _stdio

PING = b'{"jsonrpc": "2.0", "id": 3, "method": "ping"}'
NOT_JSON = {
    "text": b"this is not json",
    "cut short": b'{"jsonrpc": "2.0", "id": 5, "method": "ping"',
    "not UTF-8": b"\xff\xfe{",
}
NOT_A_MESSAGE = {  # the id the error answers
    "an object of no message": (b'{"foo": 1}', None),
    "a number": (b"42", None),
    "a request without its method": (b'{"jsonrpc": "2.0", "id": 9}', 9),
}


def _error(reply: dict[str, Any], code: int, request_id: int | None) -> None:
    assert reply["jsonrpc"] == "2.0" and reply["id"] == request_id, reply
    assert reply["error"]["code"] == code, reply
    assert reply["error"]["message"] == {-32700: "Parse error", -32600: "Invalid Request"}[code]


@pytest.mark.parametrize("line", list(NOT_JSON.values()), ids=list(NOT_JSON))
async def test_a_line_that_is_not_json_is_a_parse_error_and_the_next_is_served(
        tmp_path: Path, line: bytes) -> None:
    async with _stdio(tmp_path) as (_, proc):
        await _send(proc, line, PING)
        _error(await _reply(proc), -32700, None)
        assert await _reply(proc) == {"jsonrpc": "2.0", "id": 3, "result": {}}
    assert proc.stderr is not None
    stderr = (await proc.stderr.read()).decode()
    assert "Traceback" not in stderr and "Error" not in stderr, stderr


@pytest.mark.parametrize(("line", "request_id"), list(NOT_A_MESSAGE.values()),
                         ids=list(NOT_A_MESSAGE))
async def test_json_that_is_no_message_is_an_invalid_request(
        tmp_path: Path, line: bytes, request_id: int | None) -> None:
    async with _stdio(tmp_path) as (_, proc):
        await _send(proc, line, PING)
        _error(await _reply(proc), -32600, request_id)
        assert (await _reply(proc))["id"] == 3


async def test_a_blank_line_is_no_message_and_gets_no_reply(tmp_path: Path) -> None:
    async with _stdio(tmp_path) as (_, proc):
        await _send(proc, b"", b"   ", PING)
        assert (await _reply(proc))["id"] == 3


async def test_an_estop_after_lines_of_garbage_still_stops(tmp_path: Path) -> None:
    async with _stdio(tmp_path) as (api, proc):
        await _send(proc, b"garbage", b"[1, 2", CALL % b'"name": "estop", "arguments": {}')
        replies = [await _reply(proc) for _ in range(3)]
        assert [r["id"] for r in replies] == [None, None, 2], json.dumps(replies)
        assert "result" in replies[2], replies
        assert api.gov.latch.latched
        assert [a for a, _ in api.dispatcher.calls] == ["estop"]
