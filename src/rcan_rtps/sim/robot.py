"""A simulated differential-drive robot with an arm, speaking plain ROS 2 DDS.

It is a real ROS 2 node on the wire (any rclpy tool can watch it): it integrates
`cmd_vel` (Twist or TwistStamped) into `odom` at `rate_hz`, publishes wheel and arm
`joint_states`, a `battery_state` that drains with motion (and charges while docked, see
`sim.docking`) and `diagnostics`; it halts and stays halted while `emergency_stop` is true;
its arm follows `joint_trajectory_controller/joint_trajectory`. Like ros2_control's
diff_drive controller it stops when no velocity command arrived for `cmd_timeout_s`.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from ..ros import qos
from ..ros.participant import RosNode
from ..ros.rostime import now_msg, yaw_to_quaternion

TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
ARM_JOINTS = ("shoulder_pan", "shoulder_lift", "elbow", "wrist")
# sensor_msgs/msg/BatteryState power_supply_status
CHARGING, DISCHARGING, FULL = 1, 2, 4


@dataclass
class SimParams:
    rate_hz: float = 50.0
    cmd_timeout_s: float = 0.5
    wheel_radius_m: float = 0.05
    wheel_base_m: float = 0.30
    max_linear: float = 2.0  # the sim's own physical limit, above any governed limit
    max_angular: float = 3.0
    battery_wh: float = 50.0
    idle_w: float = 5.0
    drive_w_per_mps: float = 40.0
    charge_w: float = 60.0  # what the dock supplies


@dataclass
class _ArmMotion:
    """Straight lines between the trajectory's points, each reached at its time."""

    waypoints: list[tuple[float, list[float]]]  # (seconds from `began`, positions); first at 0
    began: float

    def at(self, t: float) -> tuple[list[float], list[float], bool]:
        """(positions, velocities, finished) `t` seconds after the start."""
        for (t0, a), (t1, b) in zip(self.waypoints, self.waypoints[1:], strict=False):
            if t < t1:
                f, span = (t - t0) / (t1 - t0), t1 - t0
                return ([x + (y - x) * f for x, y in zip(a, b, strict=True)],
                        [(y - x) / span for x, y in zip(a, b, strict=True)], False)
        return list(self.waypoints[-1][1]), [0.0] * len(self.waypoints[-1][1]), True


@dataclass
class SimState:
    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    v: float = 0.0
    w: float = 0.0
    wheel_pos: list[float] = field(default_factory=lambda: [0.0, 0.0])
    arm_pos: list[float] = field(default_factory=lambda: [0.0] * len(ARM_JOINTS))
    arm_vel: list[float] = field(default_factory=lambda: [0.0] * len(ARM_JOINTS))
    energy_wh: float = 50.0
    estop: bool = False
    distance_m: float = 0.0
    docked_at: str | None = None  # the dock the robot is on (charging), until it drives off


class SimRobot:
    def __init__(self, node: RosNode, *, cmd_vel_type: str = "geometry_msgs/msg/Twist",
                 params: SimParams | None = None) -> None:
        self.node = node
        self.params = params or SimParams()
        self.state = SimState(energy_wh=self.params.battery_wh)
        self._lock = threading.Lock()
        self._cmd = (0.0, 0.0)
        self._cmd_at = -math.inf
        self._arm: _ArmMotion | None = None
        self._stamped = cmd_vel_type == TWIST_STAMPED
        latched = qos.DEFAULT.with_(depth=1, durability=qos.Durability.TRANSIENT_LOCAL)
        self.inputs = {
            "cmd_vel": node.create_subscription("cmd_vel", cmd_vel_type,
                                                callback=self._on_cmd_vel),
            "estop": node.create_subscription("emergency_stop", "std_msgs/msg/Bool", latched,
                                              callback=self._on_estop),
            "trajectory": node.create_subscription(
                "joint_trajectory_controller/joint_trajectory",
                "trajectory_msgs/msg/JointTrajectory", callback=self._on_trajectory),
        }
        self.odom = node.create_publisher("odom", "nav_msgs/msg/Odometry")
        self.joints = node.create_publisher("joint_states", "sensor_msgs/msg/JointState")
        self.battery = node.create_publisher("battery_state", "sensor_msgs/msg/BatteryState")
        self.diagnostics = node.create_publisher("diagnostics",
                                                 "diagnostic_msgs/msg/DiagnosticArray")

    # -- inputs (the node's reader thread) ------------------------------------------------
    def _on_cmd_vel(self, msg: Any) -> None:
        twist = msg.twist if self._stamped else msg
        with self._lock:
            self._cmd = (twist.linear.x, twist.angular.z)
            self._cmd_at = time.monotonic()

    def _on_estop(self, msg: Any) -> None:
        with self._lock:
            self.state.estop = bool(msg.data)
            if self.state.estop:
                self._cmd = (0.0, 0.0)
                self._arm = None

    def _on_trajectory(self, msg: Any) -> None:
        if not msg.points:
            return
        with self._lock:
            if self.state.estop:
                return
            start = list(self.state.arm_pos)
            waypoints, last, target = [(0.0, start)], 0.0, start
            for point in msg.points:
                at = point.time_from_start.sec + point.time_from_start.nanosec / 1e9
                target = list(target)
                for name, position in zip(msg.joint_names, point.positions, strict=False):
                    if name in ARM_JOINTS:
                        target[ARM_JOINTS.index(name)] = float(position)
                last = max(at, last + 1e-3)  # times must increase; a controller would refuse
                waypoints.append((last, target))
            self._arm = _ArmMotion(waypoints, time.monotonic())

    def drive(self, linear: float, angular: float) -> None:
        """A velocity command from inside the process (the navigation controller)."""
        with self._lock:
            self._cmd = (linear, angular)
            self._cmd_at = time.monotonic()

    def dock(self, dock_id: str) -> None:
        """On the dock `dock_id`: charging until the robot drives off it."""
        with self._lock:
            self.state.docked_at = dock_id

    # -- physics -----------------------------------------------------------------------------
    def step(self, dt: float) -> None:
        p, s = self.params, self.state
        with self._lock:
            fresh = time.monotonic() - self._cmd_at <= p.cmd_timeout_s
            v, w = self._cmd if fresh and not s.estop and s.energy_wh > 0 else (0.0, 0.0)
            s.v = max(-p.max_linear, min(p.max_linear, v))
            s.w = max(-p.max_angular, min(p.max_angular, w))
            s.x += s.v * math.cos(s.yaw) * dt
            s.y += s.v * math.sin(s.yaw) * dt
            s.yaw = math.atan2(math.sin(s.yaw + s.w * dt), math.cos(s.yaw + s.w * dt))
            s.distance_m += abs(s.v) * dt
            half = p.wheel_base_m / 2
            for i, sign in enumerate((-1.0, 1.0)):
                s.wheel_pos[i] += (s.v + sign * s.w * half) / p.wheel_radius_m * dt
            if s.v or s.w:
                s.docked_at = None  # driven off the dock
            power = p.idle_w + p.drive_w_per_mps * abs(s.v)
            if s.docked_at is not None:
                power -= p.charge_w
            s.energy_wh = min(p.battery_wh, max(0.0, s.energy_wh - power * dt / 3600.0))
            self._step_arm()

    def _step_arm(self) -> None:
        s, arm = self.state, self._arm
        if arm is None:
            s.arm_vel = [0.0] * len(ARM_JOINTS)
            return
        s.arm_pos, s.arm_vel, finished = arm.at(time.monotonic() - arm.began)
        if finished:
            self._arm = None

    # -- outputs -----------------------------------------------------------------------------
    def publish_odom(self) -> None:
        s = self.state
        self.odom.publish({
            "header": {"stamp": now_msg(), "frame_id": "odom"},
            "child_frame_id": "base_link",
            "pose": {"pose": {"position": {"x": s.x, "y": s.y, "z": 0.0},
                              "orientation": yaw_to_quaternion(s.yaw)}},
            "twist": {"twist": {"linear": {"x": s.v}, "angular": {"z": s.w}}},
        })

    def publish_joints(self) -> None:
        s, p = self.state, self.params
        half = p.wheel_base_m / 2
        wheel_vel = [(s.v - s.w * half) / p.wheel_radius_m, (s.v + s.w * half) / p.wheel_radius_m]
        self.joints.publish({
            "header": {"stamp": now_msg()},
            "name": ["left_wheel", "right_wheel", *ARM_JOINTS],
            "position": [*s.wheel_pos, *s.arm_pos],
            "velocity": [*wheel_vel, *s.arm_vel],
            "effort": [],
        })

    def publish_battery(self) -> None:
        s = self.state
        fraction = s.energy_wh / self.params.battery_wh
        supply = DISCHARGING if s.docked_at is None else (CHARGING if fraction < 1.0 else FULL)
        self.battery.publish({
            "header": {"stamp": now_msg()}, "voltage": 22.0 + 3.2 * fraction,
            "percentage": fraction, "present": True, "power_supply_status": supply,
        })

    def publish_diagnostics(self) -> None:
        s = self.state
        low = s.energy_wh / self.params.battery_wh < 0.1
        statuses = [
            {"level": 2 if s.energy_wh <= 0 else (1 if low else 0), "name": "sim: battery",
             "message": "empty" if s.energy_wh <= 0 else ("low" if low else "ok"),
             "hardware_id": self.node.fqn},
            {"level": 1 if s.estop else 0, "name": "sim: emergency stop",
             "message": "engaged" if s.estop else "released", "hardware_id": self.node.fqn},
            {"level": 0, "name": "sim: dock", "hardware_id": self.node.fqn,
             "message": "undocked" if s.docked_at is None else f"docked at {s.docked_at}"},
        ]
        self.diagnostics.publish({"header": {"stamp": now_msg()}, "status": statuses})

    async def run(self, stop: asyncio.Event | None = None) -> None:
        """Steps and publishes until `stop` is set (or forever)."""
        stop = stop or asyncio.Event()
        period = 1.0 / self.params.rate_hz
        tick, last = 0, time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            self.step(now - last)
            last = now
            self.publish_odom()
            if tick % max(1, round(self.params.rate_hz / 10)) == 0:  # 10 Hz
                self.publish_joints()
            if tick % max(1, round(self.params.rate_hz)) == 0:  # 1 Hz
                self.publish_battery()
                self.publish_diagnostics()
            tick += 1
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(stop.wait(), timeout=max(0.0, period - (time.monotonic()
                                                                                 - now)))
