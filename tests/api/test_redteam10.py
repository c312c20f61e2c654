"""Red team 10: what today's cancel paths (a motion call its MCP client cancels, POST
/api/command/cancel) and the `/mcp` door around them leave in the log and on the robot.

Each test here failed on main (196d064) before its fix; see each test's docstring.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import Any

import aiohttp
import pytest
from waiting import eventually

from rcan_rtps.mcp_server.server import RobotTools
from tests.api.apihelpers import Api
from tests.api.test_mcp_http import MOVE, _endpoint, agent
from tests.api.test_mcp_stop_intake import LEGACY, headers

LEAVES = 16  # clients that leave; each left a traceback with a chance of ~1 in 4


async def _leave(api: Api, yields: int) -> None:
    """One MCP client (2025 protocol) with its event stream (GET) open leaves as the SDK's
    client does: it closes its session (DELETE) and its stream's connection together, the
    close `yields` loop turns after the DELETE went out."""
    sent = await headers(api, "planner", LEGACY)
    async with aiohttp.ClientSession() as client:
        stream = await client.get(api.http.make_url("/mcp"),
                                  headers={**sent, "Accept": "text/event-stream"})
        assert stream.status == 200 and stream.content_type == "text/event-stream"
        closing = asyncio.ensure_future(api.http.delete("/mcp", headers=sent))
        for _ in range(yields):
            await asyncio.sleep(0)
        stream.close()
    (await closing).close()


async def test_clients_that_leave_with_their_event_stream_open_log_no_traceback(
        api: Api, caplog: pytest.LogCaptureFixture) -> None:
    """The end of a client's event stream, written by the server as the session closes,
    raced the client closing that stream's connection: written to a closing transport, it
    raised ClientConnectionResetError, and the SDK logged `Error in standalone SSE response`
    at ERROR with two tracebacks — for a client that merely left (2 of 3 runs of `rcan-rtps
    run --sim` behind the SDK's own client; here 3 of 12 leaves). Now the end of a response
    whose client has gone is dropped, as the client can read nothing more."""
    caplog.set_level(logging.WARNING)
    for yields in range(LEAVES):
        await _leave(api, yields % 8)
    await eventually(lambda: not _sessions(api), what="every session ended")
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]
    assert errors == [], [(r.name, r.getMessage()) for r in errors]


def _sessions(api: Api) -> list[str]:
    """The sessions the endpoint's SDK manager still runs (a stream ends with its own)."""
    return list(_endpoint(api)._server._manager._server_instances)


async def test_a_move_whose_caller_is_cancelled_as_its_client_lists_the_tools_stops(
        api: Api, monkeypatch: pytest.MonkeyPatch) -> None:
    """The SDK's client, its tool list not cached (a session's first call; a 2026-07-28
    client's list past its ttl), takes a call's answer and then lists the tools to check
    it (`ClientSession.validate_tool_result`). A caller cancelled meanwhile never gets the
    answer, and the client's `notifications/cancelled` names the tools/list, not the call:
    the server stops nothing, and the move runs on, held by the server's heartbeats for
    its whole duration. Seen with `rcan-rtps mcp` against `rcan-rtps run --sim`: 1 in 20
    and 1 in 45 motion calls cancelled 1-30 ms after they were sent (the SDK client's cancel
    went to the tools/list). Here the listing is held until the caller is cancelled. Now a
    listing that comes right after a motion call's answer stands for that call: its cancel
    stops the principal's motion."""
    listing, listed = asyncio.Event(), asyncio.Event()
    list_tools = RobotTools.list_tools

    async def held(tools: RobotTools, ctx: Any, params: Any) -> Any:
        if api.gov.streams.active is not None:  # the move's answer is out: its check lists
            listing.set()
            await listed.wait()
        return await list_tools(tools, ctx, params)

    monkeypatch.setattr(RobotTools, "list_tools", held)
    async with agent(api, mode="legacy") as client:
        call = asyncio.ensure_future(client.call_tool("move", MOVE))
        await asyncio.wait_for(listing.wait(), timeout=30)
        call.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await call
        listed.set()
        await eventually(lambda: api.gov.streams.active is None, timeout=5,
                         what="PLANNER's move stopped")
