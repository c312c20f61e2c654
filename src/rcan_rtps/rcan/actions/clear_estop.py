"""`clear_estop`: unlatch the emergency stop and tell the robot."""

from __future__ import annotations

from typing import Any

from .._enums import Role
from ._spec import ActionSpec, Effect, EstopSignal, Invariant, MessageKit, Publish
from .estop import BOOL
from .stop import NoParams


def released(params: NoParams, kit: MessageKit) -> dict[str, Any]:
    return {"data": False}


SPEC = ActionSpec(
    order=60,
    name="clear_estop",
    summary="Clear the emergency stop (the robot may move again).",
    params=NoParams,
    effect=Effect.CLEAR_ESTOP,
    default_role=Role.OWNER,
    ros=EstopSignal(engaged=False, signal=Publish(
        topic_key="estop_topic", type_name=BOOL, latched=True, build=released)),
    invariants=(Invariant.FINITE,),
)
