"""Issue 25: the bridge's own `/mcp` (streamable HTTP, bearer token), driven by the official
MCP SDK's client against the API in process (the real governor and audit log; the robot side
recorded). The tools are the registry's, described with this robot's limits; each call is a
command of the authenticated principal, with the agent's model, client and a thought id in
its audit entry; gated commands wait for an approver; e-stops work for any principal; a
session belongs to the principal that opened it; the agent reads only its own audit entries;
a session closed while its move runs stops it. The wire end to end (`run --sim`) is in
tests/interop/test_mcp_sim.py."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from types import MappingProxyType
from typing import Any

import aiohttp
import pytest
from mcp import Client
from mcp.client.streamable_http import streamable_http_client
from mcp.shared._httpx_utils import create_mcp_http_client
from mcp.shared.exceptions import MCPError
from mcp_types import CallToolResult, Implementation
from waiting import eventually

from rcan_rtps.api import _asgi
from rcan_rtps.rcan.actions import _registry, names
from tests.api.apihelpers import TOKENS, ZERO, Api, own_stops
from tests.api.test_hitl_reviews import review
from tests.mcp.test_mcp_tools import BEEP, READ_TOOLS

AGENT = {"RCAN-AI-Provider": "acme", "RCAN-AI-Model": "planner-7b"}
CLIENT = Implementation(name="test-agent", version="1.2")


@contextlib.asynccontextmanager
async def agent(api: Api, who: str = "planner", headers: dict[str, str] | None = None,
                url_query: str = "", mode: Any = "auto") -> AsyncIterator[Client]:
    """The SDK's client; `mode="legacy"`: the 2025 handshake with a session (what most agent
    clients speak today), else the sessionless 2026-07-28 protocol."""
    url = str(api.http.make_url("/mcp")) + url_query
    sent = {"Authorization": f"Bearer {TOKENS[who]}", **(AGENT if headers is None else headers)}
    async with create_mcp_http_client(headers=sent) as http, \
            Client(streamable_http_client(url, http_client=http), client_info=CLIENT,
                   mode=mode) as c:
        yield c


MODES = pytest.mark.parametrize("mode", ["auto", "legacy"])


def data(done: CallToolResult) -> dict[str, Any]:
    assert done.structured_content is not None, done
    return dict(done.structured_content)


def commands(api: Api, action: str) -> list[dict[str, Any]]:
    return [e for e in api.entries if e.get("action_type") == action
            and e["event"] in ("COMMAND_DISPATCHED", "COMMAND_REJECTED")]


async def test_the_tools_with_this_robots_limits(api: Api) -> None:
    async with agent(api) as client:
        tools = {t.name: t for t in (await client.list_tools()).tools}
    assert set(tools) == set(names()) | READ_TOOLS
    move = tools["move"].description or ""
    # the harness's config: 1.0 m/s, 0.5 rad/s, the default 30 s timed move
    assert "max_linear_vel 1 m/s; max_angular_vel 0.5 rad/s; max_move_duration_s 30 s" in move
    assert "beyond that refused" in move
    navigate = tools["navigate"].description or ""
    assert "workspace polygon (-10, -10) (10, -10) (10, 10) (-10, 10) (frame map, m)" in navigate
    assert "This robot's limits" not in (tools["lock"].description or "")  # none apply


@MODES
async def test_a_move_is_a_command_of_the_principal_with_the_agents_identity(
        api: Api, mode: str) -> None:
    async with agent(api, mode=mode) as client:
        done = await client.call_tool("move", {"linear_x": 0.3, "duration_s": 2.0,
                                               "confidence": 0.9, "reasoning": "to the door"})
        assert not done.is_error, done
        assert (data(done)["outcome"], data(done)["http_status"]) == ("executed", 200)
        over = await client.call_tool("move", {"linear_x": 2.0, "duration_s": 1.0,
                                               "confidence": 0.9})
        assert over.is_error
        assert (data(over)["http_status"], data(over)["reason"]) == (409, "velocity_limit")
        assert over.content[0].text.startswith(  # type: ignore[union-attr]
            "refused: COMMAND_REJECTED: velocity_limit")
    assert api.dispatcher.calls[0][0] == "move"
    assert api.dispatcher.calls[0][1]["linear_x"] == 0.3
    sent = commands(api, "move")
    assert [e["outcome"] for e in sent] == ["executed", "safety_violation"]
    for entry in sent:
        assert entry["principal"] == "planner"
        assert {k: entry["ai"][k] for k in ("provider", "model", "client")} == {
            "provider": "acme", "model": "planner-7b", "client": "test-agent/1.2"}
    assert sent[0]["ai"]["thought_id"] == data(done)["thought_id"]
    assert sent[0]["ai"]["thought_id"] != sent[1]["ai"]["thought_id"]
    assert "reasoning_sha256" in sent[0]["ai"] and "to the door" not in json.dumps(sent[0])


async def test_the_model_from_the_query_when_no_header_is_set(api: Api) -> None:
    async with agent(api, headers={}, url_query="?ai_provider=acme&ai_model=q-1") as client:
        done = await client.call_tool("move", {"linear_x": 0.1, "duration_s": 0.5,
                                               "confidence": 0.9})
        assert data(done)["outcome"] == "executed", done
    assert commands(api, "move")[0]["ai"]["model"] == "q-1"


async def test_no_model_named_refuses_all_but_stops(api: Api) -> None:
    async with agent(api, headers={}) as client:
        refused = await client.call_tool("move", {"linear_x": 0.1, "duration_s": 1.0,
                                                  "confidence": 0.9})
        assert refused.is_error and data(refused)["reason"] == "ai_model_required", refused
        stopped = await client.call_tool("estop", {"reason": "no model, still stops"})
        assert data(stopped)["outcome"] == "executed", stopped
        assert "ai_model_required" in " ".join(data(stopped).get("warnings", []))
    assert api.gov.latch.latched
    assert api.dispatcher.calls == [("estop", {"reason": "no model, still stops"})]


@MODES
async def test_a_gated_command_waits_for_the_owner_over_rest(api: Api, mode: str) -> None:
    async with agent(api, mode=mode) as client:
        held = await client.call_tool("arm_joint", {"joints": ["elbow"], "positions": [0.5],
                                                    "duration_s": 1.0, "confidence": 0.9})
        assert (data(held)["outcome"], data(held)["http_status"]) == ("pending_auth", 202)
        pending_id = data(held)["pending_id"]
        waiting = asyncio.create_task(client.call_tool(
            "wait_for_approval", {"pending_id": pending_id, "timeout_s": 30}))
        await asyncio.sleep(0.3)
        assert not waiting.done()
        status, approved = await review(api, "authorize", "ops", pending_id)
        assert (status, approved["outcome"]) == (200, "executed"), approved
        done = await asyncio.wait_for(waiting, 30)
        assert not done.is_error, done
        assert (data(done)["state"], data(done)["outcome"]) == ("resolved", "executed")
    assert [c[0] for c in api.dispatcher.calls] == ["arm_joint"]


async def test_every_principal_estops_and_only_an_owner_clears(api: Api) -> None:
    async with agent(api, "viewer") as guest:  # a GUEST agent
        done = await guest.call_tool("estop", {"reason": "person"})
        assert data(done)["outcome"] == "executed", done
        moved = await guest.call_tool("move", {"linear_x": 0.1, "duration_s": 1.0,
                                               "confidence": 0.9})
        assert moved.is_error and data(moved)["http_status"] == 403  # a GUEST never moves it
    async with agent(api) as user:
        assert data(await user.call_tool("clear_estop", {}))["http_status"] == 403
        refused = await user.call_tool("move", {"linear_x": 0.1, "duration_s": 1.0,
                                                "confidence": 0.9})
        assert (data(refused)["http_status"], data(refused)["reason"]) == (409, "estop_active")
    assert api.gov.latch.latched
    async with agent(api, "ops") as owner:
        cleared = await owner.call_tool("clear_estop", {"confidence": 0.9})
        assert data(cleared)["outcome"] == "executed", cleared
    assert not api.gov.latch.latched


@pytest.mark.parametrize("authorization", [None, "Bearer not-a-token-0123456789abcdef",
                                           "Basic cGxhbm5lcjp4"])
async def test_a_missing_or_wrong_token_is_refused(api: Api, authorization: str | None
                                                   ) -> None:
    initialize = {"jsonrpc": "2.0", "id": 1, "method": "initialize", "params": {
        "protocolVersion": "2025-06-18", "capabilities": {},
        "clientInfo": {"name": "x", "version": "1"}}}
    headers = {"Accept": "application/json, text/event-stream"}
    if authorization is not None:
        headers["Authorization"] = authorization
    async with api.http.post("/mcp", json=initialize, headers=headers) as resp:
        body = await resp.json()
        assert (resp.status, body["error_code"]) == (401, "UNAUTHENTICATED"), body
        assert resp.headers["WWW-Authenticate"].startswith("Bearer")
    with pytest.raises(Exception):  # the SDK's own client cannot even initialize  # noqa: B017
        async with agent(api, "planner", headers={"Authorization": authorization or ""}):
            pass
    assert not [e for e in api.entries if e.get("ai")]


async def test_a_session_is_its_openers_alone(api: Api) -> None:
    async with agent(api, mode="legacy") as client:
        await client.call_tool("get_status", {})
        listed = {"jsonrpc": "2.0", "id": 7, "method": "tools/list"}
        sessions = await _session_ids(api)
        assert sessions, "no MCP session was opened"
        for sid in sessions:
            headers = {"Authorization": f"Bearer {TOKENS['ops']}", "Mcp-Session-Id": sid,
                       "Accept": "application/json, text/event-stream",
                       "Mcp-Protocol-Version": "2025-06-18"}
            async with api.http.post("/mcp", json=listed, headers=headers) as resp:
                assert resp.status == 404, (resp.status, await resp.text())
        assert (await client.list_tools()).tools  # still the opener's


async def _session_ids(api: Api) -> list[str]:
    """The open sessions' ids, as the endpoint's SDK manager holds them."""
    endpoint = _endpoint(api)
    assert endpoint._server is not None
    return list(endpoint._server._manager._server_instances)


def _endpoint(api: Api) -> Any:
    assert api.app is not None
    for route in api.app.router.routes():
        if route.resource is not None and route.resource.canonical == "/mcp":
            return route.handler.__self__.endpoint  # type: ignore[attr-defined]
    raise AssertionError("no /mcp route")


async def test_resources_and_only_ones_own_audit_entries(api: Api) -> None:
    await api.command("ops", {"action": "stop", "params": {}})  # another principal's entry
    async with agent(api) as client:
        await client.call_tool("move", {"linear_x": 0.1, "duration_s": 0.5,
                                        "confidence": 0.9})
        uris = {str(r.uri) for r in (await client.list_resources()).resources}
        assert uris == {"robot://status", "robot://telemetry", "robot://safety-manifest",
                        "robot://audit/mine"}
        mine = json.loads((await client.read_resource("robot://audit/mine"))
                          .contents[0].text)  # type: ignore[union-attr]
        telemetry = json.loads((await client.read_resource("robot://telemetry"))
                               .contents[0].text)  # type: ignore[union-attr]
        manifest = json.loads((await client.read_resource("robot://safety-manifest"))
                              .contents[0].text)  # type: ignore[union-attr]
        with pytest.raises(MCPError, match="no resource"):
            await client.read_resource("robot://audit/all")
    assert [e["principal"] for e in mine["entries"]] == ["planner"]
    assert mine["entries"][0]["action_type"] == "move"
    assert telemetry["battery_pct"] == 87.5 and "ros" not in telemetry
    assert manifest["limits"]["max_linear_vel"] == 1.0
    status, body = await api.call("GET", "/api/audit/mine", "viewer")
    assert (status, body["entries"]) == (200, [])  # a GUEST reads its own (none)
    status, body = await api.call("GET", "/api/audit/mine", "ops")
    assert [e["action_type"] for e in body["entries"]] == ["stop"]


async def test_the_own_audit_route_pages_and_refuses_bad_queries(api: Api) -> None:
    for _ in range(5):
        await api.command("planner", {"action": "stop", "params": {}})
    await api.command("ops", {"action": "stop", "params": {}})
    status, body = await api.call("GET", "/api/audit/mine?last=2", "planner")
    seqs = [e["seq"] for e in body["entries"]]
    assert status == 200 and len(seqs) == 2 and seqs == sorted(seqs)
    assert seqs[-1] == max(e["seq"] for e in api.entries if e["principal"] == "planner")
    status, first = await api.call("GET", "/api/audit/mine?limit=3", "planner")
    assert len(first["entries"]) == 3
    status, rest = await api.call("GET", f"/api/audit/mine?since={first['next_since']}",
                                  "planner")
    assert len(rest["entries"]) == 2
    for query in ("last=-1", "last=abc", "since=x", "limit=0", "last=100000"):
        status, body = await api.call("GET", f"/api/audit/mine?{query}", "planner")
        assert (status, body["error_code"]) == (400, "SCHEMA_VALIDATION_FAILED"), query
    status, _ = await api.call("GET", "/api/audit/mine")
    assert status == 401


async def test_closing_the_session_stops_the_move_it_started(api: Api) -> None:
    async with agent(api, mode="legacy") as client:
        done = await client.call_tool("move", {"linear_x": 0.2, "duration_s": 20.0,
                                               "confidence": 0.9})
        assert data(done)["outcome"] == "executed"
    # The client's DELETE ended its session while the 20 s move ran. The SDK's client may
    # hang up before the answer (its exit cancelled under load): the stop goes on regardless.
    stops = await eventually(lambda: commands(api, "stop"), what="the session's stop")
    assert [e["params"]["reason"] for e in stops] == ["MCP session closed"], stops
    assert stops[0]["principal"] == "planner" and stops[0]["ai"]["model"] == "planner-7b"


async def test_a_move_not_yet_sent_when_its_session_closes_never_starts(api: Api) -> None:
    """The session's move waits for the robot (not yet executed: nothing held for it) when
    its session is closed: the session's stop stops it too — refused `stopped`, nothing
    reaches the robot — and it is not held for the closed session. It used to start once
    the robot was ready and be held (heartbeats) for its whole 20 s by a session gone."""
    release = api.dispatcher.hold_ready = asyncio.Event()
    entered = api.dispatcher.ready_entered
    async with agent(api, mode="legacy") as client:
        moving = asyncio.ensure_future(client.call_tool(
            "move", {"linear_x": 0.2, "duration_s": 20.0, "confidence": 0.9}))
        await asyncio.wait_for(entered.wait(), timeout=30)
        [sid] = await _session_ids(api)
        headers = {"Authorization": f"Bearer {TOKENS['planner']}", "Mcp-Session-Id": sid,
                   "Mcp-Protocol-Version": "2025-06-18"}
        async with api.http.delete("/mcp", headers=headers) as resp:
            assert resp.status < 300, (resp.status, await resp.text())
        stops = await eventually(lambda: commands(api, "stop"), what="the session's stop")
        release.set()
        with contextlib.suppress(Exception):  # its session is gone: it may get no answer
            await asyncio.wait_for(moving, timeout=30)
    # (the client's call may end, its session gone, before the governor has written the
    # move's outcome: CI once read the entries in between)
    [move] = await eventually(
        lambda: [e for e in api.entries if e.get("action_type") == "move"
                 and e["event"] == "COMMAND_FAILED"], what="the move's refusal")
    assert move["deny_reason"] == "COMMAND_REJECTED:stopped", move
    assert [e["params"]["reason"] for e in stops] == ["MCP session closed"], stops
    assert [a for a, _ in api.dispatcher.calls] == ["stop"]
    assert not _endpoint(api)._keepalives["planner"].holding


async def test_a_session_closed_after_its_move_ended_stops_nothing(api: Api) -> None:
    async with agent(api, mode="legacy") as client:
        done = await client.call_tool("move", {"linear_x": 0.1, "duration_s": 0.2,
                                               "confidence": 0.9})
        assert data(done)["outcome"] == "executed"
        keepalive = _endpoint(api)._keepalives["planner"]
        await eventually(lambda: not keepalive.holding, timeout=30, what="the move's end")
    assert commands(api, "stop") == []


async def test_an_action_added_to_the_registry_is_a_tool_at_mcp(
        api: Api, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_registry, "ACTIONS",
                        MappingProxyType({**_registry.ACTIONS, "beep": BEEP}))
    async with agent(api) as client:
        tools = {t.name: t for t in (await client.list_tools()).tools}
    assert tools["beep"].input_schema["required"] == ["volume"]


async def test_a_bad_body_is_a_clear_error_not_a_crash(api: Api) -> None:
    headers = {"Authorization": f"Bearer {TOKENS['planner']}",
               "Accept": "application/json, text/event-stream",
               "Content-Type": "application/json"}
    for raw in (b"{", b"[]", b'{"jsonrpc": "2.0"}', b"\xff\xfe", b"x" * (70 * 1024)):
        async with api.http.post("/mcp", data=raw, headers=headers) as resp:
            assert 400 <= resp.status < 500, (raw[:20], resp.status)
            assert resp.content_type == "application/json"
    async with aiohttp.ClientSession() as raw_client:
        url = api.http.make_url("/mcp")
        async with raw_client.get(url, headers=headers) as resp:  # a GET without a session
            assert 400 <= resp.status < 500


def test_a_bridge_loads_the_sdk_only_when_asked_and_says_what_is_missing(tmp_path: Path
                                                                         ) -> None:
    script = """
import asyncio, sys
from pathlib import Path
from tests.api.apihelpers import Api
async def main(block):
    if block:
        sys.modules["mcp"] = None  # as if the extra were not installed
    api = await Api(Path(sys.argv[1])).start()
    status, _ = await api.call("GET", "/api/status", "planner")
    sdk = ("mcp", "mcp_types", "starlette", "pydantic")
    loaded = sorted(m for m in sys.modules
                    if m.split(".")[0] in sdk and sys.modules[m] is not None)
    print("loaded", loaded)
    code, body = await api.call("POST", "/mcp", "planner", body={})
    print("mcp", code, body.get("error_code"), body.get("reason"))
    await api.close()
asyncio.run(main(sys.argv[2] == "block"))
"""
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(root / "src"), str(root), str(root / "tests")])}
    for mode, expect in (("block", "mcp 501 NOT_IMPLEMENTED"), ("free", "mcp 4")):
        (tmp_path / mode).mkdir()
        run = subprocess.run([sys.executable, "-c", script, str(tmp_path / mode), mode],
                             capture_output=True, text=True, timeout=120, check=False,
                             cwd=root, env=env)
        assert run.returncode == 0, run.stderr
        assert "loaded []" in run.stdout, run.stdout
        assert expect in run.stdout, run.stdout
        if mode == "block":
            assert "pip install 'rcan-rtps[mcp]'" in run.stdout


async def test_an_agent_lists_its_own_held_commands_only(api: Api) -> None:
    arm = {"joints": ["elbow"], "positions": [0.5], "duration_s": 1.0, "confidence": 0.9}
    await api.command("slow", {"action": "arm_joint", "params": {
        "joints": ["elbow"], "positions": [0.2], "duration_s": 1.0}})  # another USER's
    async with agent(api) as client:
        held = [data(await client.call_tool("arm_joint", arm))["pending_id"] for _ in range(2)]
        mine = await client.call_tool("get_my_pending_approvals", {})
    assert mine.content[0].text.startswith("2 held for a human")  # type: ignore[union-attr]
    assert sorted(p["pending_id"] for p in data(mine)["pending"]) == sorted(held)
    status, body = await api.call("GET", "/api/hitl/pending?mine=true", "slow")
    assert (status, [p["issued_by"] for p in body["pending"]]) == (200, ["slow"])
    status, body = await api.call("GET", "/api/hitl/pending", "slow")
    assert status == 403  # the whole list stays the approvers'
    status, body = await api.call("GET", "/api/hitl/pending?mine=yes", "slow")
    assert (status, body["path"]) == (400, "$.query.mine")
    status, body = await api.call("GET", "/api/hitl/pending?mine=false", "ops")
    assert status == 200 and len(body["pending"]) == 3


# -- a client that cancels a motion call (`notifications/cancelled`) -------------------------
#
# The SDK's client cancels a call when the task awaiting it is cancelled: it sends
# `notifications/cancelled` naming the call (the 2025 protocol: `legacy`). Before, the SDK
# cancelled the tool's handler, but the governor's decision is detached: the move was decided
# and ran on until its principal's session lapsed (session_timeout_s; never, on the harness's
# manual clock). Now the principal's motion on its way never starts and what runs stops.

MOVE = {"linear_x": 0.2, "duration_s": 20.0, "confidence": 0.9}
NAVIGATE = {"x": 1.0, "y": 2.0, "yaw": 0.0, "confidence": 0.9}


def failed(api: Api, action: str) -> list[dict[str, Any]]:
    return [e for e in api.entries if e.get("action_type") == action
            and e["event"] == "COMMAND_FAILED"]


async def cancelled(call: asyncio.Future[Any]) -> None:
    """Cancel the client's call (its `notifications/cancelled` goes out) and let it end."""
    call.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await call


def answers_held(api: Api) -> tuple[asyncio.Event, asyncio.Event]:
    """The governor's decision of a motion command is made (its motion started), and its
    answer held until the first event is set; the second is set once one is held."""
    return api.hold_decisions(lambda command: command.spec.motion, decided=True)


def replies_held(monkeypatch: pytest.MonkeyPatch, saying: bytes, *, first_only: bool = False
                 ) -> tuple[asyncio.Event, asyncio.Event]:
    """A reply saying `saying` is held on its way out of /mcp (its handler has returned)
    until the first event is set; the second is set once one is held. `first_only`: only
    the first such reply is held, the others go out."""
    release, answered = asyncio.Event(), asyncio.Event()
    send = _asgi._Exchange.send

    async def held(exchange: Any, message: Any) -> None:
        if message["type"] == "http.response.body" and saying in message.get("body", b"") \
                and not (first_only and answered.is_set()):
            answered.set()
            await release.wait()
        await send(exchange, message)

    monkeypatch.setattr(_asgi._Exchange, "send", held)
    return release, answered


@contextlib.asynccontextmanager
async def cancelling(api: Api, monkeypatch: pytest.MonkeyPatch) -> AsyncIterator[Client]:
    """The SDK's client (2025 protocol), the replies to its cancelled calls (`Request
    cancelled`) let out once it has gone: it fails to close when one comes as it closes."""
    reply, _ = replies_held(monkeypatch, b"Request cancelled")
    try:
        async with agent(api, mode="legacy") as client:
            yield client
    finally:
        reply.set()


async def withdrawals(api: Api) -> list[dict[str, Any]]:
    """The HITL_WITHDRAWN entries, once there is one."""
    return await eventually(lambda: [e for e in api.entries if e["event"] == "HITL_WITHDRAWN"],
                            what="its withdrawal")


def assert_never_started(api: Api, stop: dict[str, Any], refused: dict[str, Any]) -> None:
    """PLANNER's motion call, cancelled while it waited for the robot: refused `stopped`,
    nothing of it reached the robot, its own stop audited as its client's cancel, and no
    heartbeat holds anything of it."""
    assert refused["deny_reason"] == "COMMAND_REJECTED:stopped", refused
    assert stop["principal"] == "planner" and stop["applied"] == {
        "scope": "own", "cancelled_by_client": True, "on_its_way": True,
        "stream_ended": None, "goals_cancelled": []}, stop
    assert api.dispatcher.calls == [] and api.dispatcher.samples == []
    assert api.gov.streams.active is None and api.gov.streams.goals == {}
    assert not _endpoint(api)._keepalives["planner"].holding


def assert_zeroed_by_cancel(api: Api, stop: dict[str, Any], active: Any) -> None:
    """PLANNER's running move (`active`), cancelled by its client: its stream ended with
    zero, ended as cancelled by PLANNER, its own stop audited as its client's cancel."""
    assert api.gov.streams.active is None and api.dispatcher.samples[-1] == ZERO
    [ended] = [e for e in api.entries if e["event"] == "STREAM_ENDED"]
    assert (ended["params"]["reason"], ended["params"]["ended_by"]) == ("cancelled", "planner")
    assert stop["applied"]["stream_ended"] == active.message_id, stop
    assert stop["applied"]["cancelled_by_client"] is True


@pytest.mark.parametrize(("tool", "args"), [("move", MOVE), ("navigate", NAVIGATE)])
async def test_a_motion_call_cancelled_while_it_waits_never_starts(
        api: Api, monkeypatch: pytest.MonkeyPatch, tool: str, args: dict[str, Any]) -> None:
    """The call waits for the robot when its client cancels it: refused `stopped`, nothing
    reaches the robot, and the stop of the principal's own motion says its client cancelled
    it. Before, it started once the robot was ready and ran on."""
    release = api.dispatcher.hold_ready = asyncio.Event()
    async with cancelling(api, monkeypatch) as client:
        call = asyncio.ensure_future(client.call_tool(tool, args))
        await asyncio.wait_for(api.dispatcher.ready_entered.wait(), timeout=30)
        await cancelled(call)
        [stop] = await eventually(lambda: own_stops(api.entries), what="the cancel's own stop")
        release.set()
        [refused] = await eventually(lambda: failed(api, tool), what="its refusal")
    assert_never_started(api, stop, refused)


@pytest.mark.parametrize("answer", ["being_made", "on_its_way_out"])
async def test_a_move_cancelled_after_it_started_is_zeroed(
        api: Api, monkeypatch: pytest.MonkeyPatch, answer: str) -> None:
    """The move runs when its client cancels the call: its answer still being made (the
    SDK cancels the handler), or made and on its way out (the cancel crossed it: the client
    drops it and never learns the move started). Its stream ends with zero at once — not at
    its session's timeout, which the harness's manual clock never reaches — audited as its
    client's cancel; nothing else is halted and nothing holds the move (heartbeats)."""
    if answer == "being_made":
        _, held = answers_held(api)  # never released: the cancel interrupts the handler
    else:  # the answer the client drops goes out once it has gone (`cancelling`)
        reply, held = replies_held(monkeypatch, b"executed")
    async with cancelling(api, monkeypatch) as client:
        call = asyncio.ensure_future(client.call_tool("move", MOVE))
        await asyncio.wait_for(held.wait(), timeout=30)
        active = api.gov.streams.active
        assert active is not None and active.owner == "planner"
        await cancelled(call)
        [stop] = await eventually(lambda: own_stops(api.entries), what="the cancel's own stop")
    if answer == "on_its_way_out":
        reply.set()
    assert_zeroed_by_cancel(api, stop, active)
    assert [a for a, _ in api.dispatcher.calls] == ["move"]  # no stop of the whole robot
    assert not _endpoint(api)._keepalives["planner"].holding


async def test_another_principals_motion_goes_on(api: Api, monkeypatch: pytest.MonkeyPatch
                                                ) -> None:
    """OPS drives (over REST) while PLANNER's move waits for the robot and PLANNER's client
    cancels it: PLANNER's never starts, OPS's stream is neither zeroed nor replaced."""
    status, body = await api.command("ops", {"action": "move", "params": {"linear_x": 0.3}})
    assert (status, body["outcome"]) == (200, "executed"), body
    release = api.dispatcher.hold_ready = asyncio.Event()
    async with cancelling(api, monkeypatch) as client:
        call = asyncio.ensure_future(client.call_tool("move", MOVE))
        await asyncio.wait_for(api.dispatcher.ready_entered.wait(), timeout=30)
        samples = len(api.dispatcher.samples)
        await cancelled(call)
        await eventually(lambda: own_stops(api.entries), what="the cancel's own stop")
        release.set()
        await eventually(lambda: failed(api, "move"), what="PLANNER's refusal")
    active = api.gov.streams.active
    assert active is not None and (active.owner, active.target.linear_x) == ("ops", 0.3)
    assert ZERO not in api.dispatcher.samples[samples:]
    assert [a for a, _ in api.dispatcher.calls] == ["move"]  # OPS's, and no halt


ARM = {"joints": ["elbow"], "positions": [0.5], "duration_s": 1.0, "confidence": 0.9}


def held_for(api: Api, who: str) -> list[str]:
    return [p.pending_id for p in api.gov.pending() if p.issued_by == who]


async def test_an_arm_joint_held_for_approval_when_its_call_is_cancelled_is_withdrawn(
        api: Api, monkeypatch: pytest.MonkeyPatch) -> None:
    """PLANNER's arm_joint (gated behind an OWNER) is held, its answer `pending_auth` not yet
    sent, when its client cancels the call: it is withdrawn (HITL_WITHDRAWN by PLANNER, its
    reason its client's cancel), and an OWNER's approval is answered `pending_not_found` and
    moves nothing. SLOW's arm_joint held beside it still waits. Before, it stayed pending and
    the approval moved the arm for a client that had cancelled."""
    status, theirs = await api.command("slow", {"action": "arm_joint", "params": {
        "joints": ["elbow"], "positions": [0.2], "duration_s": 1.0}})
    assert (status, theirs["outcome"]) == (202, "pending_auth"), theirs
    release, decided = answers_held(api)
    async with cancelling(api, monkeypatch) as client:
        call = asyncio.ensure_future(client.call_tool("arm_joint", ARM))
        await asyncio.wait_for(decided.wait(), timeout=30)
        [mine] = held_for(api, "planner")
        await cancelled(call)
        [withdrawn] = await withdrawals(api)
        release.set()
    assert (withdrawn["principal"], withdrawn["pending_id"]) == ("planner", mine), withdrawn
    assert "cancelled" in withdrawn["approvals"][0]["reason"], withdrawn
    assert held_for(api, "planner") == [] and held_for(api, "slow") == [theirs["pending_id"]]
    status, late = await review(api, "authorize", "ops", mine)
    assert (status, late["reason"]) == (404, "pending_not_found"), late
    assert api.dispatcher.calls == []


async def test_an_arm_joint_whose_held_answer_crosses_its_cancel_is_withdrawn(
        api: Api, monkeypatch: pytest.MonkeyPatch) -> None:
    """PLANNER's arm_joint is held for an OWNER and its answer `pending_auth` made, on its
    way out, when its client cancels the call: the client drops that answer and never learns
    of the pending id, so the command is withdrawn as if the cancel had come in time
    (HITL_WITHDRAWN by PLANNER, its reason its client's cancel); an OWNER's approval after it
    is answered `pending_not_found` and moves nothing. Before, only an `executed` answer was
    remembered: it stayed held and the approval moved the arm for a client that had
    cancelled."""
    reply, answered = replies_held(monkeypatch, b"pending_auth")
    async with cancelling(api, monkeypatch) as client:
        call = asyncio.ensure_future(client.call_tool("arm_joint", ARM))
        await asyncio.wait_for(answered.wait(), timeout=30)
        [mine] = held_for(api, "planner")
        await cancelled(call)
        [withdrawn] = await withdrawals(api)
    reply.set()
    assert (withdrawn["principal"], withdrawn["pending_id"]) == ("planner", mine), withdrawn
    assert "cancelled" in withdrawn["approvals"][0]["reason"], withdrawn
    assert held_for(api, "planner") == []
    status, late = await review(api, "authorize", "ops", mine)
    assert (status, late["reason"]) == (404, "pending_not_found"), late
    assert api.dispatcher.calls == []


async def test_another_principals_answers_do_not_make_a_crossing_cancel_miss(
        api: Api, monkeypatch: pytest.MonkeyPatch) -> None:
    """PLANNER's arm_joint is held and its answer on its way out when LESSEE's agent (no
    session, the 2026 protocol) makes as many motion calls as the bridge remembers answers
    of, each answered `pending_auth`; then PLANNER's client cancels its call. The cancel
    still names a remembered call of PLANNER's: its arm_joint is withdrawn. Before, the
    answers were remembered in one store for all principals, the oldest let go first:
    another principal's calls pushed PLANNER's out, the cancel named nothing, and an OWNER
    could approve the arm_joint later for a client that had cancelled it."""
    from rcan_rtps.mcp_server.server import ANSWERED_KEPT

    reply, answered = replies_held(monkeypatch, b"pending_auth", first_only=True)
    async with cancelling(api, monkeypatch) as client:
        call = asyncio.ensure_future(client.call_tool("arm_joint", ARM))
        await asyncio.wait_for(answered.wait(), timeout=30)
        [mine] = held_for(api, "planner")
        async with agent(api, "lessee") as other:
            for _ in range(ANSWERED_KEPT):
                assert data(await other.call_tool("arm_joint", ARM))["outcome"] == \
                    "pending_auth"
        await cancelled(call)
        [withdrawn] = await withdrawals(api)
    reply.set()
    assert (withdrawn["principal"], withdrawn["pending_id"]) == ("planner", mine), withdrawn
    assert len(held_for(api, "lessee")) == ANSWERED_KEPT  # nobody else's is withdrawn
    status, late = await review(api, "authorize", "ops", mine)
    assert (status, late["reason"]) == (404, "pending_not_found"), late
