"""`estop_not_holding` with only expected publishers is a WARN only while the robot is seen
still by *fresh* odometry (and, for a trajectory topic, a fresh JointState): what the robot's
other nodes keep sending (diagnostics, battery) says nothing about whether it moves.
A real node's TelemetryState, fed real messages of the robot's types; its clock is the test's."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from interop.bridge_rig import bridge_config

from rcan_rtps.bridge.telemetry import ESTOP_NOT_HOLDING, MAX_FOREIGN, TelemetryState
from rcan_rtps.config import RcanConfig
from rcan_rtps.rcan import ForeignPublisher
from rcan_rtps.ros.participant import RosNode

CMD_VEL = "/robot1/cmd_vel"
ARM = "/robot1/arm/joint_trajectory"
ODOM, JOINTS = "nav_msgs/msg/Odometry", "sensor_msgs/msg/JointState"
DIAGNOSTICS, BATTERY = "diagnostic_msgs/msg/DiagnosticArray", "sensor_msgs/msg/BatteryState"


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@contextmanager
def telemetry_of(name: str, config: RcanConfig, *, latched: bool,
                 clock: Clock | None = None) -> Iterator[tuple[RosNode, TelemetryState]]:
    """A real node's TelemetryState (the e-stop latched or not; the test's clock, if given),
    closed after."""
    kwargs = {} if clock is None else {"monotonic": clock}
    with RosNode(name, "/robot1", domain_id=config.bridge.ros2.domain_id) as node:
        telemetry = TelemetryState(node, config, estop_latched=lambda: latched,
                                   active_goals=list, **kwargs)
        try:
            yield node, telemetry
        finally:
            telemetry.close()


def estop_level(telemetry: TelemetryState) -> str:
    (fault, *_) = [f for f in telemetry.status(pending_auth=0).faults
                   if f.name == ESTOP_NOT_HOLDING]
    return fault.level


async def test_stale_odometry_is_not_still_while_other_telemetry_comes(
        tmp_path: Path, domain_id: int) -> None:
    config = bridge_config(tmp_path, domain_id)  # telemetry_stale_s: 1.0
    clock = Clock()
    with telemetry_of("stillness", config, latched=True, clock=clock) as (node, telemetry):
        values = node.values
        telemetry.foreign_publishers([ForeignPublisher(
            topic=CMD_VEL, type="geometry_msgs/msg/Twist", participant="01",
            node="/controller_server", expected=True)], {CMD_VEL})
        telemetry._on_odom(values.build(ODOM, {}))  # at rest
        assert estop_level(telemetry) == "WARN"
        diagnostics = values.build(DIAGNOSTICS, {"status": [
            {"level": 0, "name": "motor", "hardware_id": "base", "message": "ok"}]})
        battery = values.build(BATTERY, {"percentage": 0.8, "voltage": 12.0})
        for _ in range(5):  # odometry has stopped; the robot's other nodes go on
            clock.now += 0.9
            telemetry._on_diagnostics(diagnostics)
            telemetry._on_battery(battery)
        assert telemetry.status(pending_auth=0).ros.connected  # the robot is heard
        assert estop_level(telemetry) == "ERROR"  # but not seen still: odometry is stale
        telemetry._on_odom(values.build(ODOM, {}))
        assert estop_level(telemetry) == "WARN"


async def test_a_stale_joint_state_is_not_still_for_a_trajectory_topic(
        tmp_path: Path, domain_id: int) -> None:
    config = bridge_config(tmp_path, domain_id, "arms:\n  arm: {topic: arm/joint_trajectory}\n")
    clock = Clock()
    with telemetry_of("stillness_arm", config, latched=True, clock=clock) as (node, telemetry):
        values = node.values
        telemetry.foreign_publishers([ForeignPublisher(
            topic=ARM, type="trajectory_msgs/msg/JointTrajectory", participant="01",
            node="/move_group", expected=True)], {CMD_VEL, ARM})
        resting = values.build(JOINTS, {"name": ["elbow"], "position": [0.1],
                                        "velocity": [0.0]})
        telemetry._on_joints(resting)
        telemetry._on_odom(values.build(ODOM, {}))
        assert estop_level(telemetry) == "WARN"
        for _ in range(5):  # the JointState has stopped; odometry goes on, at rest
            clock.now += 0.9
            telemetry._on_odom(values.build(ODOM, {}))
        assert estop_level(telemetry) == "ERROR"
        telemetry._on_joints(resting)
        assert estop_level(telemetry) == "WARN"


async def test_status_lists_the_unexpected_publishers_before_the_expected(
        tmp_path: Path, domain_id: int) -> None:
    """STATUS lists MAX_FOREIGN of them: participants claiming an expected node's name
    (any may) must not push an unexpected one out of the list."""
    config = bridge_config(tmp_path, domain_id)
    with telemetry_of("foreign_order", config, latched=False) as (_node, telemetry):
        claimed = [ForeignPublisher(topic=CMD_VEL, type="geometry_msgs/msg/Twist",
                                    participant=f"{i:02x}", node="/controller_server",
                                    expected=True) for i in range(MAX_FOREIGN + 8)]
        teleop = ForeignPublisher(topic=CMD_VEL, type="geometry_msgs/msg/Twist",
                                  participant="ff", node="/teleop")
        telemetry.foreign_publishers([*claimed, teleop], {CMD_VEL})
        status = telemetry.status(pending_auth=0)
        assert status.foreign_publishers_count == MAX_FOREIGN + 9
        assert len(status.foreign_publishers) == MAX_FOREIGN
        assert status.foreign_publishers[0].node == "/teleop"


async def test_a_holonomic_base_moving_sideways_is_not_still(
        tmp_path: Path, domain_id: int) -> None:
    """STATUS's velocity is linear x and angular z; a mecanum base driven by nav2's
    holonomic controllers moves along y too (and odometry can say anything of the rest):
    seen still is the whole twist at rest."""
    config = bridge_config(tmp_path, domain_id)
    with telemetry_of("stillness_holonomic", config, latched=True) as (node, telemetry):
        telemetry.foreign_publishers([ForeignPublisher(
            topic=CMD_VEL, type="geometry_msgs/msg/Twist", participant="01",
            node="/controller_server", expected=True)], {CMD_VEL})
        for twist in ({"linear": {"y": 0.4}}, {"linear": {"z": float("nan")}},
                      {"angular": {"x": 0.5}}):
            telemetry._on_odom(node.values.build(ODOM, {"twist": {"twist": twist}}))
            assert estop_level(telemetry) == "ERROR", twist
        telemetry._on_odom(node.values.build(ODOM, {}))
        assert estop_level(telemetry) == "WARN"


async def test_status_state_is_moving_for_any_component_of_the_twist(
        tmp_path: Path, domain_id: int) -> None:
    """STATUS's `state` reads the whole twist, as the e-stop's stillness does: a holonomic
    base moving along y is "moving", not "idle"; a component that is not a number is not
    idle either; only a twist wholly at rest is."""
    config = bridge_config(tmp_path, domain_id)
    with telemetry_of("state_holonomic", config, latched=False) as (node, telemetry):
        for twist in ({"linear": {"y": 0.4}}, {"linear": {"z": -0.2}},
                      {"angular": {"x": 0.5}}, {"angular": {"y": float("nan")}},
                      {"linear": {"x": 0.3}}, {"angular": {"z": float("nan")}}):
            telemetry._on_odom(node.values.build(ODOM, {"twist": {"twist": twist}}))
            assert telemetry.status(pending_auth=0).state == "moving", twist
        telemetry._on_odom(node.values.build(ODOM, {}))
        assert telemetry.status(pending_auth=0).state == "idle"


async def test_a_sideways_start_tells_the_robot_changed(tmp_path: Path, domain_id: int) -> None:
    """The robot event (what pushes STATUS to WebSocket clients) fires when the robot starts
    or stops moving along y, as it does along x."""
    config = bridge_config(tmp_path, domain_id)
    with telemetry_of("state_event", config, latched=False) as (node, telemetry):
        told: list[int] = []
        telemetry.events.robot.subscribe(lambda: told.append(1))
        telemetry._on_odom(node.values.build(ODOM, {}))  # connected: told
        told.clear()
        telemetry._on_odom(node.values.build(ODOM, {"twist": {"twist": {
            "linear": {"y": 0.4}}}}))
        assert told, "starting to move along y is a change of state"
        told.clear()
        telemetry._on_odom(node.values.build(ODOM, {}))
        assert told, "stopping is a change of state"
