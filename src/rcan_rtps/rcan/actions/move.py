"""`move`: drive at a velocity (geometry_msgs Twist, or TwistStamped if configured).

The velocity is streamed: republished at `bridge.ros2.cmd_rate_hz` for `duration_s` seconds
(at most `safety.max_move_duration_s`), or, without `duration_s`, held until `stop`, the next
move, an e-stop, the loss of the sender's control session or of the robot; then zero.
"""

from __future__ import annotations

from typing import Annotated, Any

import msgspec

from .._enums import Role
from .._types import ActionParams, Finite
from ._spec import ActionSpec, Effect, Invariant, MessageKit, Publish

TWIST = "geometry_msgs/msg/Twist"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
VECTOR3 = "geometry_msgs/msg/Vector3"


class MoveParams(ActionParams, frozen=True):
    linear_x: Finite = 0.0
    linear_y: Finite = 0.0
    angular_z: Finite = 0.0
    duration_s: Annotated[float, msgspec.Meta(gt=0.0, le=86400.0)] | None = None  # None: held


class RampedMove(MoveParams, frozen=True):
    """A move as governed: the ramp from the velocity commanded when it was decided."""

    ramp_from: list[float] = msgspec.field(default_factory=lambda: [0.0, 0.0, 0.0])  # x, y, z
    ramp_s: float = 0.0  # how long the acceleration limits take to reach the target


def velocity(params: MoveParams, kit: MessageKit) -> Any:
    # Built directly (the hot path): the governor has already checked these numbers.
    vec = kit.struct(VECTOR3)
    twist = kit.struct(TWIST)(linear=vec(float(params.linear_x), float(params.linear_y), 0.0),
                              angular=vec(0.0, 0.0, float(params.angular_z)))
    if kit.message_type != TWIST_STAMPED:
        return twist
    header = kit.struct("std_msgs/msg/Header")(stamp=kit.struct(
        "builtin_interfaces/msg/Time")(**kit.now()), frame_id="")
    return kit.struct(TWIST_STAMPED)(header=header, twist=twist)


SPEC = ActionSpec(
    order=10,
    name="move",
    summary=("Drive at a velocity (m/s, rad/s), clamped to the safety limits and ramped "
             "within the acceleration limits, for `duration_s` or until stopped."),
    params=MoveParams,
    effect=Effect.MOTION,
    default_role=Role.USER,
    ros=Publish(topic_key="cmd_vel_topic", type_key="cmd_vel_type", build=velocity),
    invariants=(Invariant.ESTOP_GUARD, Invariant.FINITE, Invariant.VELOCITY,
                Invariant.DURATION, Invariant.ACCELERATION),
    streamed=True,
)
