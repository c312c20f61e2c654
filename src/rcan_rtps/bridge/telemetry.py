"""ROS 2 telemetry → RCAN STATUS (spec §4, profile STATUS).

Subscriptions keep the latest odometry, joint states, diagnostics and battery; `status()`
derives the state machine from them:

    estop      the governor's e-stop latch is engaged
    fault      any DiagnosticStatus is ERROR (or has a level DiagnosticStatus does not define),
               or more components are in fault than STATUS lists (bridge/faults.py)
    offline    no telemetry for `telemetry_stale_s` (or none yet)
    safe_stop  a control session was lost, until the next command
    executing  a goal (navigation, docking) is active
    moving     odometry reports motion: any of its twist's six components not at rest (a
               holonomic base moving along y included; not a number is not at rest)
    idle       otherwise

What it copies is bounded, whatever the robot's nodes send: faults (`faults.FaultTable`),
joints (`joints.bounded_joints`), other publishers on the command topics (`MAX_FOREIGN`,
told by `commanders.CommanderWatch`). Another publisher on a topic the bridge commands the
robot on is a WARN fault of that topic, unless it is expected (declared in
`bridge.ros2.foreign_publishers.expected`). One on a motion topic while the e-stop is latched
is the fault `ESTOP_NOT_HOLDING`, first: the robot obeys it, and the latch cannot hold it.
That fault is never left out; it is an ERROR unless every such publisher is expected *and*
the robot is seen still (fresh odometry at rest, and, for a publisher on a trajectory
topic, every joint's reported velocity at rest), when it is a WARN that says the same (the
operator declared them, and nothing moves the robot now; the moment it moves, or its
telemetry goes stale, it is an ERROR again).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from ..config import RcanConfig
from ..events import Events
from ..rcan import (
    Fault,
    ForeignPublisher,
    Joints,
    Navigation,
    Position,
    RobotPosition,
    RosInfo,
    Status,
    Telemetry,
    Velocity,
    invoke_caps,
)
from ..ros import qos
from ..ros.participant import RosNode
from ..ros.rostime import quaternion_to_yaw
from .faults import FaultTable, Level
from .hostcpu import CpuMeter
from .joint_positions import JointPositions
from .joints import bounded_joints

log = logging.getLogger(__name__)
_OK = 0
_LEVELS: dict[int, Level] = {1: "WARN", 2: "ERROR", 3: "STALE"}
MAX_FOREIGN = 32  # other publishers STATUS lists (all are counted)
ESTOP_NOT_HOLDING = "rcan_rtps/estop_not_holding"
FOREIGN_PUBLISHER = "rcan_rtps/foreign_publisher"  # + the topic
_MOVING_EPS = 1e-3  # m/s or rad/s below which the robot counts as still


def _level(raw: Any) -> int:
    return raw[0] if isinstance(raw, (bytes, bytearray)) else int(raw)


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


class TelemetryState:
    """Latest robot telemetry, written from the node's reader thread, read by the API."""

    def __init__(self, node: RosNode, config: RcanConfig, *,
                 estop_latched: Callable[[], bool], active_goals: Callable[[], list[str]],
                 navigation: Callable[[], Navigation | None] = lambda: None,
                 monotonic: Callable[[], float] = time.monotonic,
                 events: Events | None = None,
                 joint_positions: JointPositions | None = None) -> None:
        self.config = config
        # Where the joints an arm hold needs are (`arm_holds`): told every JointState.
        self._joint_positions = joint_positions or JointPositions()
        self._estop_latched = estop_latched
        self._active_goals = active_goals
        self._navigation = navigation
        self._monotonic = monotonic
        self._lock = threading.Lock()
        self._last_rx: float | None = None
        # When odometry and a JointState last came: "seen still" needs them fresh, whatever
        # else the robot's nodes keep sending (`_Stillness`).
        self._odom_rx: float | None = None
        self._twist_at_rest = False  # the last odometry's whole twist (not only x and yaw)
        self._joints_rx: float | None = None
        self._position: Position | None = None
        self._yaw: float | None = None
        self._velocity: Velocity | None = None
        self._joints: Joints | None = None
        self._battery: float | None = None
        self._battery_v: float | None = None
        self._faults = FaultTable()
        self._foreign: list[ForeignPublisher] = []
        self._foreign_motion: list[str] = []  # motion topics among theirs
        # The joints the bridge commands: listed first when a JointState is cut.
        self._commanded_joints = frozenset(
            j for arm in config.bridge.ros2.arms.values() for j in arm.joints)
        self._base_topic = config.bridge.ros2.resolve(config.bridge.ros2.cmd_vel_topic)
        self._arm_joints = {config.bridge.ros2.resolve(arm.topic): frozenset(arm.joints)
                            for arm in config.bridge.ros2.arms.values()}
        self.safe_stopped = False
        self._caps = invoke_caps(config.bridge.skills)  # fixed for the run, as its skills
        self._started = monotonic()
        self._cpu = CpuMeter()
        self._seq = 0
        self._last_us = 0
        # Told (on the reader thread, or the loop) when what STATUS shows may have changed.
        self.events = events or Events()
        ros2 = config.bridge.ros2
        self.domain_id = node.domain_id
        self._own_hardware_id = node.fqn  # what the bridge's DiagnosticsNotifier signs with
        self.distro = node.store.distro
        # Sensor-data QoS (best effort) matches both reliable and best-effort publishers.
        sensor = qos.SENSOR_DATA.with_(depth=10)
        self.subscriptions = [
            node.create_subscription(ros2.odom_topic, "nav_msgs/msg/Odometry", sensor,
                                     callback=self._on_odom),
            node.create_subscription(ros2.joint_states_topic, "sensor_msgs/msg/JointState",
                                     sensor, callback=self._on_joints),
            node.create_subscription(ros2.diagnostics_topic,
                                     "diagnostic_msgs/msg/DiagnosticArray", sensor,
                                     callback=self._on_diagnostics),
            node.create_subscription(ros2.battery_topic, "sensor_msgs/msg/BatteryState", sensor,
                                     callback=self._on_battery),
        ]

    def close(self) -> None:
        """Stops the deliveries (none after this returns); idempotent."""
        for subscription in self.subscriptions:
            subscription.close()

    # -- DDS side (the node's reader thread) --------------------------------------------
    def _touch(self) -> bool:
        """Note a sample; True if the robot was silent until now (STATUS: connected)."""
        now, last = self._monotonic(), self._last_rx
        self._last_rx = now
        return last is None or now - last > self.config.bridge.ros2.telemetry_stale_s

    def _tell(self, changed: bool) -> None:
        if changed:
            self.events.robot.emit()

    def _on_odom(self, msg: Any) -> None:
        p, twist = msg.pose.pose, msg.twist.twist
        with self._lock:
            was_moving = self._odom_moving()
            self._position = Position(p.position.x, p.position.y, p.position.z)
            self._yaw = quaternion_to_yaw(p.orientation)
            self._velocity = Velocity(twist.linear.x, twist.angular.z)
            self._twist_at_rest = _at_rest(twist)
            self._odom_rx = self._monotonic()
            changed = self._touch() or was_moving != self._odom_moving()
        self._tell(changed)

    def _odom_moving(self) -> bool:
        """The last odometry's whole twist is not at rest (none yet: not moving)."""
        return self._velocity is not None and not self._twist_at_rest

    def _on_joints(self, msg: Any) -> None:
        info = getattr(msg, "sample_info", None)  # whose: two senders may disagree
        self._joint_positions.heard(msg.name, msg.position, msg.velocity,
                                    None if info is None else info.publication_handle)
        with self._lock:
            self._joints = bounded_joints(msg.name, msg.position, msg.velocity,
                                          self._commanded_joints)
            self._joints_rx = self._monotonic()
            changed = self._touch()
        self._tell(changed)

    def _on_diagnostics(self, msg: Any) -> None:
        # The bridge's own notices (a HiTL approval waiting) are not the robot's faults, nor
        # a sign of the robot's life: those are in `pending_auth`.
        statuses = [s for s in msg.status if s.hardware_id != self._own_hardware_id]
        if not statuses:
            return
        with self._lock:
            before = self._faults.faults()
            for status in statuses:
                level = _level(status.level)
                if level == _OK:  # OK clears what this component reported before
                    self._faults.report(status.name, None, status.message)
                elif level in _LEVELS:
                    self._faults.report(status.name, _LEVELS[level], status.message)
                else:  # a level DiagnosticStatus does not define is not "fine": fail closed
                    self._faults.report(
                        status.name, "ERROR",
                        f"unknown diagnostic level {level}: {status.message}")
            changed = self._touch() or before != self._faults.faults()
        self._tell(changed)

    def _on_battery(self, msg: Any) -> None:
        with self._lock:
            before = self._battery
            pct = _finite_or_none(float(msg.percentage))
            self._battery = None if pct is None else max(0.0, min(100.0, pct * 100.0))
            self._battery_v = _finite_or_none(float(msg.voltage))
            changed = self._touch() or before != self._battery
        self._tell(changed)

    def foreign_publishers(self, found: list[ForeignPublisher], motion_topics: set[str]) -> None:
        """Other participants now publishing on the command topics (`motion_topics`: those
        that move the robot); called from the loop, never holding a DDS call. The unexpected
        ones first: STATUS lists MAX_FOREIGN, and any participant may claim an expected
        node's name (governance.md), so those must not push an unexpected one out."""
        found = sorted(found, key=lambda f: (f.expected, f.topic, f.node or "", f.participant))
        motion = sorted({f.topic for f in found if f.topic in motion_topics})
        with self._lock:
            changed = found != self._foreign or motion != self._foreign_motion
            self._foreign, self._foreign_motion = found, motion
        self._tell(changed)

    def mark_safe_stop(self) -> None:
        changed, self.safe_stopped = not self.safe_stopped, True
        self._tell(changed)

    def clear_safe_stop(self) -> None:
        changed, self.safe_stopped = self.safe_stopped, False
        self._tell(changed)

    # -- API side --------------------------------------------------------------------------
    def _stale(self, last: float | None) -> bool:
        return last is None or self._monotonic() - last > self.config.bridge.ros2.telemetry_stale_s

    def age_s(self) -> float | None:
        return None if self._last_rx is None else self._monotonic() - self._last_rx

    def status(self, *, pending_auth: int, counted: bool = True) -> Status:
        """STATUS now; `counted=False`: a look that takes no `seq` (the mDNS advert's: the
        STATUS clients see keep their sequence without gaps)."""
        with self._lock:
            age = self.age_s()
            faults = self._faults.faults()
            foreign, foreign_motion = self._foreign, self._foreign_motion
            telemetry = Telemetry(self._position, self._yaw, self._velocity, self._joints)
            battery, volts = self._battery, self._battery_v
            self._seq += counted
            now_us = self._last_us = max(time.time_ns() // 1000, self._last_us + 1)
            seq = self._seq
            odom_stale, joints_stale = self._stale(self._odom_rx), self._stale(self._joints_rx)
            twist_at_rest = self._twist_at_rest
            moving = self._odom_moving()
        goals = self._active_goals()
        navigation = self._navigation() if goals else None
        stale = age is None or age > self.config.bridge.ros2.telemetry_stale_s
        estop = self._estop_latched()
        still = _Stillness(odom_stale or not twist_at_rest, joints_stale, telemetry,
                           self._base_topic, self._arm_joints)
        faults = _commander_faults(estop, foreign, foreign_motion, still) + faults
        return Status(
            ruri=self.config.robot.ruri, state=self._state(estop, faults, stale, goals, moving),
            estop=estop, battery_pct=battery, telemetry=telemetry, faults=faults,
            active_goals=goals, pending_auth=pending_auth,
            ros=RosInfo(self.domain_id, self.distro, not stale,
                        None if age is None else round(age, 3)),
            timestamp_ms=now_us // 1000, navigation=navigation,
            battery_percent=battery, battery_v=volts, cpu_percent=self._cpu.percent(),
            uptime_ms=int((self._monotonic() - self._started) * 1000), seq=seq,
            timestamp_us=now_us, position=_position(telemetry),
            foreign_publishers=foreign[:MAX_FOREIGN], foreign_publishers_count=len(foreign),
            caps=self._caps,
        )

    def _state(self, estop: bool, faults: list[Fault], stale: bool, goals: list[str],
               moving: bool) -> Any:
        if estop:
            return "estop"
        if any(f.level == "ERROR" for f in faults):
            return "fault"
        if stale:
            return "offline"
        if self.safe_stopped:
            return "safe_stop"
        if goals:
            return "executing"
        # The whole twist, as the e-stop's stillness reads it: STATUS's velocity (linear x,
        # angular z) does not show a holonomic base moving along y.
        return "moving" if moving else "idle"


class _Stillness:
    """Whether the robot is seen at rest, for the motion topics some publishers are on:
    fresh odometry at rest for the velocity topic (`odom_stale` is also true when its twist
    is not wholly at rest, which `telemetry.velocity` does not show); for any other (a
    trajectory topic) also a fresh JointState whose every listed joint reports a velocity at
    rest, and which lists the joints of the arms on those topics (`arm_joints`: resolved
    topic -> the arm's configured joints; an arm with none, or a topic of no arm, needs every
    joint of the JointState, so one cut short is not enough). What is not known is not
    still, and each is fresh by its own age: diagnostics or a battery still coming say
    nothing of a robot whose odometry has stopped."""

    def __init__(self, odom_stale: bool, joints_stale: bool, telemetry: Telemetry,
                 base_topic: str, arm_joints: Mapping[str, frozenset[str]]) -> None:
        self.odom_stale, self.joints_stale = odom_stale, joints_stale
        self.telemetry, self.base_topic, self.arm_joints = telemetry, base_topic, arm_joints

    def __call__(self, topics: set[str]) -> bool:
        velocity, joints = self.telemetry.velocity, self.telemetry.joints
        if self.odom_stale or velocity is None or _moving(velocity):
            return False
        if topics <= {self.base_topic}:
            return True
        if self.joints_stale or joints is None or \
                not len(joints.velocities) == len(joints.names) > 0 or \
                not all(abs(v) <= _MOVING_EPS for v in joints.velocities):
            return False
        arms = [self.arm_joints.get(t, frozenset()) for t in topics - {self.base_topic}]
        if any(not arm for arm in arms):  # any joint may be the arm's: all must be seen
            return joints.count is None or joints.count == len(joints.names)
        return frozenset().union(*arms) <= set(joints.names)


def _commander_faults(estop: bool, foreign: list[ForeignPublisher], motion: list[str],
                      still: Callable[[set[str]], bool]) -> list[Fault]:
    """What other publishers on the command topics mean for the robot: first, while the
    e-stop is latched and one publishes motion, that the latch cannot hold the robot; then a
    WARN per topic with an unexpected one."""
    faults = []
    if estop and motion:
        faults.append(_estop_not_holding(foreign, set(motion), still))
    surprising = [f for f in foreign if not f.expected]
    for topic in sorted({f.topic for f in surprising}):
        faults.append(Fault(f"{FOREIGN_PUBLISHER}:{topic}", (
            f"another participant publishes on {topic}, which the bridge commands the robot "
            f"on: the robot obeys it too ({_who(surprising, {topic})})"), "WARN"))
    return faults


def _estop_not_holding(foreign: list[ForeignPublisher], motion: set[str],
                       still: Callable[[set[str]], bool]) -> Fault:
    """ERROR, unless every publisher on a motion topic is expected and the robot is seen
    still; then a WARN saying the same (the e-stop still cannot hold the robot)."""
    topics = ", ".join(sorted(motion))
    who = _who(foreign, motion)
    if any(not f.expected for f in foreign if f.topic in motion):
        return Fault(ESTOP_NOT_HOLDING, (
            f"e-stop latched, but another participant publishes on {topics}: the robot obeys "
            f"it, and the e-stop cannot hold the robot against it ({who})"), "ERROR")
    if not still(motion):
        return Fault(ESTOP_NOT_HOLDING, (
            f"e-stop latched, but the robot is not seen still and expected publishers are on "
            f"{topics} ({who}): the robot obeys them, and the e-stop cannot hold the robot "
            f"against them"), "ERROR")
    return Fault(ESTOP_NOT_HOLDING, (
        f"e-stop latched; expected publishers are on {topics} ({who}): the robot obeys them, "
        f"and the e-stop cannot hold the robot against them. The robot is still now; this is "
        f"an ERROR again if it moves"), "WARN")


def _who(foreign: list[ForeignPublisher], topics: set[str]) -> str:
    names = [(f.node or f"participant {f.participant}") + (" (expected)" if f.expected else "")
             for f in foreign if f.topic in topics]
    shown = ", ".join(dict.fromkeys(names[:4]))
    return shown + (f" and {len(names) - 4} more" if len(names) > 4 else "")


def _position(telemetry: Telemetry) -> RobotPosition | None:
    """§20.3's position from the odometry's."""
    p = telemetry.position
    return None if p is None else RobotPosition(p.x, p.y, telemetry.yaw)


def _at_rest(twist: Any) -> bool:
    """Every component of an odometry twist at rest: a holonomic base moves along y, which
    STATUS's velocity (linear x, angular z) does not show; not a number is not at rest."""
    return all(abs(float(getattr(vector, axis))) <= _MOVING_EPS
               for vector in (twist.linear, twist.angular) for axis in "xyz")


def _moving(v: Velocity | None) -> bool:
    # A velocity that is not a number (NaN) is not "still": only one known small is.
    return v is not None and not (abs(v.linear_x) <= _MOVING_EPS and
                                  abs(v.angular_z) <= _MOVING_EPS)
