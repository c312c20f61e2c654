"""Several arms (issue 11 item 5): each joint group on its own trajectory topic, multi-point
trajectories, and refusals that reach no topic. rclpy subscribes to both arms' topics.

The bridge makes an arm's writer with the arm's first command (issue 27: idle memory), so the
rclpy subscriptions are made before any writer of the bridge is there to match them: each
first trajectory below is sent on a writer made for it, and must arrive all the same."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from waiting import take

from .bridge_rig import AGENT, Rig, bridge_config, close_rig, make_rig

TRAJ = "trajectory_msgs/msg/JointTrajectory"
CMD_VEL, TWIST = "/robot1/cmd_vel", "geometry_msgs/msg/Twist"
LEFT, RIGHT = "/robot1/left_arm/joint_trajectory", "/robot1/right_arm/joint_trajectory"
ARMS = """\
arms:
  left: {topic: left_arm/joint_trajectory, joints: [l_shoulder, l_elbow]}
  right: {topic: right_arm/joint_trajectory, joints: [r_shoulder, r_elbow]}
"""


@pytest.fixture
async def rig(tmp_path: Path, jazzy_python: Path, domain_id: int) -> AsyncIterator[Rig]:
    rig = await make_rig(bridge_config(tmp_path, domain_id, extra_ros2=ARMS), jazzy_python,
                         domain_id)
    try:
        for topic in (LEFT, RIGHT):
            await rig.oracle.acall("subscribe", topic=topic, type=TRAJ)
        yield rig
    finally:
        await close_rig(rig)


async def test_each_arm_gets_its_own_multi_point_trajectory(rig: Rig) -> None:
    left = await rig.command(AGENT, {"action": "arm_joint", "params": {
        "group": "left", "joints": ["l_shoulder", "l_elbow"], "points": [
            {"positions": [0.1, 0.2], "time_from_start_s": 0.5},
            {"positions": [0.3, 0.4], "velocities": [0.0, 0.1], "time_from_start_s": 1.25},
            {"positions": [0.5, 0.6], "time_from_start_s": 2.0}]}})
    assert left.http_status == 200 and left.ros2_topic == LEFT, left
    right = await rig.command(AGENT, {"action": "arm_joint", "params": {
        "group": "right", "joints": ["r_elbow"], "positions": [-0.7], "duration_s": 1.0}})
    assert right.http_status == 200 and right.ros2_topic == RIGHT, right

    (on_left,) = await take(rig.oracle, LEFT)
    assert on_left["joint_names"] == ["l_shoulder", "l_elbow"]
    assert [p["positions"] for p in on_left["points"]] == [[0.1, 0.2], [0.3, 0.4], [0.5, 0.6]]
    assert [p["velocities"] for p in on_left["points"]] == [[], [0.0, 0.1], []]
    assert [p["time_from_start"] for p in on_left["points"]] == [
        {"sec": 0, "nanosec": 500_000_000}, {"sec": 1, "nanosec": 250_000_000},
        {"sec": 2, "nanosec": 0}]
    (on_right,) = await take(rig.oracle, RIGHT)
    assert on_right["joint_names"] == ["r_elbow"] and on_right["points"][0]["positions"] == [-0.7]
    audited = [e for e in rig.entries() if e["event"] == "COMMAND_DISPATCHED"]
    assert [(e["applied"]["group"], e["ros2_topic"]) for e in audited] == [
        ("left", LEFT), ("right", RIGHT)]


async def test_an_arms_writer_is_made_by_its_first_command(rig: Rig) -> None:
    # Once rclpy sees the bridge's cmd_vel writer it has seen every writer the bridge made at
    # start (they are announced in the order they were made, the arms' first).
    assert await rig.oracle.acall("wait_publishers", topic=CMD_VEL) == 1
    assert await rig.oracle.acall("publishers_info", topic=LEFT) == []
    assert await rig.oracle.acall("publishers_info", topic=RIGHT) == []
    # A stop publishes only on what was made at start: it makes no arm's writer.
    await rig.oracle.acall("subscribe", topic=CMD_VEL, type=TWIST)
    assert await rig.oracle.acall("wait_matched", topic=CMD_VEL) == 1
    stopped = await rig.command(AGENT, {"action": "stop"})
    assert stopped.http_status == 200, stopped
    await take(rig.oracle, CMD_VEL)  # the zero velocity is out
    assert await rig.oracle.acall("publishers_info", topic=LEFT) == []
    left = await rig.command(AGENT, {"action": "arm_joint", "params": {
        "group": "left", "joints": ["l_elbow"], "positions": [0.2], "duration_s": 1.0}})
    assert left.http_status == 200, left
    (first,) = await take(rig.oracle, LEFT)
    assert first["points"][0]["positions"] == [0.2]
    assert await rig.oracle.acall("wait_publishers", topic=LEFT) == 1
    assert await rig.oracle.acall("publishers_info", topic=RIGHT) == []  # not commanded yet


async def test_refusals_reach_no_arm(rig: Rig) -> None:
    refused = [
        {"joints": ["l_elbow"], "positions": [0.1], "duration_s": 1.0},  # which arm?
        {"group": "left", "joints": ["r_elbow"], "positions": [0.1], "duration_s": 1.0},
        {"group": "tail", "joints": ["t1"], "positions": [0.1], "duration_s": 1.0},
    ]
    for params in refused:
        decision = await rig.command(AGENT, {"action": "arm_joint", "params": params})
        assert decision.http_status == 409 and decision.reason == "joint_group_violation", \
            decision
    # the sentinel: one reliable, ordered writer per arm, so a refused trajectory that had
    # been published would have arrived before it
    for topic, group, joint in ((LEFT, "left", "l_elbow"), (RIGHT, "right", "r_elbow")):
        ok = await rig.command(AGENT, {"action": "arm_joint", "params": {
            "group": group, "joints": [joint], "positions": [0.9], "duration_s": 1.0}})
        assert ok.http_status == 200, ok
        (first,) = await take(rig.oracle, topic)
        assert first["points"][0]["positions"] == [0.9]
