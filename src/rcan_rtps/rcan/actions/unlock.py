"""`unlock`: release a motion lock engaged with `lock`."""

from __future__ import annotations

from .._enums import Role
from ._spec import ActionSpec, Effect, Invariant, NoRoute
from .lock import LockParams

SPEC = ActionSpec(
    order=80,
    name="unlock",
    summary="Release a motion lock.",
    params=LockParams,
    effect=Effect.UNLOCK,
    default_role=Role.USER,
    ros=NoRoute(),
    invariants=(Invariant.FINITE,),
)
