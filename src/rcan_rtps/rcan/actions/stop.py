"""`stop`: zero velocity and cancel every goal, on every goal server. Never gated, never
rate-limited."""

from __future__ import annotations

from typing import Annotated, Any

import msgspec

from .._enums import Role
from .._types import ActionParams
from ._spec import ActionSpec, Effect, Halt, HitlDefault, Invariant, MessageKit, Publish
from .move import MoveParams, velocity


class NoParams(ActionParams, frozen=True):
    """clear_estop takes no parameters."""


class StopParams(ActionParams, frozen=True, omit_defaults=True):
    """stop and estop: only why, for the audit log (what stops is not negotiable)."""

    # RCAN SAFETY messages allow 512 characters of reason (the `rcan` SDK truncates there).
    reason: Annotated[str, msgspec.Meta(max_length=512)] | None = None


def zero_velocity(params: ActionParams, kit: MessageKit) -> Any:
    return velocity(MoveParams(), kit)


HALT = Halt(velocity=Publish(topic_key="cmd_vel_topic", type_key="cmd_vel_type",
                             build=zero_velocity))

SPEC = ActionSpec(
    order=40,
    name="stop",
    summary="Stop: zero velocity, hold each arm still moving where it is, cancel every goal "
            "(navigation, docking).",
    params=StopParams,
    effect=Effect.HALT,
    default_role=Role.USER,
    ros=HALT,
    invariants=(Invariant.FINITE,),
    hitl=HitlDefault(gateable=False),
)
