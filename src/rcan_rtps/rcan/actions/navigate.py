"""`navigate`: a Nav2 NavigateToPose goal in the navigation frame."""

from __future__ import annotations

import math
from typing import Annotated, Any

import msgspec

from .._enums import Role
from .._types import ActionParams, Finite
from ._spec import ActionSpec, Effect, Invariant, MessageKit, SendGoal

NAVIGATE_TO_POSE = "nav2_msgs/action/NavigateToPose"


class NavigateParams(ActionParams, frozen=True):
    x: Finite
    y: Finite
    yaw: Finite
    frame_id: Annotated[str, msgspec.Meta(min_length=1, max_length=128)] | None = None


def goal(params: NavigateParams, kit: MessageKit) -> dict[str, Any]:
    half = params.yaw / 2.0
    frame_id = params.frame_id or kit.setting("nav_frame_id")
    return {"pose": {"header": {"stamp": kit.now(), "frame_id": frame_id},
                     "pose": {"position": {"x": params.x, "y": params.y, "z": 0.0},
                              "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(half),
                                              "w": math.cos(half)}}}}


SPEC = ActionSpec(
    order=30,
    name="navigate",
    summary="Drive to a pose (x, y in m, yaw in rad) with Nav2; inside the workspace.",
    params=NavigateParams,
    effect=Effect.MOTION,
    default_role=Role.USER,
    ros=SendGoal(action_key="nav_action", type_name=NAVIGATE_TO_POSE, build=goal),
    invariants=(Invariant.ESTOP_GUARD, Invariant.FINITE, Invariant.WORKSPACE),
    starts_goal=True,
)
