"""`lock`: engage a configured motion lock (`bridge.motion.locks`), like a twist_mux lock.

While engaged, velocity streams of a lower priority than the lock's are refused, and a running
one is ended. Only a principal whose priority reaches the lock's may engage or release it.
"""

from __future__ import annotations

from typing import Annotated

import msgspec

from .._enums import Role
from .._types import ActionParams, whole
from ._spec import ActionSpec, Effect, Invariant, NoRoute

LockName = Annotated[str, msgspec.Meta(min_length=1, max_length=64,
                                       pattern=whole(r"[A-Za-z0-9_.-]+"))]


class LockParams(ActionParams, frozen=True):
    name: LockName


SPEC = ActionSpec(
    order=70,
    name="lock",
    summary="Engage a configured motion lock: lower-priority moves are refused until unlock.",
    params=LockParams,
    effect=Effect.LOCK,
    default_role=Role.USER,
    ros=NoRoute(),
    invariants=(Invariant.FINITE,),
)
