"""Issue 25: an AI agent over MCP, driven by the official MCP SDK's own client against
`rcan-rtps run --sim` (a real subprocess each), through both doors — `rcan-rtps mcp` (stdio,
in front of the bridge's REST API) and the bridge's own `/mcp` (streamable HTTP): the tools
are the registry's; a timed move drives the simulator about as far as it should (longer than
the session timeout: the server's heartbeats hold it); an over-limit move is refused with its
reason; a gated arm command waits for the OWNER, who approves it over REST, and the agent's
wait returns executed; an e-stop latches while the agent waits on another; a wrong token is
refused; the audit log names the agent — its model, provider and MCP client — on every
command it sent."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import signal
import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from mcp import Client, StdioServerParameters
from mcp.client.stdio import stdio_client
from mcp.client.streamable_http import streamable_http_client
from mcp.shared._httpx_utils import create_mcp_http_client
from mcp_types import CallToolResult, Implementation
from waiting import eventually

from rcan_rtps.rcan.actions import names
from tests.interop.test_demo import (
    ROOT,
    Demo,
    call,
    timed_move_distance,
    wait_status,
)

AGENT = {"provider": "acme", "model": "planner-7b", "client": "test-agent/1.2"}
READS = {"get_status", "get_goals", "get_my_pending_approvals", "get_pending_approval",
         "wait_for_approval"}


@pytest.fixture
async def http() -> AsyncIterator[aiohttp.ClientSession]:
    async with aiohttp.ClientSession() as session:
        yield session


@pytest.fixture(params=["stdio", "http"])
def door(request: pytest.FixtureRequest) -> str:
    return str(request.param)


@contextlib.asynccontextmanager
async def agent(demo: Demo, tmp_path: Path, token: str | None = None, door: str = "stdio"
                ) -> AsyncIterator[Client]:
    """With the USER's token: `python -m rcan_rtps mcp` as an MCP client launches it, or the
    bridge's `/mcp` with the agent's model in headers."""
    if door == "http":
        headers = {"Authorization": f"Bearer {token or demo.user}",
                   "RCAN-AI-Provider": AGENT["provider"], "RCAN-AI-Model": AGENT["model"]}
        async with create_mcp_http_client(headers=headers) as http, Client(
                streamable_http_client(f"{demo.url}/mcp", http_client=http),
                client_info=Implementation(name="test-agent", version="1.2")) as c:
            yield c
        return
    server = StdioServerParameters(
        command=sys.executable,
        args=["-m", "rcan_rtps", "mcp", "--url", demo.url, "--token-env", "AGENT_TOKEN",
              "--ai-provider", AGENT["provider"], "--ai-model", AGENT["model"]],
        env={"AGENT_TOKEN": token or demo.user, "PYTHONPATH": os.environ.get("PYTHONPATH", "")})
    with (tmp_path / "mcp.err").open("a") as errlog:
        async with Client(stdio_client(server, errlog=errlog),
                          client_info=Implementation(name="test-agent", version="1.2")) as c:
            yield c


def data(done: CallToolResult) -> dict[str, Any]:
    assert done.structured_content is not None, done
    return dict(done.structured_content)


def entries(demo: Demo) -> list[dict[str, Any]]:
    return [json.loads(line) for line in demo.audit.read_text().splitlines()]


async def test_tools_and_a_timed_move(sim: Demo, http: aiohttp.ClientSession,
                                      tmp_path: Path, door: str) -> None:
    async with agent(sim, tmp_path, door=door) as client:
        tools = {t.name for t in (await client.list_tools()).tools}
        assert tools == set(names()) | READS

        async def send() -> str:
            # 7 s: longer than the demo's 5 s session timeout, held by the server's heartbeats
            done = await client.call_tool("move", {"linear_x": 0.2, "duration_s": 7.0,
                                                   "confidence": 0.9})
            assert not done.is_error, done
            assert (data(done)["outcome"], data(done)["http_status"]) == ("executed", 200)
            return str(data(done)["message_id"])

        distance = await timed_move_distance(http, sim, send)
        assert 1.2 <= distance <= 1.5, distance  # 7 s at 0.2 m/s, less the 0.1 s ramp
        status = data(await client.call_tool("get_status", {}))
        assert status["state"] != "safe_stop" and status["estop"] is False, status

        over = await client.call_tool("move", {"linear_x": 2.0, "duration_s": 1.0,
                                               "confidence": 0.9})
        assert over.is_error
        assert (data(over)["http_status"], data(over)["outcome"], data(over)["reason"]) == (
            409, "safety_violation", "velocity_limit"), data(over)
        assert "velocity_limit" in over.content[0].text  # type: ignore[union-attr]
        untimed = await client.call_tool("move", {"linear_x": 0.1, "confidence": 0.9})
        assert untimed.is_error and "duration_s" in data(untimed)["reason"]
        goals = data(await client.call_tool("get_goals", {}))
        assert goals["goals"] == []
    mine = [e for e in entries(sim) if e.get("action_type") == "move"
            and e["event"] in ("COMMAND_DISPATCHED", "COMMAND_REJECTED")]
    assert [e["outcome"] for e in mine] == ["executed", "safety_violation"], mine
    for entry in mine:  # the agent's identity, with a thought of its own per call
        assert entry["principal"] == "operator"
        assert {k: entry["ai"][k] for k in AGENT} == AGENT, entry["ai"]
    assert len({e["ai"]["thought_id"] for e in mine}) == 2
    ended = [e for e in entries(sim) if e["event"] == "STREAM_ENDED"]
    assert [e["params"]["reason"] for e in ended] == ["completed"], ended


async def test_a_gated_command_waits_for_the_owner(sim: Demo, http: aiohttp.ClientSession,
                                                   tmp_path: Path, door: str) -> None:
    await wait_status(http, sim, lambda s: s["ros"]["connected"])
    async with agent(sim, tmp_path, door=door) as client:
        held = await client.call_tool("arm_joint", {
            "joints": ["elbow"], "positions": [0.8], "duration_s": 1.0, "confidence": 0.9})
        assert not held.is_error, held
        pending_id = data(held)["pending_id"]
        assert (data(held)["outcome"], data(held)["http_status"]) == ("pending_auth", 202)
        assert "wait_for_approval" in held.content[0].text  # type: ignore[union-attr]
        seen = data(await client.call_tool("get_pending_approval", {"pending_id": pending_id}))
        assert (seen["state"], seen["pending"]["requires_auth_from_role"]) == (
            "pending", "OWNER"), seen

        waiting = asyncio.create_task(client.call_tool(
            "wait_for_approval", {"pending_id": pending_id, "timeout_s": 60}))
        await asyncio.sleep(1.0)
        assert not waiting.done()
        code, approved = await call(http, sim, sim.owner, "POST", "/api/hitl/authorize",
                                    {"pending_id": pending_id})
        assert (code, approved["outcome"]) == (200, "executed"), approved
        done = await asyncio.wait_for(waiting, 30)
        assert not done.is_error, done
        assert (data(done)["state"], data(done)["outcome"]) == ("resolved", "executed")
        assert data(done)["decision"]["audit_id"] == approved["audit_id"]
    authorized = [e for e in entries(sim) if e["event"] == "HITL_AUTHORIZED"]
    assert len(authorized) == 1 and authorized[0]["ai"]["client"] == AGENT["client"]


async def test_estop_latches_while_the_agent_waits(sim: Demo, http: aiohttp.ClientSession,
                                                   tmp_path: Path, door: str) -> None:
    await wait_status(http, sim, lambda s: s["ros"]["connected"])
    async with agent(sim, tmp_path, door=door) as client:
        held = data(await client.call_tool("arm_joint", {
            "joints": ["elbow"], "positions": [0.3], "duration_s": 1.0, "confidence": 0.9}))
        waiting = asyncio.create_task(client.call_tool(
            "wait_for_approval", {"pending_id": held["pending_id"], "timeout_s": 20}))
        await asyncio.sleep(0.5)
        stopped = await client.call_tool("estop", {"reason": "agent saw a person"})
        assert not stopped.is_error and data(stopped)["outcome"] == "executed", stopped
        # The e-stop withdrew the held arm_joint (it stops all held motion), which ends the
        # wait: an e-stop that waited behind the wait would have found it ended still
        # pending, at its timeout.
        done = data(await waiting)
        assert (done["state"], done["decision"]["reason"]) == ("resolved", "hitl_withdrawn"), done
        await wait_status(http, sim, lambda s: s["estop"])
        refused = await client.call_tool("move", {"linear_x": 0.1, "duration_s": 1.0,
                                                  "confidence": 0.9})
        assert refused.is_error and data(refused)["http_status"] == 409, data(refused)
        clear = await client.call_tool("clear_estop", {})  # an OWNER's, not a USER's
        assert clear.is_error and data(clear)["http_status"] == 403, data(clear)
    estops = [e for e in entries(sim) if e.get("action_type") == "estop"]
    assert estops and estops[0]["ai"]["client"] == AGENT["client"], estops


async def test_a_wrong_token_is_refused(sim: Demo, http: aiohttp.ClientSession,
                                        tmp_path: Path, door: str) -> None:
    await wait_status(http, sim, lambda s: s["ros"]["connected"])
    before = len(entries(sim))
    wrong = "not-the-agents-token-0123456789"
    if door == "http":  # refused at the door: the SDK's client cannot even initialize
        with pytest.raises(Exception):  # noqa: B017 (the SDK's error type varies by era)
            async with agent(sim, tmp_path, token=wrong, door=door):
                pass
        async with http.post(f"{sim.url}/mcp", json={}) as resp:  # and no token at all
            assert (resp.status, (await resp.json())["error_code"]) == (401, "UNAUTHENTICATED")
    else:  # the stdio server starts (the bridge may come later); each call is refused
        async with agent(sim, tmp_path, token=wrong, door=door) as client:
            for name, args in (("get_status", {}),
                               ("move", {"linear_x": 0.1, "duration_s": 1.0}), ("estop", {})):
                done = await client.call_tool(name, args)
                assert done.is_error, name
                assert (data(done)["http_status"], data(done)["error_code"]) == (
                    401, "UNAUTHENTICATED"), data(done)
    code, status = await call(http, sim, sim.user, "GET", "/api/status")
    assert code == 200 and status["estop"] is False
    assert not [e for e in entries(sim)[before:] if e.get("ai")]  # nothing of it ran


async def test_a_goal_is_held_until_it_ends(sim: Demo, http: aiohttp.ClientSession,
                                            tmp_path: Path, door: str) -> None:
    """A navigation goal outlasts the 5 s session timeout: the server heartbeats until the goal
    has ended (without, the session would lapse and the bridge cancel the goal)."""
    await wait_status(http, sim, lambda s: s["ros"]["connected"])
    async with agent(sim, tmp_path, door=door) as client:
        sent = await client.call_tool("navigate", {"x": 2.0, "y": 1.0, "yaw": 0.0,
                                                   "confidence": 0.9})
        assert not sent.is_error and data(sent)["goal_id"], sent
        goal_id = data(sent)["goal_id"]

        async def ended() -> str | None:
            goals = data(await client.call_tool("get_goals", {}))["goals"]
            state = next(g["state"] for g in goals if g["goal_id"] == goal_id)
            return None if state in ("accepted", "executing") else str(state)

        assert await eventually(ended, timeout=60, what="the goal's end") == "succeeded"
    assert not [e for e in entries(sim) if e["event"] == "NETWORK_LOSS_SAFE_STOP"]


async def test_an_agent_gone_mid_move_stops_it(sim: Demo, http: aiohttp.ClientSession,
                                               tmp_path: Path) -> None:
    await wait_status(http, sim, lambda s: s["ros"]["connected"])
    async with agent(sim, tmp_path) as client:
        done = await client.call_tool("move", {"linear_x": 0.2, "duration_s": 20.0,
                                               "confidence": 0.9})
        assert data(done)["outcome"] == "executed", done
        await wait_status(http, sim, lambda s: s["state"] == "moving")
    # the client closed the server's stdin: it stopped what it had started, at once
    stops = [e for e in entries(sim) if e.get("action_type") == "stop"]
    assert [e["params"].get("reason") for e in stops] == ["MCP client disconnected"], stops
    await wait_status(http, sim, lambda s: s["telemetry"]["velocity"]["linear_x"] == 0.0)


def _rpc(proc: subprocess.Popen[str], message: dict[str, Any]) -> dict[str, Any] | None:
    """One JSON-RPC message to the stdio server; its reply when it is a request."""
    assert proc.stdin is not None and proc.stdout is not None
    proc.stdin.write(json.dumps({"jsonrpc": "2.0", **message}) + "\n")
    proc.stdin.flush()
    if "id" not in message:
        return None
    reply: dict[str, Any] = json.loads(proc.stdout.readline())
    assert reply.get("id") == message["id"] and "result" in reply, reply
    return reply


async def test_an_agent_server_terminated_mid_move_stops_it(
        sim: Demo, http: aiohttp.ClientSession, tmp_path: Path) -> None:
    """SIGTERM (a supervisor ending the agent's server; SIGINT and SIGHUP likewise) while
    its move runs: the server stops the move before it exits, as when its client goes.
    Before, SIGTERM killed it on the spot and the robot drove on to the move's end."""
    await wait_status(http, sim, lambda s: s["ros"]["connected"])
    with (tmp_path / "mcp.err").open("w") as errlog:
        proc = subprocess.Popen(
            [sys.executable, "-m", "rcan_rtps", "mcp", "--url", sim.url, "--token-env",
             "AGENT_TOKEN", "--ai-provider", AGENT["provider"], "--ai-model", AGENT["model"]],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=errlog, text=True,
            env={**os.environ, "AGENT_TOKEN": sim.user})
    try:
        _rpc(proc, {"id": 1, "method": "initialize", "params": {
            "protocolVersion": "2025-06-18", "capabilities": {},
            "clientInfo": {"name": "test-agent", "version": "1.2"}}})
        _rpc(proc, {"method": "notifications/initialized"})
        done = _rpc(proc, {"id": 2, "method": "tools/call", "params": {
            "name": "move", "arguments": {"linear_x": 0.2, "duration_s": 30.0,
                                          "confidence": 0.9}}})
        assert done is not None and done["result"]["structuredContent"]["outcome"] == \
            "executed", done
        await wait_status(http, sim, lambda s: s["state"] == "moving")
        proc.send_signal(signal.SIGTERM)
        code = await asyncio.to_thread(proc.wait, 60)
    finally:
        proc.kill()
        proc.wait()
        assert proc.stdin is not None
        proc.stdin.close()
    assert code == 128 + signal.SIGTERM, (tmp_path / "mcp.err").read_text()
    stops = [e for e in entries(sim) if e.get("action_type") == "stop"]
    assert [e["params"].get("reason") for e in stops] == ["MCP server ended by SIGTERM"], stops
    await wait_status(http, sim, lambda s: s["telemetry"]["velocity"]["linear_x"] == 0.0)


def readme_config(path: Path, name: str = "mcp-config") -> dict[str, Any]:
    block = re.search(rf"<!-- {name} -->\n```json\n(.*?)```", path.read_text(), re.S)
    assert block, f"{path.name} has no mcp-config block"
    return dict(json.loads(block.group(1)))


async def test_the_readme_client_configuration(sim: Demo, http: aiohttp.ClientSession,
                                               tmp_path: Path) -> None:
    """The README's one line, as a client would run it (with this run's URL and token)."""
    config = readme_config(ROOT / "README.md")
    assert config == readme_config(ROOT / "docs" / "mcp.md")
    entry = config["mcpServers"]["robot"]
    assert entry["command"] == "rcan-rtps"
    args = [sim.url if a == "http://127.0.0.1:8765" else a for a in entry["args"]]
    env = {name: sim.user for name in entry["env"]}
    server = StdioServerParameters(
        command=str(Path(sys.executable).parent / "rcan-rtps"), args=args,
        env={**env, "PYTHONPATH": os.environ.get("PYTHONPATH", "")})
    await wait_status(http, sim, lambda s: s["ros"]["connected"])
    with (tmp_path / "mcp.err").open("a") as errlog:
        async with Client(stdio_client(server, errlog=errlog)) as client:
            status = data(await client.call_tool("get_status", {}))
            assert (status["http_status"], status["estop"]) == (200, False), status
            done = await client.call_tool("stop", {"reason": "readme check"})
            assert data(done)["outcome"] == "executed", done
    stop = [e for e in entries(sim) if e.get("action_type") == "stop"][-1]
    assert (stop["ai"]["provider"], stop["ai"]["model"]) == ("anthropic", "claude-sonnet-4-5")


async def test_the_readme_http_client_configuration(sim: Demo, http: aiohttp.ClientSession
                                                    ) -> None:
    """The README's HTTP line, as a client would use it (this run's URL and USER token)."""
    config = readme_config(ROOT / "README.md", "mcp-http-config")
    assert config == readme_config(ROOT / "docs" / "mcp.md", "mcp-http-config")
    entry = config["mcpServers"]["robot"]
    assert entry["type"] == "http"
    url = entry["url"].replace("http://127.0.0.1:8765", sim.url)
    headers = {k: v.replace("<USER token>", sim.user) for k, v in entry["headers"].items()}
    await wait_status(http, sim, lambda s: s["ros"]["connected"])
    async with create_mcp_http_client(headers=headers) as client_http, \
            Client(streamable_http_client(url, http_client=client_http)) as client:
        status = data(await client.call_tool("get_status", {}))
        assert (status["http_status"], status["estop"]) == (200, False), status
        done = await client.call_tool("stop", {"reason": "readme check"})
        assert data(done)["outcome"] == "executed", done
    stop = [e for e in entries(sim) if e.get("action_type") == "stop"][-1]
    assert (stop["principal"], stop["ai"]["provider"], stop["ai"]["model"]) == (
        "operator", "anthropic", "claude-sonnet-4-5")


# -- the README's session transcript ----------------------------------------------------------

TRANSCRIPT = re.compile(r"<!-- mcp-transcript -->\n```text\n(.*?)```", re.S)
SESSION: list[tuple[str, dict[str, Any]]] = [
    ("move", {"linear_x": 0.3, "duration_s": 2.0, "confidence": 0.9,
              "reasoning": "the user asked me to drive to the door"}),
    ("move", {"linear_x": 2.0, "duration_s": 1.0, "confidence": 0.9}),
    ("arm_joint", {"joints": ["elbow"], "positions": [0.8], "duration_s": 1.0,
                   "confidence": 0.9}),
    ("wait_for_approval", {"pending_id": "<pending_id>", "timeout_s": 60}),
    ("estop", {"reason": "a person stepped in front of the robot"}),
    ("move", {"linear_x": 0.1, "duration_s": 1.0, "confidence": 0.9}),
]


def said(done: CallToolResult) -> str:
    first = done.content[0].text.splitlines()[0]  # type: ignore[union-attr]
    return ("error: " if done.is_error else "") + first


async def transcript_of_a_session(client: Client, http: aiohttp.ClientSession,
                                  sim: Demo) -> list[str]:
    """The session as an agent's client sees it: each call and the first line of its result
    (pending ids replaced by `<pending_id>`); an OWNER approves the held command over REST."""
    tools = [t.name for t in (await client.list_tools()).tools]
    lines = ["→ tools/list", f"← {len(tools)} tools: {', '.join(tools)}"]
    pending_id = ""
    for name, args in SESSION:
        sent = {k: (pending_id if v == "<pending_id>" else v) for k, v in args.items()}
        if name == "wait_for_approval":
            code, approved = await call(http, sim, sim.owner, "POST", "/api/hitl/authorize",
                                        {"pending_id": pending_id})
            assert code == 200, (approved.get("reason"), approved)
            lines.append(f"  (an OWNER: POST /api/hitl/authorize → {code} "
                         f"{approved['outcome']})")
        done = await client.call_tool(name, sent)
        if data(done).get("outcome") == "pending_auth":
            pending_id = str(data(done)["pending_id"])
        lines += [f"→ {name} {json.dumps(args)}",
                  f"← {said(done).replace(pending_id or '<none>', '<pending_id>')}"]
    return lines


async def test_the_readme_transcript(sim: Demo, http: aiohttp.ClientSession,
                                     tmp_path: Path) -> None:
    """A real session over `/mcp`, as README.md and docs/mcp.md show it (RCAN_WRITE_DOCS=1
    writes it there)."""
    await wait_status(http, sim, lambda s: s["ros"]["connected"])
    async with agent(sim, tmp_path, door="http") as client:
        lines = await transcript_of_a_session(client, http, sim)
    entry = next(e for e in entries(sim) if e.get("action_type") == "move")
    lines.append(f"audit: {json.dumps({k: entry[k] for k in ('principal', 'outcome')})} "
                 f"ai={json.dumps({k: entry['ai'][k] for k in AGENT})}")
    text = "\n".join(lines) + "\n"
    for doc in (ROOT / "README.md", ROOT / "docs" / "mcp.md"):
        if os.environ.get("RCAN_WRITE_DOCS") == "1":
            doc.write_text(TRANSCRIPT.sub(lambda _: f"<!-- mcp-transcript -->\n```text\n"
                                          f"{text}```", doc.read_text(), count=1))
        shown = TRANSCRIPT.search(doc.read_text())
        assert shown, f"{doc.name} has no mcp-transcript block"
        assert shown.group(1) == text, f"{doc.name}'s transcript is not this session's"
