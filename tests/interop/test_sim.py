"""The simulated robot is a real ROS 2 node: rclpy drives it and watches it."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
from oracle.client import RclpyOracle
from waiting import eventually, eventually_sync, take

from rcan_rtps.ros.participant import RosNode
from rcan_rtps.sim.robot import ARM_JOINTS, SimRobot


@pytest.fixture
def oracle(jazzy_python: Path, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_python, "operator", "/robot1", domain_id=domain_id) as agent:
        yield agent


@pytest.fixture
async def sim(domain_id: int) -> AsyncIterator[SimRobot]:
    stop = asyncio.Event()
    with RosNode("sim_robot", "/robot1", domain_id=domain_id) as node:
        robot = SimRobot(node)
        task = asyncio.create_task(robot.run(stop))
        yield robot
        stop.set()
        await task


async def latest(oracle: RclpyOracle, topic: str, timeout: float = 10.0) -> dict:
    return (await take(oracle, topic, timeout=timeout))[-1]  # type: ignore[no-any-return]


async def odometry(oracle: RclpyOracle, predicate: Any, timeout: float = 15.0) -> None:
    """Some odometry message on /robot1/odom satisfies `predicate` in time."""
    await take(oracle, "/robot1/odom", until=lambda got: any(predicate(m) for m in got),
               timeout=timeout)


async def test_rclpy_drives_the_sim_and_sees_odometry(oracle: RclpyOracle,
                                                      sim: SimRobot) -> None:
    await oracle.acall("subscribe", topic="/robot1/odom", type="nav_msgs/msg/Odometry")
    await oracle.acall("publisher", topic="/robot1/cmd_vel", type="geometry_msgs/msg/Twist")
    assert await oracle.acall("wait_subscribers", topic="/robot1/cmd_vel") >= 1
    await sim.inputs["cmd_vel"].wait_for_publishers(1, timeout=15)
    start = await latest(oracle, "/robot1/odom")
    # in a thread: the sim steps on this event loop while rclpy publishes
    await oracle.acall("publish", topic="/robot1/cmd_vel",
                       type="geometry_msgs/msg/Twist", value={"linear": {"x": 0.5}},
                       count=20, period=0.05)
    x0 = start["pose"]["pose"]["position"]["x"]
    await odometry(oracle, lambda m: m["pose"]["pose"]["position"]["x"] > x0 + 0.2)
    # cmd_vel timeout: the base stops by itself
    await odometry(oracle, lambda m: m["twist"]["twist"]["linear"]["x"] == 0.0)


async def test_estop_halts_and_latches(oracle: RclpyOracle, sim: SimRobot) -> None:
    await oracle.acall("publisher", topic="/robot1/emergency_stop", type="std_msgs/msg/Bool",
                       qos="transient_local")
    await sim.inputs["estop"].wait_for_publishers(1, timeout=15)
    await oracle.acall("publish", topic="/robot1/emergency_stop", type="std_msgs/msg/Bool",
                       value={"data": True})
    await eventually(lambda: sim.state.estop, timeout=5, what="the sim latched the e-stop")
    await oracle.acall("publisher", topic="/robot1/cmd_vel", type="geometry_msgs/msg/Twist")
    await oracle.acall("wait_subscribers", topic="/robot1/cmd_vel")
    await sim.inputs["cmd_vel"].wait_for_publishers(1, timeout=15)
    x0 = sim.state.x
    await oracle.acall("publish", topic="/robot1/cmd_vel",
                       type="geometry_msgs/msg/Twist", value={"linear": {"x": 1.0}},
                       count=10, period=0.05)
    assert sim.state.x == x0 and sim.state.v == 0.0


async def test_arm_follows_a_trajectory(oracle: RclpyOracle, sim: SimRobot) -> None:
    topic = "/robot1/joint_trajectory_controller/joint_trajectory"
    await oracle.acall("publisher", topic=topic, type="trajectory_msgs/msg/JointTrajectory")
    await oracle.acall("subscribe", topic="/robot1/joint_states", type="sensor_msgs/msg/JointState")
    assert await oracle.acall("wait_subscribers", topic=topic) >= 1
    await sim.inputs["trajectory"].wait_for_publishers(1, timeout=15)
    # Sent a few times: a volatile sample can be lost while both sides finish matching.
    await oracle.acall(
        "publish", topic=topic, type="trajectory_msgs/msg/JointTrajectory",
        value={"joint_names": ["elbow"],
               "points": [{"positions": [1.2],
                           "time_from_start": {"sec": 0, "nanosec": 300_000_000}}]},
        count=5, period=0.1)

    async def elbow_there() -> dict[str, Any] | None:
        js = await latest(oracle, "/robot1/joint_states")
        return js if abs(js["position"][js["name"].index("elbow")] - 1.2) < 1e-9 else None

    js = await eventually(elbow_there, timeout=30)
    assert js["name"][2:] == list(ARM_JOINTS)
    assert abs(js["position"][js["name"].index("elbow")] - 1.2) < 1e-9


async def test_battery_drains_with_motion(sim: SimRobot) -> None:
    idle_before = sim.state.energy_wh
    sim.step(10.0)
    idle_use = idle_before - sim.state.energy_wh
    sim.drive(1.0, 0.0)
    moving_before = sim.state.energy_wh
    sim.step(10.0)
    assert moving_before - sim.state.energy_wh > idle_use > 0


def test_sim_command_is_a_node_rclpy_sees(jazzy_python: Path, domain_id: int) -> None:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    proc = subprocess.Popen([sys.executable, "-m", "rcan_rtps", "sim", "--namespace", "/bot"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stdout is not None
        assert "rcan-rtps sim ready node=/bot/sim_robot" in proc.stdout.readline()
        with RclpyOracle(jazzy_python, "watcher", domain_id=domain_id) as oracle:
            oracle.call("subscribe", topic="/bot/odom", type="nav_msgs/msg/Odometry")
            eventually_sync(lambda: ["sim_robot", "/bot"] in oracle.call("node_names"))
            topics = dict((n, t) for n, t in oracle.call("topic_names"))
            for topic, type_name in (("/bot/odom", "nav_msgs/msg/Odometry"),
                                     ("/bot/joint_states", "sensor_msgs/msg/JointState"),
                                     ("/bot/battery_state", "sensor_msgs/msg/BatteryState"),
                                     ("/bot/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")):
                assert topics.get(topic) == [type_name], topics
            eventually_sync(lambda: oracle.call("take", topic="/bot/odom"),
                            what="odometry from the sim")
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    assert proc.returncode == 0
