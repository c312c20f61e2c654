"""A goal on its way to its server when a stop comes, through governor and bridge together.

A `stop` wins over it: the goal is cancelled and its command answered `stopped` (409), the
same answer as for a goal the governor cancels itself once accepted. A session loss of
another principal does not touch it: that principal's motion stops, the goal runs on.

The robot side: a NavigateToPose server of our own on a second DDS participant whose goals
run until cancelled, and an rclpy subscriber on cmd_vel (a stop's zero is matched at once, so
its server-wide cancel goes out while the goal is still being sent)."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from waiting import eventually

from rcan_rtps.governance import Decision
from rcan_rtps.ros.actions import ServerGoal

from .bridge_rig import AGENT, OPS, Rig, bridge_config, nav_tracker, navigation_rig

MOTION = """\
motion:
  role_priorities: {USER: 10, OWNER: 50}
"""
GOAL = {"action": "navigate", "params": {"x": 3.0, "y": 0.0, "yaw": 0.0}}


async def _until_cancelled(goal: ServerGoal) -> dict[str, Any]:
    while not goal.cancel_requested.is_set():
        await asyncio.sleep(0.05)
    goal.canceled()
    return {}


@pytest.fixture
async def rig(tmp_path: Path, jazzy_python: Path, domain_id: int) -> AsyncIterator[Rig]:
    config = bridge_config(tmp_path, domain_id, extra=MOTION)
    async with navigation_rig(config, jazzy_python, domain_id, _until_cancelled) as rig:
        await rig.oracle.acall("subscribe", topic="/robot1/cmd_vel",
                               type="geometry_msgs/msg/Twist")
        await rig.oracle.acall("wait_matched", topic="/robot1/cmd_vel")
        await eventually(lambda: rig.dispatcher.cmd_vel.matched_count() > 0,
                         what="cmd_vel matched")
        yield rig


def _when_sent(rig: Rig, then: Callable[[], Awaitable[Decision]]
               ) -> list[asyncio.Future[Decision]]:
    """The next goal's send, once under way (its request leaving), starts `then` beside it."""
    tracker = nav_tracker(rig)
    send, started = tracker.send, []

    async def sending(*args: Any, **kw: Any) -> str:
        tracker.send = send  # type: ignore[method-assign]
        goal = asyncio.ensure_future(send(*args, **kw))
        await asyncio.sleep(0)  # the goal is on its way
        started.append(asyncio.ensure_future(then()))
        return await goal

    tracker.send = sending  # type: ignore[method-assign]
    return started


async def test_a_stop_while_a_goal_is_sent_answers_it_stopped(rig: Rig) -> None:
    stopping = _when_sent(rig, lambda: rig.command(OPS, {"action": "stop"}))
    sent = await rig.command(AGENT, GOAL)
    [stop] = stopping
    assert (await stop).http_status == 200
    # Refused as the governor refuses a goal a stop came before: not a robot failure (503).
    assert (sent.http_status, sent.reason) == (409, "stopped"), sent
    view = nav_tracker(rig).goals()[-1]
    await eventually(lambda: view.state == "canceled", timeout=15,
                     what=f"goal {view.goal_id} cancelled (now {view.state})")
    [failed] = [e for e in rig.entries()
                if e["event"] == "COMMAND_FAILED" and e["message_id"] == sent.message_id]
    assert failed["deny_reason"].endswith(":stopped"), failed


async def test_a_session_loss_leaves_another_principals_goal_on_its_way_running(
        rig: Rig) -> None:
    first = await rig.command(AGENT, GOAL)  # AGENT drives: its goal holds a session
    assert first.http_status == 200 and first.goal_id, first
    losing = _when_sent(rig, lambda: rig.governor.safe_stop(AGENT, "no heartbeat for 1 s"))
    sent = await rig.command(OPS, GOAL)
    [lost] = losing
    assert (await lost).http_status == 200
    assert sent.http_status == 200 and sent.goal_id, sent  # OPS's goal was not stopped
    view = nav_tracker(rig).goal(sent.goal_id)
    assert view is not None
    await asyncio.sleep(1.0)  # a cancel would have reached it by now
    assert view.state not in ("canceled", "aborted"), view.state
    assert nav_tracker(rig).active() == [sent.goal_id]  # AGENT's goal ended (its own / replaced)
    # AGENT's own session may also run out meanwhile (it sends nothing more): one entry or
    # two, each a stop of AGENT's own motion only.
    scopes = [e["applied"]["scope"] for e in rig.entries()
              if e["event"] == "NETWORK_LOSS_SAFE_STOP"]
    assert scopes and set(scopes) == {"own"}, scopes
    await rig.command(OPS, {"action": "stop"})
    await eventually(lambda: not nav_tracker(rig).active(), timeout=15, what="stopped")


async def _heartbeats(rig: Rig, principal: Any) -> None:
    while True:  # well inside the rig's 1 s session timeout
        rig.governor.heartbeat(principal)
        await asyncio.sleep(0.2)


async def test_a_session_loss_cancels_the_lost_principals_own_goal_on_its_way(
        rig: Rig) -> None:
    """AGENT drives (a held move; it heartbeats) when OPS's connection closes while OPS's goal
    is on its way: OPS's motion alone stops. Its goal is cancelled on the server once accepted
    and answered `stopped`; AGENT's stream runs on. The goal used to be held once accepted,
    running after OPS was gone and, higher, ending AGENT's stream."""
    attended = asyncio.ensure_future(_heartbeats(rig, AGENT))
    try:
        moving = await rig.command(AGENT, {"action": "move", "params": {"linear_x": 0.1}})
        assert moving.http_status == 200, moving

        async def close_ops_connection() -> Decision:
            lost = await rig.governor.end_session(OPS)
            assert lost is not None, "OPS held a control session: its goal was being sent"
            return lost

        closing = _when_sent(rig, close_ops_connection)
        sent = await rig.command(OPS, GOAL)
        [closed] = closing
        assert (await closed).http_status == 200
        assert (sent.http_status, sent.reason) == (409, "stopped"), sent
        view = nav_tracker(rig).goals()[-1]
        await eventually(lambda: view.state == "canceled", timeout=15,
                         what=f"goal {view.goal_id} cancelled (now {view.state})")
        active = rig.governor.streams.active
        assert active is not None and active.owner == AGENT.name, active
        [entry] = [e for e in rig.entries() if e["event"] == "NETWORK_LOSS_SAFE_STOP"]
        assert (entry["principal"], entry["applied"]["scope"]) == (OPS.name, "own"), entry
    finally:
        attended.cancel()
    await rig.command(OPS, {"action": "stop"})
    await eventually(lambda: not nav_tracker(rig).active(), timeout=15, what="stopped")


@pytest.mark.parametrize("body", [{"action": "move", "params": {"linear_x": 0.3}}, GOAL],
                         ids=["move", "navigate"])
async def test_motion_waiting_for_its_entry_when_its_connection_closes_never_starts(
        rig: Rig, body: dict[str, Any]) -> None:
    """OPS's move or goal waits for its write-ahead entry (no session opened yet) when OPS's
    connection closes: it is refused `stopped`, and nothing of it reaches the robot — no
    Twist of the move on cmd_vel, no goal on the server. It used to start after the close."""
    release, entered = asyncio.Event(), asyncio.Event()
    write_ahead = rig.governor._steps.write_ahead

    async def held_write(entry: Any, *, urgent: bool = False) -> Any:
        if entry.action_type == body["action"]:
            entered.set()
            await release.wait()
        return await write_ahead(entry, urgent=urgent)

    rig.governor._steps.write_ahead = held_write  # type: ignore[method-assign]
    sending = asyncio.ensure_future(rig.command(OPS, body))
    try:
        await asyncio.wait_for(entered.wait(), timeout=15)
        lost = await rig.governor.end_session(OPS)
    finally:
        release.set()  # never left holding the entry: the rig's stop waits for it
    sent = await sending
    assert lost is not None and lost.http_status == 200, lost
    assert (sent.http_status, sent.reason) == (409, "stopped"), sent
    await rig.command(OPS, {"action": "stop"})  # a zero the robot's reader sees last
    twists: list[dict[str, Any]] = []
    await eventually(lambda: _took(rig, twists), timeout=15, what="the stop's zero")
    assert all(t["linear"]["x"] == 0.0 for t in twists), twists
    assert nav_tracker(rig).goals() == []
    [entry] = [e for e in rig.entries() if e["event"] == "NETWORK_LOSS_SAFE_STOP"]
    assert entry["applied"]["before_session"] is True, entry


async def _took(rig: Rig, into: list[dict[str, Any]]) -> bool:
    into += await rig.oracle.acall("take", topic="/robot1/cmd_vel")
    return bool(into)


@pytest.fixture
async def readerless_rig(tmp_path: Path, jazzy_python: Path, domain_id: int
                         ) -> AsyncIterator[Rig]:
    """Nothing reads cmd_vel (a robot driven by its own planner's topic), and a topic may take
    a minute to match (`match_timeout_s: 60`)."""
    config = bridge_config(tmp_path, domain_id, extra=MOTION,
                           extra_ros2="match_timeout_s: 60.0\n")
    async with navigation_rig(config, jazzy_python, domain_id, _until_cancelled) as rig:
        yield rig


@pytest.mark.parametrize("action", ["stop", "estop"])
async def test_a_stop_cancels_goals_without_waiting_for_cmd_vel_to_match(
        readerless_rig: Rig, action: str) -> None:
    # The stop waits (up to match_timeout_s) to know whether its zero reached anyone; the
    # goal cancels go out beside that wait, never after it (before: a minute here).
    rig = readerless_rig
    sent = await rig.command(AGENT, GOAL)
    assert sent.http_status == 200, sent
    view = nav_tracker(rig).goals()[-1]
    stopping = asyncio.create_task(rig.command(AGENT, {"action": action}))

    def cancelled() -> bool:  # attended: no session-loss halt cancels it instead
        rig.governor.heartbeat(AGENT)
        return view.state == "canceled"

    try:
        await eventually(cancelled, what=f"goal {view.goal_id} cancelled (now {view.state})")
    finally:  # the robot reads them now: the stop's waits end
        await rig.oracle.acall("subscribe", topic="/robot1/cmd_vel",
                               type="geometry_msgs/msg/Twist")
        await rig.oracle.acall("subscribe", topic="/robot1/emergency_stop",
                               type="std_msgs/msg/Bool", qos="transient_local")
        await asyncio.wait_for(stopping, 30.0)
