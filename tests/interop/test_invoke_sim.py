"""Issue 24: INVOKE / INVOKE_CANCEL (§19) and AUTHORIZE (§16.4) against a real `run --sim`.

The demo config declares skills (`bridge.skills`: go_home, go_to, nudge, raise_elbow,
hold_still); the simulated robot is a real ROS 2 node, so a skill's goal is a real
NavigateToPose goal whose end answers the INVOKE. Message shapes: tests/data/rcan-spec/
(SOURCE.md). A client that waits for a goal heartbeats, as every client of a goal does (the
demo's session_timeout_s is 5 s).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from waiting import eventually

from tests.interop.test_demo import Demo, call, wait_status

DATA = Path(__file__).parents[1] / "data" / "rcan-spec"
PROSE = json.loads((DATA / "section-19-examples.json").read_text())


@pytest.fixture
async def http() -> AsyncIterator[aiohttp.ClientSession]:
    async with aiohttp.ClientSession() as client:
        yield client


@contextlib.asynccontextmanager
async def heartbeating(http: aiohttp.ClientSession, demo: Demo) -> AsyncIterator[None]:
    async def beat() -> None:
        while True:
            await call(http, demo, demo.user, "POST", "/api/heartbeat")
            await asyncio.sleep(1.0)

    task = asyncio.create_task(beat())
    try:
        yield
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


def entries(demo: Demo) -> list[dict[str, Any]]:
    return [json.loads(line) for line in demo.audit.read_text().splitlines()]


async def send(http: aiohttp.ClientSession, demo: Demo, token: str,
               body: dict[str, Any]) -> tuple[int, Any]:
    return await call(http, demo, token, "POST", "/api/command", body)


async def test_an_invoke_drives_the_simulator_and_answers_at_the_goals_end(
        sim: Demo, http: aiohttp.ClientSession) -> None:
    demo = sim
    await wait_status(http, demo, lambda s: s["ros"]["connected"])
    invoke = {"type": "INVOKE", "skill": "go_to", "params": {"x": 1.0, "y": 0.0, "yaw": 0.0},
              "timeout_ms": 60_000, "msg_id": "inv-go-to"}
    async with heartbeating(http, demo):
        code, body = await send(http, demo, demo.user, invoke)
    assert (code, body["type"], body["status"], body["reply_to"]) == (
        200, "INVOKE_RESULT", "success", "inv-go-to"), body
    goal = body["goal_id"]
    _, view = await call(http, demo, demo.user, "GET", f"/api/goals/{goal}")
    assert view["state"] == "succeeded", view  # answered once the goal had ended
    x = (await wait_status(http, demo, lambda s: True))["telemetry"]["position"]["x"]
    assert abs(x - 1.0) < 0.3, x
    log = entries(demo)
    sent = [e for e in log if e["message_id"] == "inv-go-to" and
            e["event"] == "COMMAND_DISPATCHED"]
    assert [(e["action_type"], e["rcan"]["skill"]) for e in sent] == [("navigate", "go_to")]
    assert [e["outcome"] for e in log if e["event"] == "GOAL_FINISHED"] == ["succeeded"]

    # undeclared: refused, and audited
    code, body = await send(http, demo, demo.user, PROSE["invokeMessage"])
    assert (code, body["status"], body["error"]["name"]) == (404, "not_found",
                                                             "SkillNotFound"), body


async def test_invoke_cancel_stops_a_running_skill(sim: Demo,
                                                   http: aiohttp.ClientSession) -> None:
    demo = sim
    await wait_status(http, demo, lambda s: s["ros"]["connected"])
    far = {"type": "INVOKE", "skill": "go_to", "params": {"x": 15.0, "y": 0.0, "yaw": 0.0},
           "msg_id": "inv-far"}
    cancel = json.loads(json.dumps(PROSE["invokeCancel"]))
    cancel["payload"]["msg_id"] = "inv-far"
    async with heartbeating(http, demo):
        invoked = asyncio.create_task(send(http, demo, demo.user, far))
        await wait_status(http, demo, lambda s: s["navigation"] is not None and
                          s["telemetry"]["velocity"]["linear_x"] > 0.05)
        code, body = await send(http, demo, demo.user, cancel)
        assert (code, body["status"], body["reply_to"]) == (200, "cancelled", "inv-far"), body
        code, body = await asyncio.wait_for(invoked, 30)
    assert (code, body["status"], body["error"]["code"]) == (200, "cancelled", 7007), body
    _, view = await call(http, demo, demo.user, "GET", f"/api/goals/{body['goal_id']}")
    assert view["state"] == "canceled", view
    log = entries(demo)
    cancels = [e for e in log if e.get("action_type") == "cancel_goal"]
    assert [(e["principal"], e["params"]["goal_id"]) for e in cancels] == [
        ("operator", body["goal_id"])]
    finished = [e for e in log if e["event"] == "GOAL_FINISHED"]
    assert [e["outcome"] for e in finished] == ["canceled"]
    assert "INVOKE_CANCEL by operator" in finished[0]["deny_reason"]


async def test_authorize_approves_a_held_skill_and_the_websocket_speaks_both(
        sim: Demo, http: aiohttp.ClientSession) -> None:
    demo = sim
    status = await wait_status(http, demo, lambda s: s["ros"]["connected"])
    code, held = await send(http, demo, demo.user, {"type": "INVOKE", "skill": "raise_elbow",
                                                    "msg_id": "inv-arm"})
    assert (code, held["status"], held["msg_id"]) == (202, "pending", "inv-arm"), held
    example = json.loads((DATA / "authorize.json").read_text())["examples"][0]
    authorize = {**example, "message_type": 45, "ruri": status["ruri"],
                 "pending_id": held["pending_id"]}
    del authorize["thought_id"], authorize["principal_id"]
    code, body = await send(http, demo, demo.user, authorize)  # USER: not an approver
    assert (code, body["status"]) == (403, "blocked"), body
    code, body = await send(http, demo, demo.owner, authorize)
    assert (code, body["outcome"], body["status"]) == (200, "executed", "ok"), body
    approved = [e for e in entries(demo) if e["event"] == "HITL_AUTHORIZED"]
    assert approved[0]["approvals"][0]["message_id"] == example["message_id"]

    async with http.ws_connect(demo.url + "/api/ws",
                               headers={"Authorization": f"Bearer {demo.user}"}) as ws:
        await ws.send_str(json.dumps({"message_type": 11, "skill_id": "nudge",
                                      "params": {"duration_s": 0.5}, "msg_id": "inv-ws"}))

        async def outcome() -> dict[str, Any] | None:
            msg = await ws.receive(timeout=10)
            frame: dict[str, Any] = json.loads(msg.data)
            return frame if frame["type"] == "outcome" else None

        frame = await eventually(outcome, timeout=20, what="the INVOKE's outcome frame")
    assert (frame["http_status"], frame["body"]["status"], frame["body"]["reply_to"]) == (
        200, "success", "inv-ws"), frame
