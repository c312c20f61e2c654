"""The simulated robot is a real ROS 2 node: rclpy drives it and watches it."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
from oracle.client import RclpyOracle

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
    for _ in range(int(timeout / 0.05)):
        got = oracle.call("take", topic=topic)
        if got:
            return got[-1]
        await asyncio.sleep(0.05)
    raise AssertionError(f"nothing on {topic}")


async def until(oracle: RclpyOracle, predicate: Any, timeout: float = 15.0) -> bool:
    """Whether some odometry message on /robot1/odom satisfies `predicate` in time."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while loop.time() < deadline:
        if any(predicate(m) for m in oracle.call("take", topic="/robot1/odom")):
            return True
        await asyncio.sleep(0.05)
    return False


async def test_rclpy_drives_the_sim_and_sees_odometry(oracle: RclpyOracle,
                                                      sim: SimRobot) -> None:
    oracle.call("subscribe", topic="/robot1/odom", type="nav_msgs/msg/Odometry")
    oracle.call("publisher", topic="/robot1/cmd_vel", type="geometry_msgs/msg/Twist")
    assert oracle.call("wait_subscribers", topic="/robot1/cmd_vel") >= 1
    await sim.inputs["cmd_vel"].wait_for_publishers(1, timeout=15)
    start = await latest(oracle, "/robot1/odom")
    # in a thread: the sim steps on this event loop while rclpy publishes
    await asyncio.to_thread(oracle.call, "publish", topic="/robot1/cmd_vel",
                            type="geometry_msgs/msg/Twist", value={"linear": {"x": 0.5}},
                            count=20, period=0.05)
    x0 = start["pose"]["pose"]["position"]["x"]
    assert await until(oracle, lambda m: m["pose"]["pose"]["position"]["x"] > x0 + 0.2)
    # cmd_vel timeout: the base stops by itself
    assert await until(oracle, lambda m: m["twist"]["twist"]["linear"]["x"] == 0.0)


async def test_estop_halts_and_latches(oracle: RclpyOracle, sim: SimRobot) -> None:
    oracle.call("publisher", topic="/robot1/emergency_stop", type="std_msgs/msg/Bool",
                qos="transient_local")
    await sim.inputs["estop"].wait_for_publishers(1, timeout=15)
    oracle.call("publish", topic="/robot1/emergency_stop", type="std_msgs/msg/Bool",
                value={"data": True})
    for _ in range(100):
        if sim.state.estop:
            break
        await asyncio.sleep(0.05)
    assert sim.state.estop
    oracle.call("publisher", topic="/robot1/cmd_vel", type="geometry_msgs/msg/Twist")
    oracle.call("wait_subscribers", topic="/robot1/cmd_vel")
    await sim.inputs["cmd_vel"].wait_for_publishers(1, timeout=15)
    x0 = sim.state.x
    await asyncio.to_thread(oracle.call, "publish", topic="/robot1/cmd_vel",
                            type="geometry_msgs/msg/Twist", value={"linear": {"x": 1.0}},
                            count=10, period=0.05)
    assert sim.state.x == x0 and sim.state.v == 0.0


async def test_arm_follows_a_trajectory(oracle: RclpyOracle, sim: SimRobot) -> None:
    topic = "/robot1/joint_trajectory_controller/joint_trajectory"
    oracle.call("publisher", topic=topic, type="trajectory_msgs/msg/JointTrajectory")
    oracle.call("subscribe", topic="/robot1/joint_states", type="sensor_msgs/msg/JointState")
    assert oracle.call("wait_subscribers", topic=topic) >= 1
    await sim.inputs["trajectory"].wait_for_publishers(1, timeout=15)
    # Sent a few times: a volatile sample can be lost while both sides finish matching.
    await asyncio.to_thread(
        oracle.call, "publish", topic=topic, type="trajectory_msgs/msg/JointTrajectory",
        value={"joint_names": ["elbow"],
               "points": [{"positions": [1.2],
                           "time_from_start": {"sec": 0, "nanosec": 300_000_000}}]},
        count=5, period=0.1)
    for _ in range(100):
        js = await latest(oracle, "/robot1/joint_states")
        if abs(js["position"][js["name"].index("elbow")] - 1.2) < 1e-9:
            break
        await asyncio.sleep(0.05)
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
            names: list = []
            for _ in range(100):
                names = oracle.call("node_names")
                if ["sim_robot", "/bot"] in names:
                    break
                time.sleep(0.1)
            assert ["sim_robot", "/bot"] in names
            topics = dict((n, t) for n, t in oracle.call("topic_names"))
            for topic, type_name in (("/bot/odom", "nav_msgs/msg/Odometry"),
                                     ("/bot/joint_states", "sensor_msgs/msg/JointState"),
                                     ("/bot/battery_state", "sensor_msgs/msg/BatteryState"),
                                     ("/bot/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")):
                assert topics.get(topic) == [type_name], topics
            for _ in range(200):
                if oracle.call("take", topic="/bot/odom"):
                    break
                time.sleep(0.05)
            else:
                raise AssertionError("no odometry from the sim")
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    assert proc.returncode == 0
