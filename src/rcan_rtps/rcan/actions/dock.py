"""`dock`: a Nav2 DockRobot goal (opennav_docking): drive onto a dock of the robot's own.

The dock is named by its id in the docking server's dock database; where it is is the robot's
configuration, not the command's, so there are no coordinates to check against the workspace.
It drives the base: motion, guarded by the e-stop and arbitrated like `navigate`. FINITE has
no number of its own to check (a declared `bool` is a flag, not a number) and keeps any future
one honest.
"""

from __future__ import annotations

from typing import Annotated, Any

import msgspec

from .._enums import Role
from .._types import ActionParams
from ._spec import ActionSpec, Effect, Invariant, MessageKit, SendGoal

DOCK_ROBOT = "nav2_msgs/action/DockRobot"


class DockParams(ActionParams, frozen=True):
    dock_id: Annotated[str, msgspec.Meta(min_length=1, max_length=128)]
    # False: the robot is already at the dock's staging pose (nav2 then skips driving there).
    navigate_to_staging_pose: bool = True


def goal(params: DockParams, kit: MessageKit) -> dict[str, Any]:
    # By id: the docking server knows the dock's pose and type (the rest take their defaults).
    return {"use_dock_id": True, "dock_id": params.dock_id,
            "navigate_to_staging_pose": params.navigate_to_staging_pose}


SPEC = ActionSpec(
    order=35,
    name="dock",
    summary=("Dock at a dock of the robot's dock database (`dock_id`) with Nav2's docking "
             "server; drives the base."),
    params=DockParams,
    effect=Effect.MOTION,
    default_role=Role.USER,
    ros=SendGoal(action_key="dock_action", type_name=DOCK_ROBOT, build=goal),
    invariants=(Invariant.ESTOP_GUARD, Invariant.FINITE),
    starts_goal=True,
    example={"dock_id": "home"},
)
