"""A stop takes back the simulated arm's trajectory, end to end: `rcan-rtps run --sim` (a real
subprocess), its arm commanded over REST (the USER's arm_joint, approved by the OWNER), then
stopped; the arm, as the bridge hears the sim's joint_states, stands still where it was (not
at the trajectory's target, nor anywhere else)."""

from __future__ import annotations

import asyncio
import json
from typing import Any

import aiohttp
import pytest
from waiting import eventually

from tests.interop.test_demo import Demo, call, wait_status

TARGET, DURATION_S = 2.0, 20.0  # 0.1 rad/s: far from the target when stopped


def elbow(status: dict[str, Any]) -> float | None:
    joints = status["telemetry"]["joints"]
    if not joints:
        return None
    return dict(zip(joints["names"], joints["positions"], strict=True)).get("elbow")


def elbow_at(least: float) -> Any:
    return lambda s: (elbow(s) or 0.0) > least


def audited(demo: Demo, event: str) -> list[dict[str, Any]]:
    return [e for e in map(json.loads, demo.audit.read_text().splitlines())
            if e["event"] == event]


async def arm_moving(http: aiohttp.ClientSession, sim: Demo) -> float:
    """The USER's long trajectory, approved; once the elbow is on its way: where it is."""
    await wait_status(http, sim, lambda s: s["ros"]["connected"] and elbow(s) is not None)
    code, held = await call(http, sim, sim.user, "POST", "/api/command", {
        "action": "arm_joint", "params": {"joints": ["elbow"], "positions": [TARGET],
                                          "duration_s": DURATION_S}})
    assert code == 202, held
    code, done = await call(http, sim, sim.owner, "POST", "/api/hitl/authorize",
                            {"pending_id": held["pending_id"]})
    assert (code, done["outcome"]) == (200, "executed"), done
    return elbow(await wait_status(http, sim, elbow_at(0.1))) or 0.0


async def stands_still(http: aiohttp.ClientSession, sim: Demo, near: float) -> None:
    """The elbow stopped near `near`, and stays there over the next 2 s of joint_states."""
    first = elbow(await wait_status(http, sim, lambda s: elbow_speed(s) == 0.0))
    assert first is not None and abs(first - near) < 0.3, (first, near)
    seen = []
    for _ in range(20):
        await asyncio.sleep(0.1)  # the sim publishes joint_states at 10 Hz
        seen.append(elbow(await wait_status(http, sim, lambda s: True)))
    assert seen == [first] * 20, (first, seen)


def elbow_speed(status: dict[str, Any]) -> float | None:
    joints = status["telemetry"]["joints"]
    if not joints or not joints["velocities"]:
        return None
    return dict(zip(joints["names"], joints["velocities"], strict=True)).get("elbow")


@pytest.mark.parametrize("stop", ["stop", "session_lost"])
async def test_a_stop_leaves_the_sims_arm_where_it_was(sim: Demo, stop: str) -> None:
    async with aiohttp.ClientSession() as http:
        at = await arm_moving(http, sim)
        if stop == "stop":
            code, body = await call(http, sim, sim.user, "POST", "/api/command",
                                    {"action": "stop"})
            assert (code, body["outcome"]) == (200, "executed"), body
        else:  # nobody attends the USER's session (5 s): its loss holds the arm
            await eventually(lambda: audited(sim, "NETWORK_LOSS_SAFE_STOP"), timeout=20,
                             what="the session-loss safe stop")
            at += 0.1 * 5.0
        await stands_still(http, sim, at)
