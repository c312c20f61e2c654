"""Red team 8: `rcan-rtps mcp` (stdio) against the API, with an e-stop its SDK would not run
as written. `/mcp` runs each of these as the e-stop (tests/api/test_mcp_stop_intake.py,
tests/api/test_redteam8.py); the stdio door handed every line to the SDK as it came."""

from __future__ import annotations

import asyncio
import json
import os
import sys
from pathlib import Path

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


@pytest.mark.xfail(strict=True, reason=(
    "the stdio door hands each line to the SDK as written: a repeated name runs the last "
    "(move), a surrogate or a 5000-digit integer gets no reply at all, ESTOP is "
    "UNKNOWN_TOOL, non-object arguments -32602; nothing stops. /mcp's stop_rescue is not "
    "applied to stdin lines (and would need moving out of rcan_rtps.api, whose import costs "
    "the stdio process ~1 s)"))
@pytest.mark.parametrize("line", list(ESTOPS.values()), ids=list(ESTOPS))
async def test_a_malformed_estop_over_stdio_stops(tmp_path: Path, line: bytes) -> None:
    await _estop_over_stdio(tmp_path, line)


async def test_a_plain_estop_over_stdio_stops(tmp_path: Path) -> None:
    """The same rig with a well-formed e-stop: it stops (the xfails are not the rig's)."""
    await _estop_over_stdio(tmp_path, CALL % b'"name": "estop", "arguments": {}')


async def _estop_over_stdio(tmp_path: Path, line: bytes) -> None:
    api = await Api(tmp_path).start()
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "rcan_rtps", "mcp", "--url", str(api.http.make_url("/")),
        "--token-env", "AGENT_TOKEN", "--ai-provider", "acme", "--ai-model", "m1",
        stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        env={**os.environ, "AGENT_TOKEN": TOKENS["planner"]})
    assert proc.stdin is not None and proc.stdout is not None
    try:
        proc.stdin.write(json.dumps(INITIALIZE).encode() + b"\n")
        await asyncio.wait_for(proc.stdout.readline(), REPLY_TIMEOUT)
        proc.stdin.write(b'{"jsonrpc": "2.0", "method": "notifications/initialized"}\n'
                         + line + b"\n")
        reply = await asyncio.wait_for(proc.stdout.readline(), REPLY_TIMEOUT)
        assert json.loads(reply)["id"] == 2, reply
        assert api.gov.latch.latched, reply
        assert [a for a, _ in api.dispatcher.calls] == ["estop"], reply
    finally:
        proc.stdin.close()
        try:
            await asyncio.wait_for(proc.wait(), REPLY_TIMEOUT)
        except asyncio.TimeoutError:
            proc.kill()
            await proc.wait()
        await api.close()

