"""Navigation goals end in the audit log and show in STATUS (issue 11, item 4).

The robot side is a NavigateToPose server of our own on a second DDS participant whose
behaviour each goal's x picks: 1 succeeds, 2 aborts, 3 runs until cancelled (by `stop`).
Feedback carries a distance that shrinks and a recovery count that grows.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from waiting import eventually

from rcan_rtps.ros.actions import ServerGoal
from rcan_rtps.ros.rostime import duration_msg

from .bridge_rig import AGENT, OPS, Rig, bridge_config, navigation_rig

SUCCEED, ABORT, UNTIL_CANCELLED = 1.0, 2.0, 3.0


def _feedback(step: int) -> dict[str, Any]:
    left = max(0.0, 5.0 - 0.5 * step)
    return {"distance_remaining": left, "estimated_time_remaining": duration_msg(left / 0.5),
            "navigation_time": duration_msg(0.1 * step), "number_of_recoveries": step // 3}


async def _execute(goal: ServerGoal) -> dict[str, Any]:
    x = goal.goal.pose.pose.position.x
    for step in range(10_000):
        if goal.cancel_requested.is_set():
            goal.canceled()
            return {}
        goal.publish_feedback(_feedback(step))
        if x == SUCCEED and step == 5:
            return {}
        if x == ABORT and step == 5:
            goal.abort()
            return {"error_code": 101, "error_msg": "no valid path"}
        await asyncio.sleep(0.05)
    raise AssertionError("the goal was never cancelled")


MOTION = """\
motion:
  role_priorities: {USER: 10, OWNER: 50}
  locks: [{name: teleop, priority: 50}]
"""


@pytest.fixture
async def rig(tmp_path: Path, jazzy_python: Path, domain_id: int) -> AsyncIterator[Rig]:
    config = bridge_config(tmp_path, domain_id, extra=MOTION)
    async with navigation_rig(config, jazzy_python, domain_id, _execute) as rig:
        heartbeat = asyncio.create_task(_hold_session(rig))
        try:
            yield rig
        finally:
            heartbeat.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await heartbeat


async def _hold_session(rig: Rig) -> None:
    while True:  # the control sessions must outlive the goals
        rig.governor.heartbeat(AGENT)
        rig.governor.heartbeat(OPS)
        await asyncio.sleep(0.2)


async def _navigate(rig: Rig, x: float) -> tuple[str, str]:
    decision = await rig.command(AGENT, {"action": "navigate",
                                         "params": {"x": x, "y": 0.0, "yaw": 0.0}})
    assert decision.http_status == 200 and decision.goal_id, decision
    return decision.goal_id, decision.message_id or ""


def _has_feedback(rig: Rig, goal_id: str) -> bool:
    view = rig.goals.goal(goal_id) if rig.goals is not None else None
    return view is not None and view.feedback is not None


def _finished(rig: Rig, goal_id: str) -> dict[str, Any] | None:
    for entry in rig.entries():
        if entry["event"] == "GOAL_FINISHED" and entry["params"]["goal_id"] == goal_id:
            return entry
    return None


async def test_each_outcome_is_audited_once_and_linked_to_its_command(rig: Rig) -> None:
    # One at a time: a new goal of the same priority would replace the one running.
    sent = {}
    for x in (SUCCEED, ABORT, UNTIL_CANCELLED):
        sent[x] = await _navigate(rig, x)
        if x != UNTIL_CANCELLED:
            await eventually(lambda g=sent[x][0]: _finished(rig, g))
    cancel_id, _ = sent[UNTIL_CANCELLED]
    await eventually(lambda: _has_feedback(rig, cancel_id))
    stop = await rig.command(AGENT, {"action": "stop"})
    assert stop.http_status == 200, stop
    expected = {SUCCEED: "succeeded", ABORT: "aborted", UNTIL_CANCELLED: "canceled"}
    for x, (goal_id, message_id) in sent.items():
        entry = await eventually(lambda g=goal_id: _finished(rig, g),
                                 what=f"GOAL_FINISHED of {goal_id}")
        assert entry["outcome"] == expected[x], entry
        assert entry["message_id"] == message_id  # the navigate command that sent it
        assert entry["ros2_topic"] == "/robot1/navigate_to_pose"
    dispatched = {e["message_id"] for e in rig.entries() if e["event"] == "COMMAND_DISPATCHED"}
    assert {m for _, m in sent.values()} <= dispatched
    finished = [e for e in rig.entries() if e["event"] == "GOAL_FINISHED"]
    assert len(finished) == 3  # once per goal, however many updates followed


async def test_status_shows_the_active_goal_and_its_progress(rig: Rig) -> None:
    goal_id, _ = await _navigate(rig, UNTIL_CANCELLED)

    def progressed() -> Any:
        nav = rig.telemetry.status(pending_auth=0).navigation
        return nav if nav is not None and (nav.recoveries or 0) >= 1 else None

    nav = await eventually(progressed, what="navigation with a recovery in STATUS")
    assert nav.goal_id == goal_id and nav.state in ("accepted", "executing")
    assert nav.distance_remaining is not None and 0.0 <= nav.distance_remaining < 5.0
    assert nav.eta_s == pytest.approx(nav.distance_remaining / 0.5, abs=0.01)
    assert nav.navigation_time_s is not None and nav.navigation_time_s > 0
    assert (await rig.command(AGENT, {"action": "stop"})).http_status == 200
    await eventually(lambda: rig.telemetry.status(pending_auth=0).navigation is None,
                     what="no navigation once the goal is cancelled")


# -- one arbiter for the base (issue 23 item 3), with the server seeing each cancel ----------


async def test_a_new_goal_replaces_the_one_running(rig: Rig) -> None:
    first, _ = await _navigate(rig, UNTIL_CANCELLED)
    await eventually(lambda: _has_feedback(rig, first))
    second, _ = await _navigate(rig, UNTIL_CANCELLED)
    entry = await eventually(lambda: _finished(rig, first))
    assert (entry["outcome"], entry["deny_reason"]) == ("canceled", "replaced by agent")
    assert rig.goals is not None and rig.goals.active() == [second]
    assert (await rig.command(AGENT, {"action": "stop"})).http_status == 200


async def test_a_higher_lock_cancels_a_lower_goal_and_refuses_more(rig: Rig) -> None:
    """599eb3c: a higher-priority lock left a lower-priority goal driving (5/5)."""
    goal, _ = await _navigate(rig, UNTIL_CANCELLED)
    await eventually(lambda: _has_feedback(rig, goal))
    lock = await rig.command(OPS, {"action": "lock", "params": {"name": "teleop"}})
    assert lock.http_status == 200, lock
    entry = await eventually(lambda: _finished(rig, goal))
    assert (entry["outcome"], entry["deny_reason"]) == ("canceled",
                                                      "locked out by 'teleop' by ops")
    again = await rig.command(AGENT, {"action": "navigate",
                                      "params": {"x": UNTIL_CANCELLED, "y": 0.0, "yaw": 0.0}})
    assert (again.http_status, again.reason) == (409, "motion_locked")


async def test_nothing_lower_drives_beside_a_higher_goal(rig: Rig) -> None:
    """599eb3c: a lower navigate or move was accepted while a higher goal ran (5/5)."""
    high = await rig.command(OPS, {"action": "navigate",
                                   "params": {"x": UNTIL_CANCELLED, "y": 0.0, "yaw": 0.0}})
    assert high.http_status == 200 and high.goal_id, high
    for body in ({"action": "navigate", "params": {"x": 1.0, "y": 0.0, "yaw": 0.0}},
                 {"action": "move", "params": {"linear_x": 0.2}}):
        low = await rig.command(AGENT, body)
        assert (low.http_status, low.reason) == (409, "lower_priority"), low
    assert rig.goals is not None and rig.goals.active() == [high.goal_id]
    assert (await rig.command(OPS, {"action": "stop"})).http_status == 200
