"""A governed bridge's ROS side (governor + dispatcher + telemetry) beside a real rclpy node."""

from __future__ import annotations

import contextlib
import json
import re
import textwrap
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from oracle.client import OracleEnv, RclpyOracle
from waiting import eventually

from rcan_rtps.bridge.commanders import CommanderWatch
from rcan_rtps.bridge.commands import RosDispatcher
from rcan_rtps.bridge.goals import GoalRoutes
from rcan_rtps.bridge.joint_positions import JointPositions
from rcan_rtps.bridge.navigation import GoalTracker
from rcan_rtps.bridge.notify import DiagnosticsNotifier
from rcan_rtps.bridge.runtime import watch_commanders, wire_robot_side
from rcan_rtps.bridge.telemetry import TelemetryState
from rcan_rtps.config import RcanConfig, loads_config
from rcan_rtps.events import Events
from rcan_rtps.governance import AuditLog, Decision, Governor, Principal
from rcan_rtps.rcan import Role, validate_command
from rcan_rtps.ros.action_server import ActionServer, Execute
from rcan_rtps.ros.participant import RosNode

VIEWER = Principal("viewer", Role.GUEST)
AGENT = Principal("agent", Role.USER)
OPS = Principal("ops", Role.OWNER)


def bridge_config(tmp_path: Path, domain_id: int, extra_ros2: str = "",
                  extra: str = "") -> RcanConfig:
    text = textwrap.dedent(f"""\
        robot:
          ruri: rcan://registry.local/acme/rover/unit-0001
          name: Test Rover
        bridge:
          ros2:
            namespace: /robot1
            node_name: rcan_bridge
            domain_id: {domain_id}
            telemetry_stale_s: 1.0
            match_timeout_s: 3.0
        @@ROS2@@
          api:
            auth_token_env: RCAN_BRIDGE_TOKEN
          safety:
            max_linear_vel: 1.5
            max_angular_vel: 1.0
            session_timeout_s: 1.0
            workspace: [[-10, -10], [10, -10], [10, 10], [-10, 10]]
          audit:
            path: {tmp_path / "audit.jsonl"}
            key_path: {tmp_path / "audit.key"}
        @@BRIDGE@@
        """)
    for line in extra_ros2.splitlines():  # an extra key replaces its default (never twice)
        key = line.split(":", 1)[0].strip()
        text = re.sub(rf"^    {re.escape(key)}: .*\n", "", text, flags=re.M)
    text = text.replace("@@ROS2@@", textwrap.indent(extra_ros2, "    "))
    text = text.replace("@@BRIDGE@@", textwrap.indent(extra, "  "))
    return loads_config(text, env={"RCAN_BRIDGE_TOKEN": "t" * 32})


@dataclass
class Rig:
    node: RosNode
    governor: Governor
    telemetry: TelemetryState
    dispatcher: RosDispatcher
    oracle: RclpyOracle
    audit_path: Path
    goals: GoalRoutes | None = None
    notifier: DiagnosticsNotifier | None = None
    commanders: CommanderWatch | None = None

    async def command(self, principal: Principal, body: dict[str, Any]) -> Decision:
        return await self.governor.decide(validate_command(json.dumps(body).encode()), principal)

    def entries(self) -> list[dict[str, Any]]:
        return [json.loads(line) for line in self.audit_path.read_text().splitlines()]



async def make_rig(config: RcanConfig, jazzy_python: Path | OracleEnv, domain_id: int,
                   *, navigation: bool = False, watch_s: float | None = None,
                   watch: bool = False) -> Rig:
    """`watch_s`: watch the command topics for other publishers, polling so often; `watch`:
    as often as the config says."""
    ros2 = config.bridge.ros2
    # As `run` makes it: the endpoints the robot obeys marked with its robot's id, so that
    # the rclpy peers of these tests meet the USER_DATA a real bridge's endpoints carry.
    node = RosNode(ros2.node_name, ros2.namespace, domain_id=domain_id, distro=ros2.distro,
                   governed_by=config.robot.ruri, max_sample_bytes=ros2.max_sample_bytes)
    events = Events()
    audit = await AuditLog.open(config.bridge.audit.path, config.bridge.audit.key_path,
                                audited=events.audited)
    goals = GoalRoutes(node, ros2, events=events) if navigation else None
    joints = JointPositions()  # heard by the telemetry, read by a stop holding an arm
    dispatcher = RosDispatcher(node, ros2, goals, telemetry_age=lambda: telemetry.age_s(),
                               events=events, joint_positions=joints)
    notifier = DiagnosticsNotifier(node, ros2.diagnostics_topic)
    governor = Governor.from_config(config, audit=audit, dispatcher=dispatcher,
                                    notifier=notifier, events=events)
    telemetry = TelemetryState(node, config, estop_latched=lambda: governor.latch.latched,
                               active_goals=goals.active if goals else list,
                               navigation=goals.navigation if goals else lambda: None,
                               events=events, joint_positions=joints)
    wire_robot_side(events, governor, telemetry, goals, notifier)
    events.freeze()
    await governor.start()
    commanders = (None if watch_s is None and not watch else
                  watch_commanders(node, governor, dispatcher, telemetry, watch_s))
    oracle = RclpyOracle(jazzy_python, "robot", "/robot1", domain_id=domain_id)
    return Rig(node, governor, telemetry, dispatcher, oracle, Path(config.bridge.audit.path),
               goals, notifier, commanders)


NAV = "nav2_msgs/action/NavigateToPose"


@contextlib.asynccontextmanager
async def navigation_rig(config: RcanConfig, jazzy_python: Path, domain_id: int,
                         execute: Execute) -> AsyncIterator[Rig]:
    """A rig with navigation whose robot serves NavigateToPose with `execute` (our own action
    server, on a participant of its own: the rclpy oracle serves only Fibonacci), yielded once
    the bridge has discovered that server (before any goal is sent)."""
    with RosNode("nav_robot", "/robot1", domain_id=domain_id) as robot_node:
        server = ActionServer(robot_node, "navigate_to_pose", NAV, execute)
        rig = await make_rig(config, jazzy_python, domain_id, navigation=True)
        try:
            await eventually(nav_tracker(rig).client.server_present,
                             what="the NavigateToPose server")
            yield rig
        finally:
            await close_rig(rig)
            await server.close()


def nav_tracker(rig: Rig) -> GoalTracker:
    """The tracker of the rig's navigation goals (`nav_action`)."""
    assert rig.goals is not None
    tracker = rig.goals.tracker("nav_action")
    assert tracker is not None
    return tracker


async def close_rig(rig: Rig) -> None:
    if rig.commanders is not None:
        await rig.commanders.close()
    if rig.goals is not None:
        await rig.goals.close()
    if rig.notifier is not None:
        rig.notifier.close()
    await rig.governor.stop()
    await rig.governor.audit.close()
    rig.oracle.close()
    rig.node.close()
