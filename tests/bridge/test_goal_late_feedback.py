"""The bridge's goal tracker shows a goal's end as soon as its result is in, while the goal's
feedback stream still waits for samples the server may have to send again
(docs/design/zero-loss.md): the wait must not hold the end back."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from dropping import flood, small_buffers
from waiting import eventually

from rcan_rtps.bridge.navigation import GoalTracker
from rcan_rtps.ros import action_goals
from rcan_rtps.ros.actions import ActionServer, ServerGoal
from rcan_rtps.ros.participant import RosNode

NAV = "nav2_msgs/action/NavigateToPose"
GOAL = {"pose": {"header": {"frame_id": "map"}, "pose": {"position": {"x": 1.0}}},
        "behavior_tree": ""}


async def test_a_goal_s_end_is_shown_while_its_feedback_waits_for_a_repair(
        domain_id: int, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(action_goals, "REPAIR_S", dict.fromkeys(action_goals.REPAIR_S, 60.0))
    small_buffers(monkeypatch)
    go = asyncio.Event()

    async def execute(goal: ServerGoal) -> dict[str, Any]:
        await go.wait()
        goal.publish_feedback({"distance_remaining": 0.5})
        return {"error_code": 0, "error_msg": ""}

    with RosNode("robot_sim", "/robot1", domain_id=domain_id, distro="jazzy") as robot, \
            RosNode("rcan_bridge", "/", domain_id=domain_id, distro="jazzy") as bridge:
        server = ActionServer(robot, "navigate_to_pose", NAV, execute)
        tracker = GoalTracker(bridge, "/robot1/navigate_to_pose")
        goal_id = await tracker.send(GOAL, timeout=20)
        flood(bridge)  # after the goal was sent: its feedback may be owed
        go.set()
        await eventually(lambda: (v := tracker.goal(goal_id)) is not None
                         and v.state == "succeeded")
        assert tracker._sent is not None
        assert any(not task.done() for task in tracker._sent._watchers), \
            "the feedback stream was expected to be waiting out the repair time"
        await tracker.close()
        await server.close()
