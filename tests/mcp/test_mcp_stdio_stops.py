"""Red team 8: `rcan-rtps mcp` (stdio) against the API, with an e-stop its SDK would not run
as written. `/mcp` runs each of these as the e-stop (tests/api/test_mcp_stop_intake.py,
tests/api/test_redteam8.py); the stdio door handed every line to the SDK as it came (a
repeated name ran the move, a surrogate or a 5000-digit integer got no reply, ESTOP was
UNKNOWN_TOOL, non-object arguments -32602) until it screened each line (`stdio_door`)."""

from __future__ import annotations

import asyncio
import json
import os
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import pytest

from tests.api.apihelpers import TOKENS, Api

INITIALIZE = {"jsonrpc": "2.0", "id": 1, "method": "initialize", "params": {
    "protocolVersion": "2025-06-18", "capabilities": {},
    "clientInfo": {"name": "stdio-stop-test", "version": "1"}}}
CALL = b'{"jsonrpc": "2.0", "id": 2, "method": "tools/call", "params": {%s}}'
ESTOPS = {
    "a repeated name": CALL % b'"name": "estop", "name": "move", "arguments": '
                              b'{"linear_x": 0.2, "duration_s": 2, "confidence": 0.9}',
    "an unpaired surrogate": CALL % b'"name": "estop", "arguments": {"reason": "\\ud800 x"}',
    "an integer of 5000 digits": CALL % (b'"name": "estop", "arguments": {"reason": "x", '
                                         b'"n": ' + b"9" * 5000 + b"}"),
    "spelt ESTOP": CALL % b'"name": "ESTOP", "arguments": {}',
    "arguments not an object": CALL % b'"name": "estop", "arguments": "junk"',
}
REPLY_TIMEOUT = 30.0  # s; against a hang only (a refused line gets no reply at all)


@pytest.mark.parametrize("line", list(ESTOPS.values()), ids=list(ESTOPS))
async def test_a_malformed_estop_over_stdio_stops(tmp_path: Path, line: bytes) -> None:
    await _estop_over_stdio(tmp_path, line)


async def test_a_plain_estop_over_stdio_stops(tmp_path: Path) -> None:
    """The same rig with a well-formed e-stop: it stops (the xfails are not the rig's)."""
    await _estop_over_stdio(tmp_path, CALL % b'"name": "estop", "arguments": {}')


async def test_a_stop_read_from_a_repeated_name_says_so(tmp_path: Path) -> None:
    """The door's warnings come back in the stop's tool result."""
    reply = await _estop_over_stdio(tmp_path, ESTOPS["a repeated name"])
    warnings = reply["result"]["structuredContent"]["warnings"]
    assert any("duplicate key 'name'" in w for w in warnings), warnings


@pytest.mark.parametrize("line", list(ESTOPS.values()), ids=list(ESTOPS))
async def test_the_doors_warnings_are_in_the_bridges_audit_entry(tmp_path: Path,
                                                                 line: bytes) -> None:
    """As at /mcp: what the door found wrong is in the stop's audit entry, and the tool
    result's warnings are the entry's (the door's marked as the client's)."""
    async with _stdio(tmp_path) as (api, proc):
        await _send(proc, line)
        data = (await _reply(proc))["result"]["structuredContent"]
        entry = api.entry(data["audit_id"])
    assert entry["event"] == "ESTOP" and entry["principal"] == "planner", entry
    assert entry.get("warnings") == data["warnings"], (entry, data)
    assert any(w.startswith("client: $") for w in entry["warnings"]), entry


async def test_a_notified_and_a_batched_stops_warnings_are_audited(tmp_path: Path) -> None:
    async with _stdio(tmp_path) as (api, proc):
        await _send(proc, b'{"jsonrpc": "2.0", "method": "tools/call", '
                          b'"params": {"name": "estop", "arguments": {}}}',
                    b'[' + CALL % b'"name": "stop", "arguments": {}' + b']')
        await _reply(proc)
        stops = [e for e in api.entries if e["event"] in ("ESTOP", "COMMAND_DISPATCHED")
                 and e.get("action_type") in ("estop", "stop")]
    assert [s.get("warnings") for s in stops] == [
        ["client: $: a notification (no id): run, and not answered"],
        ["client: $: a JSON-RPC batch: only its stops were run"]], stops


async def test_an_estop_sent_as_a_notification_stops_unanswered(tmp_path: Path) -> None:
    """No id: JSON-RPC answers nothing, but the stop is run (the SDK took it as an unknown
    notification and ignored it); the next request's reply is the next line out."""
    async with _stdio(tmp_path) as (api, proc):
        await _send(proc, b'{"jsonrpc": "2.0", "method": "tools/call", '
                          b'"params": {"name": "estop", "arguments": {}}}',
                    b'{"jsonrpc": "2.0", "id": 3, "method": "ping"}')
        reply = await _reply(proc)
        assert reply["id"] == 3, reply
        assert api.gov.latch.latched
        assert [a for a, _ in api.dispatcher.calls] == ["estop"]


async def test_a_batch_with_an_estop_stops_and_refuses_the_rest(tmp_path: Path) -> None:
    async with _stdio(tmp_path) as (api, proc):
        await _send(proc, b'[' + CALL % b'"name": "estop", "arguments": {}' + b', '
                          b'{"jsonrpc": "2.0", "id": 4, "method": "tools/list"}]')
        replies = [await _reply(proc), await _reply(proc)]
        assert [r["id"] for r in replies] == [2, 4], replies
        assert "result" in replies[0] and replies[1]["error"]["code"] == -32600, replies
        assert api.gov.latch.latched
        assert [a for a, _ in api.dispatcher.calls] == ["estop"]


async def _estop_over_stdio(tmp_path: Path, line: bytes) -> dict[str, Any]:
    async with _stdio(tmp_path) as (api, proc):
        await _send(proc, line)
        reply = await _reply(proc)
        assert reply["id"] == 2, reply
        assert api.gov.latch.latched, reply
        assert [a for a, _ in api.dispatcher.calls] == ["estop"], reply
        return reply


async def _send(proc: asyncio.subprocess.Process, *lines: bytes) -> None:
    assert proc.stdin is not None
    proc.stdin.write(b"".join(line + b"\n" for line in lines))
    await proc.stdin.drain()


async def _reply(proc: asyncio.subprocess.Process) -> Any:
    assert proc.stdout is not None
    line = await asyncio.wait_for(proc.stdout.readline(), REPLY_TIMEOUT)
    return json.loads(line)


@asynccontextmanager
async def _stdio(tmp_path: Path) -> AsyncIterator[tuple[Api, asyncio.subprocess.Process]]:
    """An API and `rcan-rtps mcp` against it, initialized."""
    api = await Api(tmp_path).start()
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "rcan_rtps", "mcp", "--url", str(api.http.make_url("/")),
        "--token-env", "AGENT_TOKEN", "--ai-provider", "acme", "--ai-model", "m1",
        stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        env={**os.environ, "AGENT_TOKEN": TOKENS["planner"]})
    assert proc.stdin is not None
    try:
        await _send(proc, json.dumps(INITIALIZE).encode())
        await _reply(proc)
        await _send(proc, b'{"jsonrpc": "2.0", "method": "notifications/initialized"}')
        yield api, proc
    finally:
        proc.stdin.close()
        try:
            await asyncio.wait_for(proc.wait(), REPLY_TIMEOUT)
        except asyncio.TimeoutError:
            proc.kill()
            await proc.wait()
        await api.close()


async def test_an_estop_too_large_for_the_bridge_still_stops(tmp_path: Path) -> None:
    """Red team 18: an e-stop whose arguments made the request larger than the bridge takes
    was refused PAYLOAD_TOO_LARGE and the robot was not stopped. A body large by its text
    (300 kB of `reasoning`) the bridge now reads through its skeleton and stops; one large
    by its shape (its reasoning a list of 300 000 numbers) it still refuses, and the server
    sends the stop again without its arguments, and says so."""
    text = b'"name": "estop", "arguments": {"reasoning": "' + b"x" * 300_000 + b'"}'
    reply = await _estop_over_stdio(tmp_path, CALL % text)
    warnings = reply["result"]["structuredContent"]["warnings"]
    assert any("kept only in part): stopped all the same" in w for w in warnings), warnings
    shape = b'"name": "estop", "arguments": {"reasoning": [' + b"0," * 300_000 + b'0]}'
    reply = await _estop_over_stdio(tmp_path, CALL % shape)
    warnings = reply["result"]["structuredContent"]["warnings"]
    assert any("larger than the bridge takes" in w for w in warnings), warnings
