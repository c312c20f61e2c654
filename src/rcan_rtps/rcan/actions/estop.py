"""`estop`: latch the emergency stop (any authenticated principal), tell the robot, halt."""

from __future__ import annotations

from typing import Any

from .._enums import Role
from ._spec import ActionSpec, Effect, EstopSignal, HitlDefault, Invariant, MessageKit, Publish
from .stop import HALT, StopParams

BOOL = "std_msgs/msg/Bool"


def engaged(params: StopParams, kit: MessageKit) -> dict[str, Any]:
    return {"data": True}


SPEC = ActionSpec(
    order=50,
    name="estop",
    summary="Emergency stop: latched until an OWNER clears it.",
    params=StopParams,
    effect=Effect.ESTOP,
    default_role=Role.GUEST,  # an e-stop must always be available
    ros=EstopSignal(engaged=True, halt=HALT, signal=Publish(
        topic_key="estop_topic", type_name=BOOL, latched=True, build=engaged)),
    invariants=(Invariant.FINITE,),
    hitl=HitlDefault(gateable=False),
)
