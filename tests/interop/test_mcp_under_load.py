"""MCP on a busy robot computer, against `rcan-rtps run --sim`: fresh agents over `/mcp` (both
protocol eras) with the CPU saturated by a load generator, every round an e-stop, a clear by
the OWNER and a timed move, losses counted and required to be zero; and a stdio MCP server
killed (SIGKILL) in the middle of a move it started: nobody is left to stop it, so the
bridge's session timeout must halt the robot."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from waiting import eventually

from tests.interop.test_demo import Demo, call, wait_status
from tests.interop.test_mcp_sim import AGENT, agent, data, entries

ROUNDS = 20


@pytest.mark.slow
async def test_fresh_agents_stop_clear_and_move_every_round_under_cpu_load(
        sim: Demo, tmp_path: Path, cpu_load: None) -> None:
    lost: dict[str, int] = {"estop": 0, "clear": 0, "move": 0}
    async with aiohttp.ClientSession() as http:
        await wait_status(http, sim, lambda s: s["ros"]["connected"], timeout=60)
        for round_ in range(ROUNDS):
            async with agent(sim, tmp_path, door="http") as client:
                stopped = await client.call_tool("estop", {"reason": f"round {round_}"})
                if stopped.is_error or data(stopped).get("outcome") != "executed":
                    lost["estop"] += 1
                code, _ = await call(http, sim, sim.owner, "POST", "/api/command",
                                           {"action": "clear_estop", "params": {}})
                if code != 200:
                    lost["clear"] += 1
                moved = await client.call_tool("move", {"linear_x": 0.1, "duration_s": 0.5,
                                                        "confidence": 0.9})
                if moved.is_error or data(moved).get("outcome") != "executed":
                    lost["move"] += 1
    print(f"{ROUNDS} rounds under load, lost: {lost}")
    assert lost == {"estop": 0, "clear": 0, "move": 0}
    estops = [e for e in entries(sim) if e.get("action_type") == "estop"
              and e.get("outcome") == "executed" and e["principal"] == "operator"]
    assert len(estops) == ROUNDS  # each audited once, with the agent's model
    assert {e["ai"]["model"] for e in estops} == {AGENT["model"]}


def _line(proc: subprocess.Popen[bytes], message: dict[str, Any]) -> None:
    assert proc.stdin is not None
    proc.stdin.write(json.dumps(message).encode() + b"\n")
    proc.stdin.flush()


def _reply(proc: subprocess.Popen[bytes], want_id: int) -> dict[str, Any]:
    assert proc.stdout is not None
    while True:
        line = proc.stdout.readline()
        assert line, "the MCP server closed its stdout"
        message = json.loads(line)
        if message.get("id") == want_id:
            return dict(message)


async def test_a_stdio_server_killed_mid_move_leaves_the_robot_halted(sim: Demo,
                                                                      tmp_path: Path) -> None:
    async with aiohttp.ClientSession() as http:
        await wait_status(http, sim, lambda s: s["ros"]["connected"])
        proc = subprocess.Popen(
            [sys.executable, "-m", "rcan_rtps", "mcp", "--url", sim.url, "--token-env", "T",
             "--ai-provider", AGENT["provider"], "--ai-model", AGENT["model"]],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            stderr=(tmp_path / "mcp.err").open("wb"),
            env={**os.environ, "T": sim.user})
        try:
            _line(proc, {"jsonrpc": "2.0", "id": 1, "method": "initialize", "params": {
                "protocolVersion": "2025-06-18", "capabilities": {},
                "clientInfo": {"name": "killed-agent", "version": "1"}}})
            assert "result" in _reply(proc, 1)
            _line(proc, {"jsonrpc": "2.0", "method": "notifications/initialized"})
            _line(proc, {"jsonrpc": "2.0", "id": 2, "method": "tools/call", "params": {
                "name": "move", "arguments": {"linear_x": 0.2, "duration_s": 25.0,
                                              "confidence": 0.9}}})
            moved = _reply(proc, 2)["result"]
            assert moved["structuredContent"]["outcome"] == "executed", moved
            await wait_status(http, sim, lambda s: s["state"] == "moving")
            await asyncio.sleep(6.0)  # past the 5 s session timeout: the heartbeats held it
            status = await wait_status(http, sim, lambda s: True)
            assert status["state"] == "moving", status
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=10)
        # no stop at exit (it was killed): the lapsed session halts the robot
        await wait_status(http, sim, lambda s: (s["telemetry"]["velocity"] or {})
                          .get("linear_x") == 0.0, timeout=30)

    def session_lost() -> bool:
        return any(e["event"] == "STREAM_ENDED" and e["params"].get("reason") == "session_lost"
                   for e in entries(sim))

    await eventually(session_lost, timeout=20, what="the stream ended by the lapsed session")
    stops = [e["event"] for e in entries(sim) if e.get("action_type") == "stop"]
    assert stops == ["NETWORK_LOSS_SAFE_STOP"], stops  # the bridge's halt; nobody sent one
