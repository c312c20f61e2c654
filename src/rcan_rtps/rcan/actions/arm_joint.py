"""`arm_joint`: a joint trajectory for one arm (trajectory_msgs JointTrajectory).

A robot may have several arms (`bridge.ros2.arms`), each a joint group with its own trajectory
topic; `group` names which one (it may be left out when there is one arm, or none configured:
then `joint_trajectory_topic`). One target (`positions` over `duration_s`) or several
`points`, each reached at its `time_from_start_s`.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Annotated, Any

import msgspec

from .._enums import Role
from .._types import ActionParams, Finite, JointName, Strict, whole
from ._spec import ActionSpec, Effect, Hold, Invariant, MessageKit, PathPoint, Publish

TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"
MAX_JOINTS = 64
MAX_POINTS = 1000
GroupName = Annotated[str, msgspec.Meta(pattern=whole(r"[a-z][a-z0-9_]{0,63}"))]
Seconds = Annotated[float, msgspec.Meta(gt=0.0, le=3600.0)]
Values = Annotated[list[Finite], msgspec.Meta(min_length=1, max_length=MAX_JOINTS)]


class TrajectoryPoint(Strict, frozen=True, omit_defaults=True):
    positions: Values
    time_from_start_s: Seconds
    velocities: Values | None = None


class ArmJointParams(ActionParams, frozen=True, omit_defaults=True):
    joints: Annotated[list[JointName], msgspec.Meta(min_length=1, max_length=MAX_JOINTS)]
    positions: Values | None = None  # one target, reached after `duration_s`
    duration_s: Seconds | None = None
    points: Annotated[list[TrajectoryPoint],
                      msgspec.Meta(min_length=1, max_length=MAX_POINTS)] | None = None
    group: GroupName | None = None  # the arm (`bridge.ros2.arms`)

    def __post_init__(self) -> None:
        if len(set(self.joints)) != len(self.joints):
            raise ValueError("`joints` must not repeat a name")
        if (self.points is None) == (self.positions is None):
            raise ValueError("give either `positions` with `duration_s`, or `points`")
        if self.positions is not None and self.duration_s is None:
            raise ValueError("`positions` needs `duration_s`")
        if self.points is not None and self.duration_s is not None:
            raise ValueError("`duration_s` goes with `positions`; each point has its own time")
        for point in self.trajectory():
            _check_point(point, len(self.joints))
        # Compared as sent (whole nanoseconds, `_duration`): times that round together
        # would be one instant to the controller, and the bridge's model of the trajectory
        # (a stop's hold, bridge/desired_path.py) would not be what the controller runs.
        sent = [_nanoseconds(p.time_from_start_s) for p in self.trajectory()]
        if sent[0] < 1 or any(b <= a for a, b in itertools.pairwise(sent)):
            raise ValueError("`time_from_start_s` must increase from point to point, by at "
                             "least 1 ns (from 0 too)")

    def trajectory(self) -> list[TrajectoryPoint]:
        """The points, whichever form was given."""
        if self.points is not None:
            return self.points
        assert self.positions is not None and self.duration_s is not None
        return [TrajectoryPoint(positions=self.positions, time_from_start_s=self.duration_s)]


def _check_point(point: TrajectoryPoint, joints: int) -> None:
    if len(point.positions) != joints:
        raise ValueError("`positions` must have one entry per joint")
    if point.velocities is not None and len(point.velocities) != joints:
        raise ValueError("`velocities` must have one entry per joint")


def _nanoseconds(seconds: float) -> int:
    duration = _duration(seconds)
    return duration["sec"] * 1_000_000_000 + duration["nanosec"]


def _duration(seconds: float) -> dict[str, int]:
    # Rounded once, as a whole: rounding the fraction alone sent 0.9999999999 s as 0 s.
    sec, nanosec = divmod(round(seconds * 1e9), 1_000_000_000)
    return {"sec": sec, "nanosec": nanosec}


def trajectory(params: ArmJointParams, kit: MessageKit) -> dict[str, Any]:
    # A zero header stamp tells joint_trajectory_controller to start at once.
    return {"joint_names": list(params.joints),
            "points": [{"positions": list(p.positions),
                        "velocities": list(p.velocities or ()),
                        "time_from_start": _duration(p.time_from_start_s)}
                       for p in params.trajectory()]}


def held_where_measured(joints: Sequence[str], positions: Sequence[float],
                        kit: MessageKit) -> dict[str, Any]:
    """What joint_trajectory_controller does itself when a goal is cancelled: one point, at
    the measured positions, at rest, due at once (a zero stamp: now). It replaces the
    trajectory running (the topic interface has no cancel; an empty trajectory is refused)."""
    return {"joint_names": list(joints),
            "points": [{"positions": list(positions), "velocities": [0.0] * len(joints),
                        "time_from_start": _duration(0.0)}]}


def _runs_for_s(params: ArmJointParams) -> float:
    return params.trajectory()[-1].time_from_start_s


def _path(params: ArmJointParams) -> list[PathPoint]:
    """The points as `trajectory` sends them (its velocities: none unless given)."""
    return [PathPoint(tuple(p.positions),
                      tuple(p.velocities) if p.velocities is not None else None,
                      p.time_from_start_s)
            for p in params.trajectory()]


SPEC = ActionSpec(
    order=20,
    name="arm_joint",
    summary="Move one arm's named joints (rad or m): to `positions` over `duration_s`, "
            "or through `points`.",
    params=ArmJointParams,
    effect=Effect.MOTION,
    default_role=Role.USER,
    ros=Publish(topic_key="joint_trajectory_topic", type_name=TRAJECTORY, build=trajectory,
                group_key="arms",
                hold=Hold(joints=lambda p: p.joints, runs_for_s=_runs_for_s,
                          build=held_where_measured, path=_path)),
    invariants=(Invariant.ESTOP_GUARD, Invariant.FINITE, Invariant.JOINT_GROUP),
    example={"joints": ["elbow"], "positions": [0.8], "duration_s": 0.5},
)
