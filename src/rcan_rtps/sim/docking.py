"""The simulated robot's nav2 `DockRobot` action server (as opennav_docking serves it).

The sim's world has docks at fixed places (`DOCKS`, by id; a goal may also give a dock pose).
Docking drives to the dock's staging pose (STAGING_OFFSET_M in front of it, facing it) unless
the goal says the robot is there already, then straight onto the dock; once on it the robot
charges (its battery_state says so) until it drives off. Feedback carries the docking state
and time; an unknown dock, a staging pose not reached within `max_staging_time`, or a robot
too far from the staging pose to see the dock fail with nav2's error codes. Cancel stops the
robot; an engaged e-stop aborts the goal.
"""

from __future__ import annotations

import asyncio
import math
import time
from dataclasses import dataclass
from typing import Any

from ..ros.action_server import ActionServer, ServerGoal
from ..ros.rostime import duration_msg, quaternion_to_yaw
from .navigation import CONTROL_HZ, steer
from .robot import SimRobot

ACTION_TYPE = "nav2_msgs/action/DockRobot"
# nav2_msgs/action/DockRobot: result error codes, feedback states.
DOCK_NOT_IN_DB, FAILED_TO_STAGE, FAILED_TO_DETECT_DOCK, UNKNOWN = 901, 903, 904, 999
NAV_TO_STAGING_POSE, INITIAL_PERCEPTION, CONTROLLING, WAIT_FOR_CHARGE = 1, 2, 3, 4
STAGING_OFFSET_M = 0.5  # nav2's staging_x_offset: where the final approach starts
DETECTION_RANGE_M = 0.3  # the dock is seen from this close to its staging pose
CHARGE_WAIT_STEPS = 3  # control steps in WAIT_FOR_CHARGE (the sim's charger starts at once)


@dataclass(frozen=True)
class Dock:
    """Where the robot stands when docked, facing the dock."""

    x: float
    y: float
    yaw: float

    def staging(self) -> tuple[float, float, float]:
        return (self.x - STAGING_OFFSET_M * math.cos(self.yaw),
                self.y - STAGING_OFFSET_M * math.sin(self.yaw), self.yaw)

    def pose(self) -> tuple[float, float, float]:
        return self.x, self.y, self.yaw


# Behind the robot's start (it starts at the origin facing +x): a dock it backs away from.
DOCKS = {"home": Dock(x=-1.5, y=0.0, yaw=math.pi)}


class DockingServer:
    def __init__(self, robot: SimRobot, action: str = "dock_robot",
                 docks: dict[str, Dock] | None = None) -> None:
        self.robot = robot
        self.docks = dict(DOCKS if docks is None else docks)
        self.server = ActionServer(robot.node, action, ACTION_TYPE, self._execute)

    def _dock(self, request: Any) -> tuple[str, Dock | None]:
        if not request.use_dock_id:
            pose = request.dock_pose.pose
            return "pose", Dock(pose.position.x, pose.position.y,
                                quaternion_to_yaw(pose.orientation))
        return str(request.dock_id), self.docks.get(request.dock_id)

    async def _execute(self, goal: ServerGoal) -> dict[str, Any]:
        request: Any = goal.goal
        started = time.monotonic()
        dock_id, dock = self._dock(request)
        if dock is None:
            return self._fail(goal, DOCK_NOT_IN_DB, f"no dock {dock_id!r} in the database")
        if request.navigate_to_staging_pose:
            ended = await self._drive(goal, NAV_TO_STAGING_POSE, dock.staging(), started,
                                      started + float(request.max_staging_time))
        else:
            ended = self._detect(goal, dock, started)
        ended = ended or await self._drive(goal, CONTROLLING, dock.pose(), started)
        if ended is not None:
            return ended
        self.robot.dock(dock_id)
        for _ in range(CHARGE_WAIT_STEPS):  # as nav2 does, until the charger is seen to charge
            goal.publish_feedback(self._feedback(WAIT_FOR_CHARGE, started))
            await asyncio.sleep(1.0 / CONTROL_HZ)
        return {"success": True}

    def _detect(self, goal: ServerGoal, dock: Dock, started: float) -> dict[str, Any] | None:
        """Without staging, the robot must already be where the dock is in view."""
        goal.publish_feedback(self._feedback(INITIAL_PERCEPTION, started))
        s = self.robot.state
        sx, sy, _ = dock.staging()
        if math.hypot(sx - s.x, sy - s.y) > DETECTION_RANGE_M:
            return self._fail(goal, FAILED_TO_DETECT_DOCK,
                              "dock not detected: the robot is not at its staging pose")
        return None

    async def _drive(self, goal: ServerGoal, state: int, target: tuple[float, float, float],
                     started: float, deadline: float = math.inf) -> dict[str, Any] | None:
        """Drives to `target`: None once there, else the result the goal ended with."""
        while True:
            if goal.cancel_requested.is_set():
                self.robot.drive(0.0, 0.0)
                goal.canceled()
                return {"success": False}
            if self.robot.state.estop:
                return self._fail(goal, UNKNOWN, "emergency stop engaged")
            if time.monotonic() > deadline:
                return self._fail(goal, FAILED_TO_STAGE,
                                  "staging pose not reached within max_staging_time")
            linear, angular, _, done = steer(self.robot.state, *target)
            self.robot.drive(linear, angular)
            goal.publish_feedback(self._feedback(state, started))
            if done:
                return None
            await asyncio.sleep(1.0 / CONTROL_HZ)

    def _fail(self, goal: ServerGoal, code: int, message: str) -> dict[str, Any]:
        self.robot.drive(0.0, 0.0)
        goal.abort()
        return {"success": False, "error_code": code, "error_msg": message}

    @staticmethod
    def _feedback(state: int, started: float) -> dict[str, Any]:
        return {"state": state, "docking_time": duration_msg(time.monotonic() - started),
                "num_retries": 0}

    async def close(self) -> None:
        await self.server.close()
