"""The simulated robot is a real ROS 2 node: rclpy drives it and watches it."""

from __future__ import annotations

import asyncio
import math
import os
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
from oracle.client import OracleEnv, RclpyOracle
from waiting import eventually, eventually_sync, take

from rcan_rtps.ros.actions import ActionClient, GoalState
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.sim.docking import ACTION_TYPE as DOCK_ROBOT
from rcan_rtps.sim.docking import (
    CONTROLLING,
    DOCK_NOT_IN_DB,
    DOCKS,
    FAILED_TO_DETECT_DOCK,
    NAV_TO_STAGING_POSE,
    WAIT_FOR_CHARGE,
    DockingServer,
)
from rcan_rtps.sim.robot import ARM_JOINTS, CHARGING, DISCHARGING, SimRobot


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


@pytest.fixture
def sim_process(domain_id: int) -> Iterator[subprocess.Popen[str]]:
    """`rcan-rtps sim --namespace /bot`, ready; it must end cleanly when terminated."""
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    proc = subprocess.Popen([sys.executable, "-m", "rcan_rtps", "sim", "--namespace", "/bot"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stdout is not None
        assert "rcan-rtps sim ready node=/bot/sim_robot" in proc.stdout.readline()
        yield proc
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    assert proc.returncode == 0


def test_sim_command_is_a_node_rclpy_sees(sim_process: subprocess.Popen[str],
                                         jazzy_python: Path, domain_id: int) -> None:
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
        # its goal servers: nav2 NavigateToPose and DockRobot, as rclpy lists them
        def action_servers() -> dict[str, list[str]] | None:
            info = oracle.call("node_info", name="sim_robot", namespace="/bot")
            found = {n: t for n, t in info["Action Servers"]}
            return found if len(found) >= 2 else None

        servers = eventually_sync(action_servers, what="the sim's two action servers")
        assert servers == {"/bot/navigate_to_pose": ["nav2_msgs/action/NavigateToPose"],
                           "/bot/dock_robot": ["nav2_msgs/action/DockRobot"]}, servers


# -- docking (issue 23, item 4): the sim serves nav2 DockRobot ------------------------------

@pytest.fixture
async def dock_client(sim: SimRobot, domain_id: int) -> AsyncIterator[ActionClient]:
    server = DockingServer(sim)
    with RosNode("dock_client", "/robot1", domain_id=domain_id) as node:
        client = ActionClient(node, "dock_robot", DOCK_ROBOT)
        try:
            yield client
        finally:
            client.close()
            await server.close()


async def _dock(client: ActionClient, goal: dict[str, Any]) -> tuple[Any, list[int]]:
    handle = await client.send_goal(goal, timeout=15)
    assert handle.accepted
    states = [int(f.state) async for f in handle.feedback(timeout=60)]
    return await handle.result(timeout=30), states


async def test_docking_drives_onto_the_dock_and_charges(sim: SimRobot,
                                                        dock_client: ActionClient) -> None:
    home = DOCKS["home"]
    outcome, states = await _dock(dock_client, {"dock_id": "home"})
    assert outcome.state is GoalState.SUCCEEDED and outcome.result.success, outcome
    # staging first, then the approach, then waiting for the charge
    assert states[0] == NAV_TO_STAGING_POSE, states
    assert states.index(NAV_TO_STAGING_POSE) < states.index(CONTROLLING) < states.index(
        WAIT_FOR_CHARGE), states
    s = sim.state
    assert abs(s.x - home.x) < 0.1 and abs(s.y - home.y) < 0.1
    assert abs(math.atan2(math.sin(s.yaw - home.yaw), math.cos(s.yaw - home.yaw))) < 0.1
    assert s.docked_at == "home"
    sim.state.energy_wh = 40.0
    sim.step(10.0)
    assert sim.state.energy_wh > 40.0  # charging, idle load and all
    battery = await _battery(sim)
    assert battery["power_supply_status"] == CHARGING
    sim.drive(0.3, 0.0)  # driving off the dock ends the charge
    sim.step(0.1)
    assert sim.state.docked_at is None
    assert (await _battery(sim))["power_supply_status"] == DISCHARGING


async def _battery(sim: SimRobot) -> dict[str, Any]:
    """The battery_state the sim publishes now, as a reader on the wire gets it."""
    with RosNode("battery_reader", "/robot1", domain_id=sim.node.domain_id) as node:
        reader = node.create_subscription("battery_state", "sensor_msgs/msg/BatteryState")
        msg = await reader.get(timeout=15)  # published at 1 Hz, after this reader was made
        return {"power_supply_status": int(msg.power_supply_status)}


async def test_docking_failures_carry_nav2_error_codes(sim: SimRobot,
                                                       dock_client: ActionClient) -> None:
    outcome, _ = await _dock(dock_client, {"dock_id": "garage"})
    assert outcome.state is GoalState.ABORTED
    assert (outcome.result.success, outcome.result.error_code) == (False, DOCK_NOT_IN_DB)
    # Without staging the robot must already see the dock: from the origin it does not.
    outcome, _ = await _dock(dock_client, {"dock_id": "home", "navigate_to_staging_pose": False})
    assert outcome.state is GoalState.ABORTED
    assert outcome.result.error_code == FAILED_TO_DETECT_DOCK
    assert sim.state.docked_at is None and abs(sim.state.x) < 1e-6


def _cli(domain_id: int, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    return subprocess.run([sys.executable, "-m", "rcan_rtps", *args], capture_output=True,
                          text=True, env=env, timeout=60)


def test_the_sim_serves_its_parameters(sim_process: subprocess.Popen[str],
                                       domain_id: int) -> None:
    listing = _cli(domain_id, "param", "list", "/bot/sim_robot")
    assert listing.returncode == 0, listing.stderr
    names = [line.strip() for line in listing.stdout.splitlines()]
    assert {"use_sim_time", "rate_hz", "cmd_timeout_s", "max_linear", "max_angular"} <= set(names)
    got = _cli(domain_id, "param", "get", "/bot/sim_robot", "use_sim_time")
    assert got.stdout.strip() == "Boolean value is: False", got.stderr
    got = _cli(domain_id, "param", "get", "/bot/sim_robot", "rate_hz")
    assert got.stdout.strip() == "Double value is: 50.0", got.stderr

    done = _cli(domain_id, "param", "set", "/bot/sim_robot", "max_linear", "1.5")
    assert (done.returncode, done.stdout.strip()) == (0, "Set parameter successful")
    got = _cli(domain_id, "param", "get", "/bot/sim_robot", "max_linear")
    assert got.stdout.strip() == "Double value is: 1.5"
    for name, value, why in (("rate_hz", "10.0", "read-only"),
                             ("use_sim_time", "true", "wall-clock time"),
                             ("max_linear", "fast", "is of type {double}")):
        refused = _cli(domain_id, "param", "set", "/bot/sim_robot", name, value)
        assert refused.returncode == 1 and why in refused.stdout, refused.stdout
    dump = _cli(domain_id, "param", "dump", "/bot/sim_robot")
    assert "    max_linear: 1.5" in dump.stdout and "    use_sim_time: false" in dump.stdout


def test_rclpy_reads_the_sims_parameters(sim_process: subprocess.Popen[str],
                                         jazzy_cyclone_python: Path, domain_id: int) -> None:
    """rclpy on rmw_cyclonedds_cpp (our servers speak the Cyclone request-reply mapping)."""
    with RclpyOracle(OracleEnv(jazzy_cyclone_python, "cyclonedds"), "reader",
                     domain_id=domain_id) as oracle:
        reply = oracle.call("service_call", name="/bot/sim_robot/get_parameters",
                            type="rcl_interfaces/srv/GetParameters",
                            value={"names": ["use_sim_time", "max_angular", "nothing"]},
                            wait=15.0)
    values = reply["values"]
    assert [v["type"] for v in values] == [1, 3, 0], reply
    assert values[0]["bool_value"] is False and values[1]["double_value"] == 3.0
