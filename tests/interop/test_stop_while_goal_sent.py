"""A stop that comes while a goal is still being sent — the first goal above all, which
loads the goal side, parses the action and makes and matches its services first — must
still stop it: the server-wide cancel may reach the server before the goal does (a server
cancels only the goals it has), so the goal that was on its way is cancelled once accepted
and its command refused. Real peer: an rclpy Jazzy Fibonacci server (Fast DDS) whose goals
run until cancelled."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest
from oracle.client import OracleEnv, RclpyOracle
from waiting import eventually

from rcan_rtps.bridge.navigation import GoalTracker
from rcan_rtps.ros.errors import ActionError
from rcan_rtps.ros.participant import RosNode

FIB = "test_msgs/action/Fibonacci"
ENDLESS = {"order": 400}  # slow mode: 0.2 s a step, until cancelled


@pytest.fixture
def oracle(jazzy_oracle: OracleEnv, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_oracle, "fib_server", "/", domain_id=domain_id) as agent:
        yield agent


@pytest.fixture
async def node(domain_id: int, jazzy_share: Path) -> AsyncIterator[RosNode]:
    with RosNode("rcan_stop_race", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as n:
        yield n


def _goal_requests_written(tracker: GoalTracker) -> int:
    sender = tracker.client._sending
    return 0 if sender is None else sum(p.written for p in sender._send._pairs.values())


async def _stop_after(tracker: GoalTracker, turns: int) -> None:
    """Sends a goal and stops after `turns` turns of the loop, or as soon as its request is
    written if that comes first (a later goal can be accepted within ten turns): the goal is
    on its way, and the send is refused and the goal (the tracker's newest) ends cancelled,
    not running on."""
    written = _goal_requests_written(tracker)
    sending = asyncio.create_task(tracker.send(ENDLESS, timeout=20))
    for _ in range(turns):
        await asyncio.sleep(0)
        if _goal_requests_written(tracker) > written:
            break
    assert not sending.done()
    await tracker.cancel_all()  # the stop
    with pytest.raises(ActionError, match="a stop came while the goal was being sent"):
        await sending
    view = tracker.goals()[-1]
    await eventually(lambda: view.state == "canceled", timeout=15,
                     what=f"goal {view.goal_id} cancelled (now {view.state})")


@pytest.mark.parametrize("turns", [1, 3, 10, 40])
async def test_a_stop_while_the_first_goal_is_sent_cancels_that_goal(
        oracle: RclpyOracle, node: RosNode, turns: int) -> None:
    await oracle.acall("action_server", name="/fib", mode="slow")
    tracker = GoalTracker(node, "/fib", FIB)
    try:
        tracker.keep_cancel_ready(period=0.05)  # as the bridge does at start
        await eventually(lambda: tracker.cancel_ready, timeout=20, what="cancel client ready")
        await _stop_after(tracker, turns)  # the first goal: goal side made meanwhile
        await _stop_after(tracker, turns)  # and a later one
        assert not tracker.active()
        # a goal sent after the stop is not touched by it
        goal_id = await tracker.send(ENDLESS, timeout=20)
        await asyncio.sleep(0.5)
        assert tracker.active() == [goal_id]
        await tracker.cancel_all()
        await eventually(lambda: not tracker.active(), timeout=15, what="stopped")
    finally:
        await tracker.close()
