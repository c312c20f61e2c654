"""Issue 24: the official `rcan` SDK drives `rcan-rtps run --sim` (a real subprocess, as the
README's tour does): the SDK is the oracle of the RCAN side, as rclpy is of the wire."""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import re
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from rcan.address import RobotURI
from rcan.encoding import canonical_json
from rcan.message import RCANMessage
from rcan.safety import make_estop_message, make_resume_message, make_stop_message
from waiting import eventually

from tests.interop.test_demo import ROOT, Demo, call, stream_ended, wait_status


@pytest.fixture
async def session() -> AsyncIterator[aiohttp.ClientSession]:
    async with aiohttp.ClientSession() as client:
        yield client


def sdk_lines() -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    block = re.search(r"<!-- sdk-client -->\n```python\n(.*?)```", text, re.S)
    assert block, "README.md has no sdk-client block"
    return block.group(1)


async def test_the_readme_sdk_client(sim: Demo, session: aiohttp.ClientSession,
                                     tmp_path: Path) -> None:
    demo, http = sim, session
    await wait_status(http, demo, lambda s: s["ros"]["connected"])
    script = tmp_path / "client.py"
    script.write_text(sdk_lines())
    env = {**os.environ, "API": demo.url, "U": demo.user, "O": demo.owner}
    done = await asyncio.to_thread(subprocess.run, [sys.executable, str(script)], env=env,
                                   capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    said = [line.split("#")[1].split(":")[0].strip() for line in sdk_lines().splitlines()
            if line.startswith("print(")]
    assert done.stdout.split() == said == ["AUDIT_INCOMPLETE_AI_IDENTITY", "ok",
                                           "REPLAY_DETECTED", "ok", "blocked", "ok"]


async def test_the_sdk_drives_the_simulator(sim: Demo, session: aiohttp.ClientSession) -> None:
    demo, http = sim, session
    status = await wait_status(http, demo, lambda s: s["ros"]["connected"] and
                               s["telemetry"]["position"] is not None)
    robot = RobotURI.parse(status["ruri"])  # the SDK parses the bridge's RURI
    assert str(robot) == status["ruri"]
    start_x = status["telemetry"]["position"]["x"]

    async def send(token: str, body: dict[str, Any]) -> tuple[int, Any]:
        return await call(http, demo, token, "POST", "/api/command", body)

    # COMMAND: executed, audited, and the robot moves
    held = RCANMessage(cmd="move", target=robot, params={"linear_x": 0.4}, confidence=0.8)
    ai = {"ai": {"provider": "acme", "model": "planner-7b"}}  # an AI command names its model
    code, body = await send(demo.user, held.to_dict() | ai)
    assert (code, body["status"], body["msg_id"]) == (200, "ok", held.msg_id), body
    await wait_status(http, demo, lambda s: s["telemetry"]["position"]["x"] > start_x + 0.05)
    # STOP halts that held stream
    code, body = await send(demo.user, make_stop_message(str(robot), "enough"))
    assert (code, body["status"]) == (200, "ok"), body
    await eventually(lambda: stream_ended(demo, held.msg_id) is not None, timeout=20,
                     what="the held move's end in the audit log")
    await wait_status(http, demo, lambda s: s["telemetry"]["velocity"]["linear_x"] == 0.0)

    # stale and replayed messages are refused
    stale = RCANMessage(cmd="move", target=robot, params={"linear_x": 0.1},
                        timestamp=time.time() - 60)
    code, body = await send(demo.user, stale.to_dict())
    assert (code, body["error_code"]) == (408, "MESSAGE_STALE"), body
    once = RCANMessage(cmd="move", target=robot, params={"linear_x": 0.1, "duration_s": 0.5})
    assert (await send(demo.user, once.to_dict()))[0] == 200
    code, body = await send(demo.user, once.to_dict())
    assert (code, body["error_code"]) == (409, "REPLAY_DETECTED"), body
    stop = RCANMessage(cmd="stop", target=robot)
    assert (await send(demo.user, stop.to_dict()))[0] == 200
    code, body = await send(demo.user, stop.to_dict())  # a replayed stop still stops
    assert (code, body["status"]) == (200, "ok") and body["warnings"], body

    # ESTOP latches; RESUME clears only for an OWNER
    code, body = await send(demo.user, make_estop_message(str(robot), "drill"))
    assert (code, body["status"]) == (200, "ok"), body
    await wait_status(http, demo, lambda s: s["estop"])
    code, body = await send(demo.user, held.to_dict() | ai | {"msg_id": "m-after-estop",
                                                                "timestamp": time.time()})
    assert (code, body["status"]) == (409, "blocked"), body
    code, body = await send(demo.user, make_resume_message(str(robot), "go"))
    assert (code, body["status"]) == (403, "blocked"), body
    code, body = await send(demo.owner, make_resume_message(str(robot), "go"))
    assert (code, body["status"]) == (200, "ok"), body
    await wait_status(http, demo, lambda s: not s["estop"])

    # the SDK recomputes every audit id of the run
    lines = demo.audit.read_bytes().splitlines()
    assert len(lines) > 8
    for line in lines:
        entry = json.loads(line)
        unsigned = {k: v for k, v in entry.items() if k not in ("audit_id", "sig")}
        assert entry["audit_id"] == "sha256:" + hashlib.sha256(
            canonical_json(unsigned)).hexdigest(), entry["seq"]
