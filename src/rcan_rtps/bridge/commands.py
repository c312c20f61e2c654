"""Governed commands → ROS 2 (spec §4): the bridge's `Dispatcher`.

Only parameters the governor approved (`applied`: clamped, checked) reach the wire, and only
after their audit entry is durable: `ready` does all the waiting (the governor calls it before
writing the entry), and `dispatch` publishes motion before its first await.

Robot liveness comes from the wire: a command topic whose robot-side reader is gone (it had
matched and no longer does), or a robot whose telemetry stopped for `telemetry_stale_s`, answers
ROBOT_UNAVAILABLE at once. A topic that never matched yet gets `match_timeout_s` to match
(start-up). `stop` is never held back by any of this.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from typing import Any, Protocol

from ..config import Ros2Config
from ..governance import DispatchResult
from ..rcan import NormalizedCommand
from ..ros import qos
from ..ros.errors import GraphTimeout
from ..ros.participant import RosNode, RosPublisher
from ..ros.rostime import duration_msg, now_msg, yaw_to_quaternion

log = logging.getLogger(__name__)

TWIST = "geometry_msgs/msg/Twist"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
BOOL = "std_msgs/msg/Bool"
TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"
ESTOP_QOS = qos.DEFAULT.with_(depth=1, durability=qos.Durability.TRANSIENT_LOCAL)


class Navigator(Protocol):
    """Navigation goals (NavigateToPose); implemented over the ROS action client."""

    async def send(self, goal: dict[str, Any], timeout: float) -> str:
        """Sends a goal; returns its id once accepted. Raises on rejection/unavailability."""
        ...

    async def cancel_all(self) -> int:
        """Cancels every active goal; returns how many were active."""
        ...

    @property
    def action_name(self) -> str: ...


class RosDispatcher:
    def __init__(self, node: RosNode, ros2: Ros2Config, navigator: Navigator | None = None,
                 *, telemetry_age: Callable[[], float | None] = lambda: None) -> None:
        self.node = node
        self.ros2 = ros2
        self.navigator = navigator
        self.on_command: Callable[[], None] = lambda: None  # e.g. leave `safe_stop` state
        self._telemetry_age = telemetry_age  # seconds since the robot last published, if ever
        self._ever_matched: set[str] = set()
        self.cmd_vel = node.create_publisher(ros2.cmd_vel_topic, ros2.cmd_vel_type)
        # Latched (transient-local): a robot node that (re)joins still learns the e-stop state.
        self.estop = node.create_publisher(ros2.estop_topic, BOOL, ESTOP_QOS)
        self.trajectory = node.create_publisher(ros2.joint_trajectory_topic, TRAJECTORY)
        self._vector3 = node.types.struct("geometry_msgs/msg/Vector3")

    def route(self, command: NormalizedCommand) -> str | None:
        if command.action == "navigate":
            return self.navigator.action_name if self.navigator is not None else None
        return self._publisher(command.action).topic

    def _publisher(self, action: str) -> RosPublisher:
        if action == "arm_joint":
            return self.trajectory
        return self.estop if action in ("estop", "clear_estop") else self.cmd_vel

    async def ready(self, command: NormalizedCommand) -> str | None:
        if command.action in ("stop", "estop"):
            return None  # stopping is never held back
        if command.action != "clear_estop":
            silent = self._silent()
            if silent is not None:
                return silent
        if command.action == "navigate":
            return None if self.navigator is not None else "navigation is not available"
        pub = self._publisher(command.action)
        if await self._matched(pub):
            return None
        return f"no subscriber on {pub.topic}"

    async def dispatch(self, command: NormalizedCommand,
                       applied: Mapping[str, Any]) -> DispatchResult:
        handler = {
            "move": self._move, "arm_joint": self._arm_joint, "navigate": self._navigate,
            "stop": self._stop, "estop": self._estop, "clear_estop": self._clear_estop,
        }[command.action]
        self.on_command()
        return await handler(applied)

    # -- helpers ---------------------------------------------------------------------
    def _silent(self) -> str | None:
        age = self._telemetry_age()
        if age is not None and age > self.ros2.telemetry_stale_s:
            return f"robot silent: no telemetry for {age:.1f} s"
        return None

    async def _matched(self, pub: RosPublisher) -> bool:
        if pub.matched_count():
            self._ever_matched.add(pub.topic)
            return True
        if pub.topic in self._ever_matched:
            return False  # the robot's reader left: unavailable now, not after a timeout
        try:
            await pub.wait_for_subscribers(1, timeout=self.ros2.match_timeout_s)
        except GraphTimeout:
            return False
        self._ever_matched.add(pub.topic)
        return True

    def _twist(self, linear_x: float = 0.0, linear_y: float = 0.0,
               angular_z: float = 0.0) -> Any:
        # Built directly (the hot path): the governor has already checked these numbers.
        vec: Any = self._vector3
        twist_cls: Any = self.node.types.struct(TWIST)
        twist = twist_cls(linear=vec(float(linear_x), float(linear_y), 0.0),
                          angular=vec(0.0, 0.0, float(angular_z)))
        if self.ros2.cmd_vel_type == TWIST_STAMPED:
            header = self.node.values.build("std_msgs/msg/Header", {"stamp": now_msg()})
            stamped: Any = self.node.types.struct(TWIST_STAMPED)
            return stamped(header=header, twist=twist)
        return twist

    async def _publish(self, pub: RosPublisher, message: Any) -> DispatchResult:
        # No await before the write: `ready` waited, the governor checked the latch last.
        pub.publish(message)
        return DispatchResult(ok=True, ros2_topic=pub.topic)

    async def _publish_motion(self, pub: RosPublisher, message: Any) -> DispatchResult:
        # `ready` passed before the write-ahead entry; the robot may have gone silent or its
        # reader left while that was written. Checked again with no await before the write.
        why = self._silent() or (None if pub.matched_count() else f"no subscriber on {pub.topic}")
        if why is not None:
            return DispatchResult(ok=False, ros2_topic=pub.topic, detail=why)
        return await self._publish(pub, message)

    # -- actions -----------------------------------------------------------------------
    async def _move(self, applied: Mapping[str, Any]) -> DispatchResult:
        return await self._publish_motion(self.cmd_vel, self._twist(
            applied.get("linear_x", 0.0), applied.get("linear_y", 0.0),
            applied.get("angular_z", 0.0)))

    async def _arm_joint(self, applied: Mapping[str, Any]) -> DispatchResult:
        # A zero header stamp tells joint_trajectory_controller to start at once.
        return await self._publish_motion(self.trajectory, {
            "joint_names": list(applied["joints"]),
            "points": [{"positions": list(applied["positions"]),
                        "time_from_start": duration_msg(applied["duration_s"])}],
        })

    async def _navigate(self, applied: Mapping[str, Any]) -> DispatchResult:
        if self.navigator is None:
            return DispatchResult(ok=False, detail="navigation is not available")
        frame = applied.get("frame_id") or self.ros2.nav_frame_id
        goal = {"pose": {"header": {"stamp": now_msg(), "frame_id": frame},
                         "pose": {"position": {"x": applied["x"], "y": applied["y"], "z": 0.0},
                                  "orientation": yaw_to_quaternion(applied["yaw"])}}}
        try:
            goal_id = await self.navigator.send(goal, timeout=self.ros2.match_timeout_s)
        except Exception as exc:  # rejected, no server, timeout: all mean "not executing"
            log.warning("navigate goal not accepted: %s", exc)
            return DispatchResult(ok=False, ros2_topic=self.navigator.action_name,
                                  detail=str(exc))
        return DispatchResult(ok=True, ros2_topic=self.navigator.action_name, goal_id=goal_id)

    async def halt(self) -> tuple[bool, int]:
        """Zero velocity and cancel every goal; (cmd_vel reached, goals cancelled)."""
        matched_before = self.cmd_vel.matched_count() > 0
        self.cmd_vel.publish(self._twist())  # first, unconditionally: late joiners stop too
        reached = matched_before or await self._matched(self.cmd_vel)
        if reached and not matched_before:
            self.cmd_vel.publish(self._twist())  # the first preceded the match
        cancelled = 0
        if self.navigator is not None:
            try:
                cancelled = await self.navigator.cancel_all()
            except Exception:
                log.exception("cancelling navigation goals failed")
        return reached, cancelled

    async def _stop(self, applied: Mapping[str, Any]) -> DispatchResult:
        reached, cancelled = await self.halt()
        if not reached and not cancelled:
            return DispatchResult(ok=False, ros2_topic=self.cmd_vel.topic,
                                  detail=f"no subscriber on {self.cmd_vel.topic}")
        return DispatchResult(ok=True, ros2_topic=self.cmd_vel.topic)

    async def _estop(self, applied: Mapping[str, Any]) -> DispatchResult:
        # The governor has already latched; here the robot is told, and motion halted too.
        self.estop.publish({"data": True})
        told = await self._matched(self.estop)
        if told:
            self.estop.publish({"data": True})  # the first write may have preceded the match
        reached, cancelled = await self.halt()
        if not (told or reached or cancelled):
            return DispatchResult(ok=False, ros2_topic=self.estop.topic,
                                  detail=f"no subscriber on {self.estop.topic}")
        return DispatchResult(ok=True, ros2_topic=self.estop.topic)

    async def _clear_estop(self, applied: Mapping[str, Any]) -> DispatchResult:
        return await self._publish(self.estop, {"data": False})
