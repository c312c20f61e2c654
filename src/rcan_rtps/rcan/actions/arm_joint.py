"""`arm_joint`: move named joints to positions (trajectory_msgs JointTrajectory)."""

from __future__ import annotations

import math
from typing import Annotated, Any

import msgspec

from .._enums import Role
from .._types import ActionParams, Finite, JointName
from ._spec import ActionSpec, Effect, Invariant, MessageKit, Publish

TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"


class ArmJointParams(ActionParams, frozen=True):
    joints: Annotated[list[JointName], msgspec.Meta(min_length=1, max_length=64)]
    positions: Annotated[list[Finite], msgspec.Meta(min_length=1, max_length=64)]
    duration_s: Annotated[float, msgspec.Meta(gt=0.0, le=3600.0)]

    def __post_init__(self) -> None:
        if len(self.positions) != len(self.joints):
            raise ValueError("`positions` must have one entry per joint")
        if len(set(self.joints)) != len(self.joints):
            raise ValueError("`joints` must not repeat a name")


def trajectory(params: ArmJointParams, kit: MessageKit) -> dict[str, Any]:
    # A zero header stamp tells joint_trajectory_controller to start at once.
    whole = math.floor(params.duration_s)
    duration = {"sec": int(whole),
                "nanosec": round((params.duration_s - whole) * 1e9) % 1_000_000_000}
    return {"joint_names": list(params.joints),
            "points": [{"positions": list(params.positions), "time_from_start": duration}]}


SPEC = ActionSpec(
    order=20,
    name="arm_joint",
    summary="Move named joints to positions (rad or m) over `duration_s`.",
    params=ArmJointParams,
    effect=Effect.MOTION,
    default_role=Role.USER,
    ros=Publish(topic_key="joint_trajectory_topic", type_name=TRAJECTORY, build=trajectory),
    invariants=(Invariant.ESTOP_GUARD, Invariant.FINITE),
)
