"""`move`: one velocity command (geometry_msgs Twist, or TwistStamped if configured)."""

from __future__ import annotations

from typing import Any

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
    summary="Drive at a velocity (m/s, rad/s), clamped to the safety limits.",
    params=MoveParams,
    effect=Effect.MOTION,
    default_role=Role.USER,
    ros=Publish(topic_key="cmd_vel_topic", type_key="cmd_vel_type", build=velocity),
    invariants=(Invariant.ESTOP_GUARD, Invariant.FINITE, Invariant.VELOCITY),
)
