"""Spec §10 MUSTs on the ROS side, against a real rclpy Jazzy robot node (on Fast DDS; the
representative cases on Cyclone DDS too).

Governor → dispatcher → DDS → rclpy, and rclpy telemetry → STATUS. (The HTTP edge has its
own tests; here the governor is called directly, as the API does.)
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from oracle.client import OracleEnv, both_rmws
from waiting import eventually, take

from rcan_rtps.bridge.notify import REPEAT_S
from rcan_rtps.governance import verify

from .bridge_rig import AGENT, OPS, VIEWER, Rig, bridge_config, close_rig, make_rig

TWIST = "geometry_msgs/msg/Twist"
CMD_VEL = "/robot1/cmd_vel"
SENTINEL_X = 0.125  # a move no test sends otherwise


def xs(twists: list[Any]) -> list[float]:
    return [float(t["linear"]["x"]) for t in twists]


async def before_sentinel(rig: Rig) -> list[float]:
    """The linear_x of every Twist rclpy got before a sentinel move sent now.

    cmd_vel is one reliable writer matched with a reliable reader, so samples arrive in the
    order they were written: once the sentinel is in, anything written before it is in too.
    """
    sentinel = await rig.command(AGENT, {"action": "move", "params": {"linear_x": SENTINEL_X}})
    assert sentinel.http_status == 200, sentinel
    got = xs(await take(rig.oracle, CMD_VEL, until=lambda got: SENTINEL_X in xs(got)))
    return got[:got.index(SENTINEL_X)]


@pytest.fixture
async def rig(tmp_path: Path, jazzy_oracle: OracleEnv, domain_id: int) -> AsyncIterator[Rig]:
    r = await make_rig(bridge_config(tmp_path, domain_id), jazzy_oracle, domain_id)
    yield r
    await close_rig(r)


async def subscribe(rig: Rig, topic: str, type_name: str, qos: str = "default") -> None:
    """An rclpy subscription, matched with the bridge's writer before anything is sent."""
    await rig.oracle.acall("subscribe", topic=topic, type=type_name, qos=qos)
    assert await rig.oracle.acall("wait_matched", topic=topic) >= 1


@both_rmws
async def test_rbac_before_publish(rig: Rig) -> None:
    await subscribe(rig, "/robot1/cmd_vel", TWIST)
    await rig.dispatcher.cmd_vel.wait_for_subscribers(1, timeout=15)
    decision = await rig.command(VIEWER, {"action": "move", "params": {"linear_x": 0.25}})
    assert decision.http_status == 403 and decision.error_code.value == "INSUFFICIENT_PRIVILEGES"
    # The agent's move is the sentinel: one ordered, reliable writer, so the denied move,
    # had it been published, would have arrived first.
    ok = await rig.command(AGENT, {"action": "move", "params": {"linear_x": 0.5}})
    assert ok.http_status == 200
    got = await take(rig.oracle, CMD_VEL, until=lambda got: 0.5 in xs(got))
    assert got[0]["linear"]["x"] == 0.5


async def test_clamp_within_ten_percent_and_deny_beyond(rig: Rig) -> None:
    await subscribe(rig, "/robot1/cmd_vel", TWIST)
    clamped = await rig.command(AGENT, {"action": "move",
                                        "params": {"linear_x": 1.6, "angular_z": -1.05}})
    assert clamped.http_status == 200 and clamped.applied is not None
    assert {k: clamped.applied[k] for k in ("linear_x", "linear_y", "angular_z")} == {
        "linear_x": 1.5, "linear_y": 0.0, "angular_z": -1.0}
    got = await take(rig.oracle, CMD_VEL)
    assert got[0]["linear"]["x"] == 1.5 and got[0]["angular"]["z"] == -1.0
    denied = await rig.command(AGENT, {"action": "move", "params": {"linear_x": 1.7}})
    assert denied.http_status == 409 and denied.outcome.value == "safety_violation"
    last = rig.entries()[-1]  # read before the sentinel move adds its own entry
    assert last["outcome"] == "safety_violation"
    assert last["deny_reason"] == "COMMAND_REJECTED:velocity_limit"
    # Only the held 1.5 m/s stream and the session-loss halt (zero) may follow; never the
    # denied 1.7 m/s.
    assert set(await before_sentinel(rig)) <= {1.5, 0.0}


async def test_arm_joint_becomes_a_joint_trajectory(rig: Rig) -> None:
    topic = "/robot1/joint_trajectory_controller/joint_trajectory"
    # Not `subscribe`: the bridge makes this writer with the first arm command (issue 27).
    await rig.oracle.acall("subscribe", topic=topic, type="trajectory_msgs/msg/JointTrajectory")
    # Where the arm is (a trajectory no stop could take back is not sent).
    await rig.oracle.acall("publisher", topic="/robot1/joint_states",
                           type="sensor_msgs/msg/JointState")
    await rig.oracle.acall("publish_periodic", topic="/robot1/joint_states",
                           type="sensor_msgs/msg/JointState", rate=50.0,
                           value={"name": ["shoulder", "elbow"], "position": [0.0, 0.0],
                                  "velocity": [0.0, 0.0]})
    decision = await rig.command(AGENT, {"action": "arm_joint", "params": {
        "joints": ["shoulder", "elbow"], "positions": [0.5, -1.25], "duration_s": 2.5}})
    assert decision.http_status == 200, decision
    traj = (await take(rig.oracle, topic))[0]
    assert traj["joint_names"] == ["shoulder", "elbow"]
    assert traj["points"][0]["positions"] == [0.5, -1.25]
    assert traj["points"][0]["time_from_start"] == {"sec": 2, "nanosec": 500_000_000}


@both_rmws
async def test_estop_latches_and_only_owner_clears(rig: Rig) -> None:
    await subscribe(rig, "/robot1/emergency_stop", "std_msgs/msg/Bool")
    await subscribe(rig, "/robot1/cmd_vel", TWIST)
    estop = await rig.command(VIEWER, {"action": "estop"})
    assert estop.http_status == 200
    await take(rig.oracle, "/robot1/emergency_stop", until=lambda got: {"data": True} in got)
    assert rig.telemetry.status(pending_auth=0).state == "estop"
    moved = await rig.command(AGENT, {"action": "move", "params": {"linear_x": 0.1}})
    assert moved.http_status == 409 and moved.reason == "estop_active"
    refused = await rig.command(AGENT, {"action": "clear_estop"})
    assert refused.http_status == 403
    cleared = await rig.command(OPS, {"action": "clear_estop"})
    assert cleared.http_status == 200
    await take(rig.oracle, "/robot1/emergency_stop", until=lambda got: {"data": False} in got)
    assert (await rig.command(AGENT, {"action": "move",
                                      "params": {"linear_x": 0.1}})).http_status == 200


async def test_the_configured_command_topics_are_the_ones_used(tmp_path: Path,
                                                              jazzy_python: Path,
                                                              domain_id: int) -> None:
    """Spec §4 (e-stop: "topic name configurable") and §5 (`cmd_vel_topic`, `estop_topic`):
    an e-stop on a topic the robot does not listen on would stop nothing. A relative name
    resolves in the namespace, an absolute one does not (profile, Config)."""
    config = bridge_config(tmp_path, domain_id, extra_ros2=(
        "cmd_vel_topic: base/cmd_vel\nestop_topic: /safety/estop\n"
        "joint_trajectory_topic: arm/trajectory\njoint_states_topic: arm/joint_states"))
    rig = await make_rig(config, jazzy_python, domain_id)
    try:
        await subscribe(rig, "/robot1/base/cmd_vel", TWIST)
        await subscribe(rig, "/safety/estop", "std_msgs/msg/Bool")
        moved = await rig.command(AGENT, {"action": "move", "params": {"linear_x": 0.2}})
        assert moved.http_status == 200, moved
        assert (await take(rig.oracle, "/robot1/base/cmd_vel"))[0]["linear"]["x"] == 0.2
        # The arm: sent only where its joints are heard, on the configured joint_states.
        trajectory, states = "/robot1/arm/trajectory", "/robot1/arm/joint_states"
        await rig.oracle.acall("subscribe", topic=trajectory,
                               type="trajectory_msgs/msg/JointTrajectory")
        await rig.oracle.acall("publisher", topic=states, type="sensor_msgs/msg/JointState")
        await rig.oracle.acall("publish_periodic", topic=states,
                               type="sensor_msgs/msg/JointState", rate=50.0,
                               value={"name": ["elbow"], "position": [0.0], "velocity": [0.0]})
        arm = await rig.command(AGENT, {"action": "arm_joint", "params": {
            "joints": ["elbow"], "positions": [0.5], "duration_s": 1.0}})
        assert arm.http_status == 200, arm
        assert (await take(rig.oracle, trajectory))[0]["joint_names"] == ["elbow"]
        assert (await rig.command(VIEWER, {"action": "estop"})).http_status == 200
        await take(rig.oracle, "/safety/estop", until=lambda got: {"data": True} in got)
        assert rig.entries()[-1]["ros2_topic"] == "/safety/estop"
    finally:
        await close_rig(rig)


async def test_the_configured_telemetry_topics_are_the_ones_read(tmp_path: Path,
                                                                jazzy_python: Path,
                                                                domain_id: int) -> None:
    """Spec §5 `odom_topic`, `diagnostics_topic` (an ERROR there is a fault), profile
    `battery_topic`: STATUS reads the topics the config names, not the defaults."""
    topics = {"odom": ("/robot1/base/odom", "nav_msgs/msg/Odometry"),
              "diagnostics": ("/robot1/health", "diagnostic_msgs/msg/DiagnosticArray"),
              "battery": ("/power/battery", "sensor_msgs/msg/BatteryState")}
    config = bridge_config(tmp_path, domain_id, extra_ros2=(
        "odom_topic: base/odom\ndiagnostics_topic: health\nbattery_topic: /power/battery"))
    rig = await make_rig(config, jazzy_python, domain_id)
    try:
        for topic, type_name in topics.values():
            await rig.oracle.acall("publisher", topic=topic, type=type_name)
        published = {topic for topic, _ in topics.values()}
        read = [s for s in rig.telemetry.subscriptions if s.topic in published]
        assert len(read) == len(published)  # the bridge reads exactly the configured names
        for subscription in read:
            await subscription.wait_for_publishers(1, timeout=15)
        odom = {"pose": {"pose": {"position": {"x": 2.5}, "orientation": {"w": 1.0}}}}
        await rig.oracle.acall("publish", topic=topics["odom"][0], type=topics["odom"][1],
                               value=odom, count=3)
        await rig.oracle.acall("publish", topic=topics["battery"][0],
                               type=topics["battery"][1], value={"percentage": 0.5}, count=3)
        await rig.oracle.acall("publish", topic=topics["diagnostics"][0],
                               type=topics["diagnostics"][1],
                               value={"status": [{"level": 2, "name": "motor",
                                                  "message": "overheat"}]}, count=3)

        def all_heard() -> bool:
            status = rig.telemetry.status(pending_auth=0)
            position = status.telemetry.position
            return (status.state == "fault" and status.battery_pct is not None
                    and position is not None and position.x == 2.5)

        await eventually(all_heard, timeout=15)
        status = rig.telemetry.status(pending_auth=0)
        assert status.battery_pct is not None and abs(status.battery_pct - 50.0) < 1e-4
    finally:
        await close_rig(rig)


async def test_no_subscriber_is_robot_unavailable(rig: Rig) -> None:
    decision = await rig.command(AGENT, {"action": "move", "params": {"linear_x": 0.1}})
    assert decision.http_status == 503 and decision.error_code.value == "ROBOT_UNAVAILABLE"
    assert rig.entries()[-1]["outcome"] == "failed"


async def test_every_command_is_audited_with_ai_identity(rig: Rig) -> None:
    await subscribe(rig, "/robot1/cmd_vel", TWIST)
    await rig.command(AGENT, {"action": "move", "params": {"linear_x": 0.2},
                              "ai_provider": "anthropic", "ai_model": "claude",
                              "confidence": 0.91, "thought_id": "th-42"})
    await rig.command(AGENT, {"action": "move", "params": {"linear_x": 9.0},
                              "ai_provider": "anthropic", "ai_model": "claude",
                              "confidence": 0.91, "thought_id": "th-43"})
    decisive = [e for e in rig.entries() if e.get("action_type") == "move"]
    assert [e["outcome"] for e in decisive] == ["executed", "safety_violation"]
    for entry, thought in zip(decisive, ("th-42", "th-43"), strict=True):
        assert entry["ai"] == {"provider": "anthropic", "model": "claude", "confidence": 0.91,
                               "thought_id": thought}
        assert entry["bridge"] == "ros2"
    assert decisive[0]["ros2_topic"] == "/robot1/cmd_vel"
    verify(rig.audit_path)


@both_rmws
async def test_session_loss_publishes_zero_twist(rig: Rig) -> None:
    await subscribe(rig, "/robot1/cmd_vel", TWIST)
    await rig.command(AGENT, {"action": "move", "params": {"linear_x": 0.4}})
    # No heartbeat: after session_timeout_s (1 s) the governor must halt the robot.
    # The held move streams until then.
    seen = await take(rig.oracle, CMD_VEL, until=lambda got: 0.0 in xs(got), timeout=10)
    zero = xs(seen).index(0.0)
    assert set(xs(seen)[:zero]) == {0.4} and seen[zero]["angular"]["z"] == 0.0
    # The zero goes first (a stop never waits for the disk); its entry and STATUS follow.
    await eventually(lambda: any(e["event"] == "NETWORK_LOSS_SAFE_STOP" for e in rig.entries()))
    await eventually(lambda: rig.telemetry.safe_stopped)


async def test_heartbeat_keeps_the_session(rig: Rig) -> None:
    await subscribe(rig, "/robot1/cmd_vel", TWIST)

    async def heartbeats() -> None:  # a client that stays heard from, from its command on
        while True:
            rig.governor.heartbeat(AGENT)
            await asyncio.sleep(0.25)

    await rig.command(AGENT, {"action": "move", "params": {"linear_x": 0.4}})
    beating = asyncio.create_task(heartbeats())
    try:
        assert (await take(rig.oracle, CMD_VEL))[0]["linear"]["x"] == 0.4
        await asyncio.sleep(2.0)  # the time under test: twice the session timeout
        # No halt was published meanwhile: only the held stream arrived before a sentinel.
        assert set(await before_sentinel(rig)) == {0.4}
        assert not any(e["event"] == "NETWORK_LOSS_SAFE_STOP" for e in rig.entries())
    finally:
        beating.cancel()


async def test_pending_auth_publishes_a_warn_diagnostic(tmp_path: Path, jazzy_python: Path,
                                                        domain_id: int) -> None:
    config = bridge_config(tmp_path, domain_id, extra=(
        "hitl:\n  gates:\n    - {action: arm_joint, require_auth: true}\n"))
    rig = await make_rig(config, jazzy_python, domain_id)
    try:
        await subscribe(rig, "/robot1/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
        assert rig.notifier is not None  # both ends matched: the warning is sent only once
        await rig.notifier.publisher.wait_for_subscribers(1, timeout=15)
        held = await rig.command(AGENT, {"action": "arm_joint", "params": {
            "joints": ["j1"], "positions": [0.1], "duration_s": 1.0}})
        assert held.http_status == 202 and held.pending_id
        diag = (await take(rig.oracle, "/robot1/diagnostics"))[0]["status"][0]
        assert diag["level"] == 1 and "awaits human approval" in diag["message"]
        assert {"key": "pending_id", "value": held.pending_id} in diag["values"]
        # Repeated while it waits (as ROS diagnostics are): a late monitor sees it too.
        again = (await take(rig.oracle, "/robot1/diagnostics"))[-1]["status"][0]
        assert again["level"] == 1 and again["values"] == diag["values"]
        denied = await rig.governor.deny(held.pending_id, OPS)
        assert denied.http_status == 200, denied
        last = await take(rig.oracle, "/robot1/diagnostics",
                          until=lambda got: bool(got) and got[-1]["status"][0]["level"] == 0)
        assert last[-1]["status"][0]["message"] == "no command awaits human approval"
        await asyncio.sleep(2 * REPEAT_S)  # no WARN after the OK
        assert await rig.oracle.acall("take", topic="/robot1/diagnostics") == []
    finally:
        await close_rig(rig)


@both_rmws
async def test_telemetry_becomes_status(rig: Rig) -> None:
    odom = {"header": {"frame_id": "odom"}, "child_frame_id": "base_link",
            "pose": {"pose": {"position": {"x": 1.5, "y": -2.0, "z": 0.0},
                              "orientation": {"x": 0.0, "y": 0.0,
                                              "z": math.sin(0.25), "w": math.cos(0.25)}}},
            "twist": {"twist": {"linear": {"x": 0.3}, "angular": {"z": 0.1}}}}
    for topic, type_name in (("/robot1/odom", "nav_msgs/msg/Odometry"),
                             ("/robot1/joint_states", "sensor_msgs/msg/JointState"),
                             ("/robot1/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"),
                             ("/robot1/battery_state", "sensor_msgs/msg/BatteryState")):
        await rig.oracle.acall("publisher", topic=topic, type=type_name)
    for subscription in rig.telemetry.subscriptions:  # both ends matched before publishing
        await subscription.wait_for_publishers(1, timeout=15)
    await asyncio.sleep(0.2)
    await rig.oracle.acall("publish", topic="/robot1/odom", type="nav_msgs/msg/Odometry",
                           value=odom, count=3)
    await rig.oracle.acall("publish", topic="/robot1/joint_states",
                           type="sensor_msgs/msg/JointState",
                           value={"name": ["left", "right"], "position": [0.1, 0.2],
                                  "velocity": [1.0, 1.0]}, count=3)
    await rig.oracle.acall("publish", topic="/robot1/battery_state",
                           type="sensor_msgs/msg/BatteryState",
                           value={"percentage": 0.8, "voltage": 14.2}, count=3)
    await eventually(lambda: rig.telemetry.status(pending_auth=0).battery_pct is not None)
    status = rig.telemetry.status(pending_auth=2)
    assert status.state == "moving" and status.pending_auth == 2
    assert status.telemetry.position.x == 1.5 and status.telemetry.position.y == -2.0
    assert abs(status.telemetry.yaw - 0.5) < 1e-9
    assert status.telemetry.velocity.linear_x == 0.3
    assert status.telemetry.joints.names == ["left", "right"]
    assert abs(status.battery_pct - 80.0) < 1e-4
    assert status.ros.connected and status.ros.domain_id == rig.node.domain_id
    # RCAN §20's names beside the profile's (issue 24)
    assert status.battery_percent == status.battery_pct
    assert status.battery_v is not None and abs(status.battery_v - 14.2) < 1e-4
    assert status.position is not None and (status.position.x, status.position.y) == (1.5, -2.0)
    assert status.position.heading_rad is not None
    assert abs(status.position.heading_rad - 0.5) < 1e-9
    later = rig.telemetry.status(pending_auth=0)
    assert status.seq is not None and later.seq is not None and later.seq > status.seq
    assert status.timestamp_us is not None and later.timestamp_us is not None
    assert later.timestamp_us > status.timestamp_us
    assert status.timestamp_us // 1000 == status.timestamp_ms
    assert status.uptime_ms is not None and status.uptime_ms >= 0

    await rig.oracle.acall("publish", topic="/robot1/diagnostics",
                           type="diagnostic_msgs/msg/DiagnosticArray",
                           value={"status": [{"level": 2, "name": "motor",
                                              "message": "overheat"}]},
                           count=2)
    await eventually(lambda: rig.telemetry.status(pending_auth=0).state == "fault")
    assert rig.telemetry.status(pending_auth=0).faults[0].message == "overheat"
    await rig.oracle.acall("publish", topic="/robot1/diagnostics",
                           type="diagnostic_msgs/msg/DiagnosticArray",
                           value={"status": [{"level": 0, "name": "motor", "message": "ok"}]},
                           count=2)
    await eventually(lambda: rig.telemetry.status(pending_auth=0).state != "fault")
    # The robot falls silent: offline after the staleness window (1 s here).
    await eventually(lambda: rig.telemetry.status(pending_auth=0).state == "offline")
    assert not rig.telemetry.status(pending_auth=0).ros.connected


@both_rmws
async def test_rclpy_lists_the_bridge_node(rig: Rig) -> None:
    async def listed() -> bool:
        return ["rcan_bridge", "/robot1"] in await rig.oracle.acall("node_names")

    await eventually(listed, timeout=15)


async def test_twist_stamped_carries_a_fresh_stamp(tmp_path: Path, jazzy_python: Path,
                                                   domain_id: int) -> None:
    config = bridge_config(tmp_path, domain_id,
                           extra_ros2="cmd_vel_type: geometry_msgs/msg/TwistStamped")
    rig = await make_rig(config, jazzy_python, domain_id)
    try:
        await subscribe(rig, "/robot1/cmd_vel", "geometry_msgs/msg/TwistStamped")
        before = time.time()
        assert (await rig.command(AGENT, {"action": "move",
                                          "params": {"angular_z": 0.3}})).http_status == 200
        msg = (await take(rig.oracle, CMD_VEL))[0]
        stamp = msg["header"]["stamp"]["sec"] + msg["header"]["stamp"]["nanosec"] / 1e9
        assert before - 1 <= stamp <= time.time() + 1
        assert msg["twist"]["angular"]["z"] == 0.3
    finally:
        await close_rig(rig)


async def test_navigate_and_session_loss_cancels_the_goal(tmp_path: Path, jazzy_python: Path,
                                                         domain_id: int) -> None:
    """navigate → NavigateToPose on our own server (the sim's); losing the session halts the
    robot and cancels the goal. rclpy watches cmd_vel for the zero twist."""
    from rcan_rtps.ros.participant import RosNode
    from rcan_rtps.sim.navigation import NavigationServer
    from rcan_rtps.sim.robot import SimRobot

    config = bridge_config(tmp_path, domain_id)
    stop = asyncio.Event()
    with RosNode("sim_robot", "/robot1", domain_id=domain_id) as sim_node:
        robot = SimRobot(sim_node)
        nav = NavigationServer(robot)
        sim = asyncio.create_task(robot.run(stop))
        rig = await make_rig(config, jazzy_python, domain_id, navigation=True)
        try:
            await subscribe(rig, "/robot1/cmd_vel", TWIST)
            decision = await rig.command(AGENT, {"action": "navigate",
                                                 "params": {"x": 8.0, "y": 0.0, "yaw": 0.0}})
            assert decision.http_status == 200 and decision.goal_id, decision
            assert rig.goals is not None
            view = rig.goals.goal(decision.goal_id)
            assert view is not None
            await eventually(lambda: view.feedback is not None)
            assert rig.telemetry.status(pending_auth=0).active_goals == [decision.goal_id]
            # no heartbeat: after session_timeout_s the goal is cancelled and the base halted
            await eventually(lambda: view.state == "canceled", timeout=15,
                             what=lambda: f"the goal is canceled: {view}")
            zero = await take(rig.oracle, CMD_VEL, timeout=10)
            assert zero and zero[-1]["linear"]["x"] == 0.0
            await eventually(lambda: abs(robot.state.v) < 1e-9)
            events = [e["event"] for e in rig.entries()]
            assert "NETWORK_LOSS_SAFE_STOP" in events
            assert rig.telemetry.status(pending_auth=0).active_goals == []
        finally:
            await close_rig(rig)
            stop.set()
            await sim
            await nav.close()
