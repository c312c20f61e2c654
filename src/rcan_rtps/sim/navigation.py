"""The simulated robot's nav2 `NavigateToPose` action server.

A plain go-to-goal controller: turn towards the goal, drive, then turn to the goal's
yaw; feedback carries the pose, distance remaining and an ETA. Cancel stops the robot;
an engaged e-stop aborts the goal. The sim's map frame is its odometry frame.
"""

from __future__ import annotations

import asyncio
import math
import time
from typing import Any

from ..ros.action_server import ActionServer, ServerGoal
from ..ros.rostime import duration_msg, now_msg, quaternion_to_yaw, yaw_to_quaternion
from .robot import SimRobot, SimState

ACTION_TYPE = "nav2_msgs/action/NavigateToPose"
POSITION_TOLERANCE_M = 0.05
YAW_TOLERANCE_RAD = 0.05
CRUISE_MPS = 0.5
TURN_RADPS = 1.0
CONTROL_HZ = 20.0


def _wrap(angle: float) -> float:
    return math.atan2(math.sin(angle), math.cos(angle))


def steer(s: SimState, gx: float, gy: float, gyaw: float) -> tuple[float, float, float, bool]:
    """(linear, angular, distance, done) for one control step towards a pose."""
    distance = math.hypot(gx - s.x, gy - s.y)
    if distance > POSITION_TOLERANCE_M:
        heading = _wrap(math.atan2(gy - s.y, gx - s.x) - s.yaw)
        turn = max(-TURN_RADPS, min(TURN_RADPS, 2.0 * heading))
        # Drive only when roughly facing the goal; slow down on approach.
        speed = 0.0 if abs(heading) > 0.5 else min(CRUISE_MPS, distance)
        return speed, turn, distance, False
    yaw_error = _wrap(gyaw - s.yaw)
    if abs(yaw_error) > YAW_TOLERANCE_RAD:
        return 0.0, max(-TURN_RADPS, min(TURN_RADPS, 2.0 * yaw_error)), distance, False
    return 0.0, 0.0, distance, True


class NavigationServer:
    def __init__(self, robot: SimRobot, action: str = "navigate_to_pose") -> None:
        self.robot = robot
        self.server = ActionServer(robot.node, action, ACTION_TYPE, self._execute)

    def _feedback(self, started: float, distance: float) -> dict[str, Any]:
        s = self.robot.state
        return {
            "current_pose": {"header": {"stamp": now_msg(), "frame_id": "map"},
                             "pose": {"position": {"x": s.x, "y": s.y, "z": 0.0},
                                      "orientation": yaw_to_quaternion(s.yaw)}},
            "navigation_time": duration_msg(time.monotonic() - started),
            "estimated_time_remaining": duration_msg(distance / CRUISE_MPS),
            "number_of_recoveries": 0,
            "distance_remaining": distance,
        }

    async def _execute(self, goal: ServerGoal) -> dict[str, Any]:
        request: Any = goal.goal
        pose = request.pose.pose
        gx, gy, gyaw = pose.position.x, pose.position.y, quaternion_to_yaw(pose.orientation)
        started = time.monotonic()
        while True:
            if goal.cancel_requested.is_set():
                self.robot.drive(0.0, 0.0)
                goal.canceled()
                return {}
            if self.robot.state.estop:
                goal.abort()
                return {"error_code": 9999, "error_msg": "emergency stop engaged"} \
                    if self._has_error_fields() else {}
            linear, angular, distance, done = steer(self.robot.state, gx, gy, gyaw)
            self.robot.drive(linear, angular)
            goal.publish_feedback(self._feedback(started, distance))
            if done:
                return {}
            await asyncio.sleep(1.0 / CONTROL_HZ)

    def _has_error_fields(self) -> bool:
        result = self.robot.node.store.message(ACTION_TYPE + "_Result")
        return any(f.name == "error_msg" for f in result.fields)

    async def close(self) -> None:
        await self.server.close()
