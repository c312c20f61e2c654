"""A stop larger than the bridge's `max_body_bytes` (100 kB of `reasoning`), called through the
official MCP SDK's client over every MCP transport the bridge serves: the bridge's `/mcp`
(streamable HTTP, the 2026-07-28 protocol and the 2025 handshake with a session) and
`rcan-rtps mcp` (stdio, both protocols) against a bridge. It stops, its size a warning that
comes back to the client, decided once (one audit entry: not refused and sent again). Past
`STOP_ROOM` times the limit the bridge reads it through its skeleton (`api._skim`) and it
stops all the same; only one large by its shape (its reasoning a list of a quarter of a
million numbers) it refuses: at `/mcp` the SDK's client gets a clear error (no hang, nothing
moved); `rcan-rtps mcp` sends the stop again without its arguments (red team 18), which
stops. tests/api/test_oversize_stops.py has the same at every door
with raw bodies."""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from mcp import Client, StdioServerParameters
from mcp.client.stdio import stdio_client
from mcp.shared.exceptions import MCPError
from mcp_types import CallToolResult
from mcp_types.jsonrpc import INVALID_REQUEST

from rcan_rtps.api._intake import STOP_ROOM
from rcan_rtps.mcp_server.stop_tool import TOO_LARGE_STOP
from tests.api.apihelpers import TOKENS, Api
from tests.api.test_mcp_http import CLIENT, agent

LIMIT = 64 * 1024  # the harness's max_body_bytes (the default)
BIG = "r" * (100 * 1024)  # over the limit, well within STOP_ROOM times it
PAST_ROOM = "r" * (STOP_ROOM * LIMIT)  # the call's body is past what the bridge holds whole
SHAPED = [0] * (STOP_ROOM * LIMIT)  # so is its skeleton: large by its shape
SAID_LARGE = f"over the {LIMIT} taken: stopped all the same"
SAID_CUT = "(1 of its strings kept only in part): stopped all the same"
MODES = pytest.mark.parametrize("mode", ["auto", "legacy"])  # 2026-07-28; 2025 (a session)
# A GUEST may e-stop, not halt: each stop by a principal that may send it.
STOPS = pytest.mark.parametrize(("tool", "who"), [("estop", "viewer"), ("stop", "planner")])
EVENTS = {"estop": "ESTOP", "stop": "COMMAND_DISPATCHED"}


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[Api]:
    harness = await Api(tmp_path).start()
    yield harness
    await harness.close()


@pytest.fixture
def log(caplog: pytest.LogCaptureFixture) -> pytest.LogCaptureFixture:
    caplog.set_level(logging.DEBUG)
    return caplog


def data(done: CallToolResult) -> dict[str, Any]:
    assert not done.is_error, done
    assert done.structured_content is not None, done
    return dict(done.structured_content)


def decided(api: Api) -> list[dict[str, Any]]:
    """The audit entries of decided commands (a 413 is a COMMAND_REJECTED one)."""
    return [e for e in api.entries
            if e["event"] in ("ESTOP", "COMMAND_DISPATCHED", "COMMAND_REJECTED")]


def stopped_once(api: Api, tool: str, who: str, done: dict[str, Any],
                 said: str = SAID_LARGE) -> dict[str, Any]:
    """The robot stopped (latched, for an e-stop) by `who`'s one decision, whose warnings,
    the size's among them (`said`), came back to the client: its entry."""
    assert done["outcome"] == "executed", done
    warnings = done.get("warnings", [])
    # Said once, and only as the size: before, /mcp also handed the stop to the SDK (sure to
    # refuse it 413, a second warning) and measured the command it made again (a third).
    assert [w for w in warnings if "bytes, over the" in w or "HTTP 413" in w] == [
        w for w in warnings if said in w] and len([w for w in warnings if said in w]) == 1, done
    assert [a for a, _ in api.dispatcher.calls] == [tool]
    assert api.gov.latch.latched == (tool == "estop")
    [entry] = decided(api)  # decided once, as it came: no COMMAND_REJECTED then a resend
    assert (entry["event"], entry["principal"], entry["audit_id"]) == (
        EVENTS[tool], who, done["audit_id"]), entry
    assert entry["warnings"] == done["warnings"], entry
    # (100 kB of reasoning is also over the 8192 an `ai_reasoning` may be: the agent's fields
    # are dropped from the entry, a warning too — a stop stops whatever is wrong with it)
    return entry


def no_traceback(log: pytest.LogCaptureFixture) -> None:
    assert not [r for r in log.records if r.exc_info], [r.getMessage() for r in log.records]


# -- the bridge's /mcp (streamable HTTP) -------------------------------------------------------

@MODES
async def test_an_estop_past_the_room_by_its_shape_over_mcp_http_is_a_clear_error(
        api: Api, log: pytest.LogCaptureFixture, mode: str) -> None:
    """The body is refused (413, audited): the SDK's client raises at once (no hang)
    an error that says so and that nothing stopped — a JSON-RPC error. Before, the 413's body
    was the bridge's own error, which the SDK's client shows as "Server returned an error
    response". The same client's bare e-stop then latches."""
    async with agent(api, "viewer", mode=mode) as client:
        with pytest.raises(MCPError) as refused:
            await client.call_tool("estop", {"reasoning": SHAPED})
        assert not api.gov.latch.latched and api.dispatcher.calls == []
        error = refused.value
        assert error.code == INVALID_REQUEST, error
        assert error.message.startswith("PAYLOAD_TOO_LARGE: the request is over what the "
                                        f"bridge takes ({LIMIT} bytes"), error.message
        assert "nothing was done (no stop either)" in error.message, error.message
        done = data(await client.call_tool("estop", {}))
    assert done["outcome"] == "executed", done
    assert [a for a, _ in api.dispatcher.calls] == ["estop"] and api.gov.latch.latched
    rejected, latched = decided(api)
    assert (rejected["event"], rejected["deny_reason"]) == (
        "COMMAND_REJECTED", "PAYLOAD_TOO_LARGE"), rejected
    assert error.data["audit_id"] == rejected["audit_id"], error.data
    assert error.data["error_code"] == "PAYLOAD_TOO_LARGE", error.data
    assert latched["audit_id"] == done["audit_id"]
    no_traceback(log)


@MODES
async def test_an_oversize_move_over_mcp_http_is_the_same_clear_error(
        api: Api, mode: str) -> None:
    """Over the limit and no stop: refused as before (413), with the same error."""
    async with agent(api, "planner", mode=mode) as client:
        with pytest.raises(MCPError) as refused:
            await client.call_tool("move", {"linear_x": 0.1, "duration_s": 1.0,
                                            "confidence": 0.9, "reasoning": BIG})
    assert refused.value.message.startswith("PAYLOAD_TOO_LARGE: "), refused.value
    assert refused.value.data["error_code"] == "PAYLOAD_TOO_LARGE", refused.value
    assert api.dispatcher.calls == []


# -- `rcan-rtps mcp` (stdio) against the bridge ------------------------------------------------

@contextlib.asynccontextmanager
async def stdio_agent(tmp_path: Path, who: str, mode: str
                      ) -> AsyncIterator[tuple[Api, Client]]:
    """An API, and the SDK's client of `rcan-rtps mcp` serving `who`'s token against it."""
    api = await Api(tmp_path).start()
    server = StdioServerParameters(
        command=sys.executable,
        args=["-m", "rcan_rtps", "mcp", "--url", str(api.http.make_url("/")),
              "--token-env", "AGENT_TOKEN", "--ai-provider", "acme", "--ai-model", "m1"],
        env={"AGENT_TOKEN": TOKENS[who], "PYTHONPATH": os.environ.get("PYTHONPATH", "")})
    try:
        with (tmp_path / "mcp.err").open("a") as errlog:
            async with Client(stdio_client(server, errlog=errlog), client_info=CLIENT,
                              mode=mode) as client:
                yield api, client
    finally:
        await api.close()
    no_server_traceback(tmp_path)


def no_server_traceback(tmp_path: Path) -> None:
    said = (tmp_path / "mcp.err").read_text()
    assert "Traceback" not in said, said


@contextlib.asynccontextmanager
async def http_agent(tmp_path: Path, who: str, mode: str
                     ) -> AsyncIterator[tuple[Api, Client]]:
    """An API, and the SDK's client of its `/mcp` as `who`."""
    api = await Api(tmp_path).start()
    try:
        async with agent(api, who, mode=mode) as client:
            yield api, client
    finally:
        await api.close()


# Each MCP transport a stop may come by: the bridge's /mcp, `rcan-rtps mcp` against the bridge.
AGENTS = pytest.mark.parametrize("open_agent", [http_agent, stdio_agent],
                                 ids=["mcp_http", "stdio"])


@AGENTS
@MODES
@STOPS
async def test_an_oversize_stop_stops(tmp_path: Path, log: pytest.LogCaptureFixture,
                                      open_agent: Any, mode: str, tool: str, who: str) -> None:
    async with open_agent(tmp_path, who, mode) as (api, client):
        done = data(await client.call_tool(tool, {"reason": "person", "reasoning": BIG}))
        assert (await client.list_tools()).tools  # the session goes on
        stopped_once(api, tool, who, done)
        assert api.dispatcher.calls[0][1] == {"reason": "person"}
    no_traceback(log)


@AGENTS
@MODES
async def test_an_estop_past_the_room_stops(tmp_path: Path, log: pytest.LogCaptureFixture,
                                            open_agent: Any, mode: str) -> None:
    """Read through its skeleton: it latches once, its reasoning kept in part, and the
    client is told. Before, refused 413 unread."""
    async with open_agent(tmp_path, "viewer", mode) as (api, client):
        done = data(await client.call_tool("estop", {"reason": "person",
                                                     "reasoning": PAST_ROOM}))
        stopped_once(api, "estop", "viewer", done, SAID_CUT)
        assert api.dispatcher.calls == [("estop", {"reason": "person"})]
        assert [e["event"] for e in api.entries if e["event"] != "SESSION_OPENED"] == ["ESTOP"]
    no_traceback(log)


@MODES
async def test_an_estop_past_the_room_by_its_shape_over_stdio_is_sent_again_bare(
        tmp_path: Path, log: pytest.LogCaptureFixture, mode: str) -> None:
    """Red team 18: refused 413 (audited), `rcan-rtps mcp` sends the e-stop again without its
    arguments, which latches; the client is told so."""
    async with stdio_agent(tmp_path, "viewer", mode) as (api, client):
        done = data(await client.call_tool("estop", {"reason": "person",
                                                     "reasoning": SHAPED}))
        assert done["outcome"] == "executed", done
        assert TOO_LARGE_STOP in done["warnings"], done
        assert api.gov.latch.latched
        assert api.dispatcher.calls == [("estop", {})]
        refused, latched = decided(api)
        assert (refused["event"], refused["deny_reason"]) == (
            "COMMAND_REJECTED", "PAYLOAD_TOO_LARGE"), refused
        assert (latched["event"], latched["audit_id"]) == ("ESTOP", done["audit_id"]), latched
        assert "reasoning_sha256" not in latched.get("ai", {}), latched
    no_traceback(log)
