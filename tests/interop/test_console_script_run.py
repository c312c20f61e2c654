"""`rcan-rtps run --sim` started through the console script pip installed beside this
interpreter, as a user starts it.

The other tests start the bridge as `python -m rcan_rtps`; this one goes through the
`rcan-rtps` entry point (`rcan_rtps._launch:main`). scripts/python310.sh runs it on Python 3.10
against the installed wheel (the oldest Python the project promises): the ready line, a move the
simulated robot's odometry shows, an e-stop that halts it and refuses the next move, and a clean
stop on SIGINT. Run inside `scripts/netns`.
"""

from __future__ import annotations

import asyncio
import json
import signal
import sys
from pathlib import Path
from typing import Any

import aiohttp
from waiting import eventually

from .run_process import REQUEST_TIMEOUT, RunProcess, child_env, state_args

EXIT_TIMEOUT = 60.0
MOVE = {"action": "move", "params": {"linear_x": 0.4, "duration_s": 30.0}}


class Api:
    """The bridge's HTTP API as the demo's operator (USER token)."""

    def __init__(self, http: aiohttp.ClientSession, proc: RunProcess) -> None:
        self.http, self.url = http, proc.url
        self.headers = {"Authorization": f"Bearer {proc.user}"}

    async def call(self, method: str, path: str, body: Any = None) -> tuple[int, Any]:
        async with self.http.request(method, self.url + path, json=body,
                                     headers=self.headers) as resp:
            return resp.status, await resp.json()

    async def status_when(self, holds: Any, what: str) -> dict[str, Any]:
        """The first STATUS for which `holds` is true; heartbeats keep the session (5 s in
        the demo) while it waits, so a slow machine does not halt the robot for us."""
        async def matching() -> dict[str, Any] | None:
            await self.call("POST", "/api/heartbeat")
            _, status = await self.call("GET", "/api/status")
            return status if holds(status) else None

        found: dict[str, Any] = await eventually(matching, timeout=30, interval=0.1, what=what)
        return found


def _x(status: dict[str, Any]) -> float:
    return float(status["telemetry"]["position"]["x"])


def _speed(status: dict[str, Any]) -> float | None:
    velocity = status["telemetry"]["velocity"]
    return None if velocity is None else float(velocity["linear_x"])


async def _drive_then_estop(proc: RunProcess) -> dict[str, Any]:
    timeout = aiohttp.ClientTimeout(total=REQUEST_TIMEOUT)
    async with aiohttp.ClientSession(timeout=timeout) as http:
        api = Api(http, proc)
        start = _x(await api.status_when(
            lambda s: s["ros"]["connected"] and s["telemetry"]["position"] is not None,
            "the simulated robot connected, its odometry read"))
        code, moved = await api.call("POST", "/api/command", MOVE)
        assert code == 200 and moved["outcome"] == "executed", moved
        await api.status_when(lambda s: _x(s) > start + 0.05, "the robot moving forward")

        code, stopped = await api.call("POST", "/api/command", {"action": "estop"})
        assert code == 200 and stopped["outcome"] == "executed", stopped
        halted = await api.status_when(lambda s: s["estop"] and _speed(s) == 0.0,
                                       "the e-stop latched and the robot standing")
        assert halted["state"] == "estop", halted
        code, refused = await api.call("POST", "/api/command", MOVE)
        assert code == 409 and refused["reason"] == "estop_active", refused
        return {"move": moved["message_id"], "estop": stopped["message_id"]}


def test_the_console_script_runs_moves_estops_and_stops_on_sigint(tmp_path: Path,
                                                                  domain_id: int) -> None:
    script = Path(sys.executable).with_name("rcan-rtps")
    assert script.is_file(), f"no console script beside {sys.executable}"
    proc = RunProcess(["run", "--sim", "--port", "0", "--no-mdns",
                       *state_args(tmp_path, "state")],
                      child_env(domain_id), demo=True, program=[str(script)])
    try:
        ids = asyncio.run(_drive_then_estop(proc))
        proc.signal(signal.SIGINT)
        assert proc.wait(EXIT_TIMEOUT) == 0, proc.output()
    finally:
        proc.kill()
    assert "Traceback" not in "".join(proc.stderr), proc.output()
    entries = [json.loads(line)
               for line in (tmp_path / "state" / "audit.jsonl").read_text().splitlines()]
    ended = [e["params"]["reason"] for e in entries
             if e["event"] == "STREAM_ENDED" and e["message_id"] == ids["move"]]
    assert ended == ["estopped"], ended  # the e-stop, not the move's own end, stopped it
    assert [e["event"] for e in entries if e.get("message_id") == ids["estop"]] == ["ESTOP"]
    assert entries[-1]["event"] == "BRIDGE_STOPPED", entries[-1]
