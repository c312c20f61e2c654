"""A 2026-07-28 MCP client cancels a call by closing its request (no `notifications/cancelled`
on that wire), served by the production `ApiServer` — not aiohttp's test server, which
cancels a handler whose client hung up and so hides what a real bridge does.

aiohttp's real server (`handler_cancellation=False`, its default since 3.7) lets the handler
run on: a motion call its client hung up on was carried out, answered to nobody, and its
motion held by heartbeats for its whole `duration_s`. Now the bridge takes the hang-up of a
motion tool's call for its cancel: the principal's motion on its way never starts, what
of it runs stops (its own alone). A stop whose client hangs up still stops, and other
calls are carried out as before.

The official SDK's client speaks the 2026 revision (`mode=MODERN`): cancelling the task that
awaits a call aborts its POST, which closes the connection."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from mcp import Client
from mcp.client.streamable_http import streamable_http_client
from mcp.shared._httpx_utils import create_mcp_http_client
from waiting import eventually

from rcan_rtps.api import ApiServer
from tests.api.apihelpers import TOKENS, Api, auth, own_stops
from tests.api.test_mcp_http import (
    AGENT,
    CLIENT,
    MOVE,
    NAVIGATE,
    _endpoint,
    answers_held,
    assert_never_started,
    assert_zeroed_by_cancel,
    cancelled,
    failed,
)

MODERN = "2026-07-28"
LOCKS = "motion: {locks: [{name: teleop, priority: 0}]}"  # one a USER may engage


@pytest.fixture
async def served(tmp_path: Path) -> AsyncIterator[tuple[Api, str]]:
    """The API served as `rcan-rtps run` serves it (`ApiServer`), and its URL."""
    api = Api(tmp_path, bridge_extra=LOCKS)
    app = await api.build()
    async with ApiServer(app, host="127.0.0.1", port=0) as server:
        yield api, server.url
    await api.close()


async def rest_command(url: str, who: str, body: dict[str, Any]) -> tuple[int, Any]:
    async with aiohttp.ClientSession() as session, \
            session.post(f"{url}/api/command", json=body, headers=auth(who)) as response:
        return response.status, await response.json()


@contextlib.asynccontextmanager
async def agent(url: str, who: str = "planner") -> AsyncIterator[Client]:
    """The SDK's client, speaking the sessionless 2026-07-28 revision."""
    sent = {"Authorization": f"Bearer {TOKENS[who]}", **AGENT}
    async with create_mcp_http_client(headers=sent) as http, \
            Client(streamable_http_client(f"{url}/mcp", http_client=http), client_info=CLIENT,
                   mode=MODERN) as client:
        yield client


@pytest.mark.parametrize(("tool", "args"), [("move", MOVE), ("navigate", NAVIGATE)])
async def test_a_motion_call_hung_up_on_while_it_waits_never_starts(
        served: tuple[Api, str], tool: str, args: dict[str, Any]) -> None:
    """The call waits for the robot when its client hangs up: refused `stopped`, nothing
    reaches the robot, the principal's own stop says its client cancelled it. Before, it
    started once the robot was ready and its heartbeats held it for its `duration_s`."""
    api, url = served
    release = api.dispatcher.hold_ready = asyncio.Event()
    async with agent(url) as client:
        call = asyncio.ensure_future(client.call_tool(tool, args))
        await asyncio.wait_for(api.dispatcher.ready_entered.wait(), timeout=30)
        await cancelled(call)
        [stop] = await eventually(lambda: own_stops(api.entries), what="the hang-up's stop")
        release.set()
        [refused] = await eventually(lambda: failed(api, tool), what="its refusal")
    assert_never_started(api, stop, refused)


async def test_a_move_hung_up_on_as_its_answer_is_made_is_zeroed(
        served: tuple[Api, str]) -> None:
    """The move runs (decided, its answer not yet made) when its client hangs up: its stream
    ends with zero at once, audited as its client's cancel; nothing else is halted, and no
    heartbeat holds it."""
    api, url = served
    _, held = answers_held(api)  # never released: the hang-up interrupts the handler
    async with agent(url) as client:
        call = asyncio.ensure_future(client.call_tool("move", MOVE))
        await asyncio.wait_for(held.wait(), timeout=30)
        active = api.gov.streams.active
        assert active is not None and active.owner == "planner"
        await cancelled(call)
        [stop] = await eventually(lambda: own_stops(api.entries), what="the hang-up's stop")
    assert_zeroed_by_cancel(api, stop, active)
    assert [a for a, _ in api.dispatcher.calls] == ["move"]  # no stop of the whole robot
    assert not _endpoint(api)._keepalives["planner"].holding


# Guards of the fix above (they pass on main, where nothing is cut off at a hang-up): what
# a hang-up must not cut off.

@pytest.mark.parametrize("tool", ["stop", "estop"])
async def test_a_stop_hung_up_on_still_stops(served: tuple[Api, str], tool: str) -> None:
    """The client hangs up while its stop waits to be decided: it is decided all the same
    and stops — stops always win — and the motion running is stopped."""
    api, url = served
    status, body = await rest_command(url, "ops", {"action": "move",
                                                   "params": {"linear_x": 0.3}})
    assert (status, body["outcome"]) == (200, "executed"), body
    release, entered = api.hold_decisions(lambda c: c.spec.stopping, decided=False)
    async with agent(url) as client:
        call = asyncio.ensure_future(client.call_tool(tool, {"reason": "hung up"}))
        await asyncio.wait_for(entered.wait(), timeout=30)
        await cancelled(call)
        release.set()
        [entry] = await eventually(
            lambda: [e for e in api.entries if e.get("action_type") == tool
                     and e["principal"] == "planner"], what=f"the {tool}'s decision")
    assert entry["outcome"] == "executed", entry
    assert api.gov.streams.active is None
    assert [a for a, _ in api.dispatcher.calls][-1] == tool


async def test_another_command_hung_up_on_is_decided(served: tuple[Api, str]) -> None:
    """Not a motion call (`lock`): the client's hang-up leaves it to be decided, as before,
    and nothing is stopped."""
    api, url = served
    release, entered = api.hold_decisions(lambda c: c.action == "lock", decided=False)
    async with agent(url) as client:
        call = asyncio.ensure_future(client.call_tool("lock", {"name": "teleop",
                                                                "confidence": 0.9}))
        await asyncio.wait_for(entered.wait(), timeout=30)
        await cancelled(call)
        release.set()
        [entry] = await eventually(
            lambda: [e for e in api.entries if e.get("action_type") == "lock"],
            what="the lock's decision")
    assert entry["outcome"] == "executed", entry
    assert api.gov.streams.locks == {"teleop": 0}
    assert own_stops(api.entries) == []
