"""`rcan-rtps mcp` (stdio) against the API, its MCP client cancelling a call (the SDK's client
sends `notifications/cancelled` when the task awaiting a call is cancelled).

Before, the server cancelled the tool's handler, which cut off its request to the bridge: a
motion command the bridge had was decided anyway and its motion ran until its principal's
session lapsed (never, on the harness's manual clock); a stop cut off before the bridge had
it never stopped. Now a command's request is carried through, and a motion command's cancel
is told to the bridge (POST /api/command/cancel): the principal's motion on its way never
starts, what runs stops — its own alone. The same at the bridge's `/mcp`:
tests/api/test_mcp_http.py."""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from mcp import Client, StdioServerParameters
from mcp.client.stdio import stdio_client
from waiting import eventually

from rcan_rtps.governance import Principal
from tests.api.apihelpers import TOKENS, ZERO, Api, own_stops
from tests.api.test_mcp_http import ARM, MOVE, NAVIGATE, cancelled, failed, withdrawals
from tests.mcp.test_mcp_stdio_stops import _reply, _send, _stdio

CALL = (b'{"jsonrpc": "2.0", "id": %d, "method": "tools/call", '
        b'"params": {"name": "%s", "arguments": {}}}')
CANCEL = b'{"jsonrpc": "2.0", "method": "notifications/cancelled", "params": {"requestId": %d}}'


@contextlib.asynccontextmanager
async def agent(tmp_path: Path) -> AsyncIterator[tuple[Api, Client]]:
    """An API, and the SDK's client of `rcan-rtps mcp` serving PLANNER's token against it."""
    api = await Api(tmp_path).start()
    server = StdioServerParameters(
        command=sys.executable,
        args=["-m", "rcan_rtps", "mcp", "--url", str(api.http.make_url("/")),
              "--token-env", "AGENT_TOKEN", "--ai-provider", "acme", "--ai-model", "m1"],
        env={"AGENT_TOKEN": TOKENS["planner"], "PYTHONPATH": os.environ.get("PYTHONPATH", "")})
    try:
        with (tmp_path / "mcp.err").open("a") as errlog:
            async with Client(stdio_client(server, errlog=errlog)) as client:
                yield api, client
    finally:
        await api.close()


@pytest.mark.parametrize("others", ["alone", "ops_drives"])
@pytest.mark.parametrize(("tool", "args"), [("move", MOVE), ("navigate", NAVIGATE)])
async def test_a_motion_call_cancelled_while_it_waits_never_starts(
        tmp_path: Path, tool: str, args: dict[str, Any], others: str) -> None:
    """The call's command waits for the robot when its client cancels the call: refused
    `stopped`, nothing of it reaches the robot; OPS's stream, when OPS drives, goes on."""
    async with agent(tmp_path) as (api, client):
        if others == "ops_drives":
            status, body = await api.command("ops", {"action": "move",
                                                     "params": {"linear_x": 0.3}})
            assert (status, body["outcome"]) == (200, "executed"), body
        release = api.dispatcher.hold_ready = asyncio.Event()
        call = asyncio.ensure_future(client.call_tool(tool, args))
        await asyncio.wait_for(api.dispatcher.ready_entered.wait(), timeout=60)
        samples = len(api.dispatcher.samples)
        await cancelled(call)
        [stop] = await eventually(lambda: own_stops(api.entries), what="the cancel's own stop")
        release.set()
        [refused] = await eventually(lambda: failed(api, tool), what="its refusal")
        assert refused["deny_reason"] == "COMMAND_REJECTED:stopped", refused
        assert stop["principal"] == "planner" and stop["applied"]["cancelled_by_client"]
        assert stop["applied"]["on_its_way"] is True, stop
        if others == "alone":
            assert api.dispatcher.calls == [] and api.gov.streams.active is None
            return
        active = api.gov.streams.active
        assert active is not None and (active.owner, active.target.linear_x) == ("ops", 0.3)
        assert ZERO not in api.dispatcher.samples[samples:]
        assert [a for a, _ in api.dispatcher.calls] == ["move"]  # OPS's, and no halt


async def test_a_move_cancelled_after_it_started_is_zeroed(tmp_path: Path) -> None:
    """The move runs, its answer not yet sent, when its client cancels the call: its stream
    ends with zero at once (not at its session's timeout), audited as its client's cancel."""
    async with agent(tmp_path) as (api, client):
        release, decided = api.hold_decisions(lambda c: c.spec.motion, decided=True)
        call = asyncio.ensure_future(client.call_tool("move", MOVE))
        await asyncio.wait_for(decided.wait(), timeout=60)
        active = api.gov.streams.active
        assert active is not None and active.owner == "planner"
        await cancelled(call)
        [stop] = await eventually(lambda: own_stops(api.entries), what="the cancel's own stop")
        release.set()
        assert api.gov.streams.active is None and api.dispatcher.samples[-1] == ZERO
        assert stop["applied"]["stream_ended"] == active.message_id, stop
        [ended] = [e for e in api.entries if e["event"] == "STREAM_ENDED"]
        assert ended["params"]["reason"] == "cancelled", ended
        assert [a for a, _ in api.dispatcher.calls] == ["move"]  # no stop of the robot


async def test_a_move_the_bridge_takes_after_the_cancel_is_stopped(tmp_path: Path) -> None:
    """The cancel reaches the governor before the move's command does (the bridge is still
    taking that request: two connections, either may be read first): nothing of PLANNER's is
    on its way yet, and the move then starts. The server, which waits for the move's answer
    once its call is cancelled, stops it when that answer says it executed."""
    async with agent(tmp_path) as (api, client):
        release = await cancel_read_first(api, client, "move", MOVE)
        assert own_stops(api.entries) == []
        release.set()
        [stop] = await eventually(lambda: own_stops(api.entries), what="the move's stop")
        moved = [e for e in api.entries if e["event"] == "COMMAND_DISPATCHED"]
        assert stop["applied"]["stream_ended"] == moved[0]["message_id"], (stop, moved)
        assert api.gov.streams.active is None and api.dispatcher.samples[-1] == ZERO


async def test_an_arm_joint_held_after_the_cancel_is_withdrawn(tmp_path: Path) -> None:
    """The cancel reaches the governor before the arm_joint's command does, which is then
    held for an OWNER (`pending_auth`): the server, which waits for the command's answer once
    its call is cancelled, has it withdrawn (HITL_WITHDRAWN by PLANNER), and an approval
    moves nothing. Before, it stayed pending, and the approval moved the arm."""
    async with agent(tmp_path) as (api, client):
        release = await cancel_read_first(api, client, "arm_joint", ARM)
        release.set()
        [withdrawn] = await withdrawals(api)
        assert withdrawn["principal"] == "planner", withdrawn
        assert api.gov.pending() == []
        status, late = await api.call("POST", "/api/hitl/authorize", "ops",
                                      body={"pending_id": withdrawn["pending_id"]})
        assert (status, late["reason"]) == (404, "pending_not_found"), late
        assert api.dispatcher.calls == []


async def test_stops_whose_calls_are_cancelled_still_stop(tmp_path: Path) -> None:
    """An e-stop and 7 stops, each call followed at once by its `notifications/cancelled`
    (in one write: the SDK's client cannot place its cancel as close): each is decided.
    Before, the cancel cut off the server's request to the bridge, mostly before it went
    out: 0 or 1 of 8 were decided in each of 3 runs."""
    count = 8
    async with _stdio(tmp_path) as (api, proc):
        lines = []
        for request_id, tool in enumerate(["estop"] + ["stop"] * (count - 1), start=10):
            lines += [CALL % (request_id, tool.encode()), CANCEL % request_id]
        await _send(proc, *lines, b'{"jsonrpc": "2.0", "id": 3, "method": "ping"}')
        # A cancelled call is not answered, unless it ended before its cancel was read (a
        # busy machine: CI once answered id 15 first); nothing else comes before the ping's.
        while (reply := await _reply(proc))["id"] != 3:
            assert reply["id"] in range(10, 10 + count), reply

        def decided() -> list[dict[str, Any]]:
            found = [e for e in api.entries if e.get("action_type") in ("estop", "stop")]
            return found if len(found) >= count else []

        stops = await eventually(decided, what="every stop's entry")
        assert sorted(e["action_type"] for e in stops) == ["estop"] + ["stop"] * (count - 1)
        assert {e["outcome"] for e in stops} == {"executed"}, stops
        assert api.gov.latch.latched


async def cancel_read_first(api: Api, client: Client, tool: str, args: dict[str, Any]
                            ) -> asyncio.Event:
    """PLANNER's call of `tool`, cancelled while the bridge is still taking its command, and
    the cancel told to the governor first (two connections: either may be read first), when
    nothing of PLANNER's is on its way yet. The event lets the command go on."""
    release, taking = api.hold_decisions(lambda c: c.spec.motion, decided=False)
    told = _cancels_seen(api)
    call = asyncio.ensure_future(client.call_tool(tool, args))
    await asyncio.wait_for(taking.wait(), timeout=60)
    await cancelled(call)
    await asyncio.wait_for(told.wait(), timeout=60)
    return release


def _cancels_seen(api: Api) -> asyncio.Event:
    """Set once the governor has been told of a cancelled command (and has acted on it)."""
    seen = asyncio.Event()
    motion_cancelled = api.gov.motion_cancelled

    def told(principal: Principal) -> Any:
        cancelled = motion_cancelled(principal)
        seen.set()
        return cancelled

    api.gov.motion_cancelled = told  # type: ignore[method-assign]
    return seen

