"""The action registry: one module per action (parameters, governance defaults, invariants,
ROS translation). Everything that lists actions derives the list from `ACTIONS`."""

from typing import TYPE_CHECKING, Literal

from ._invariants import READS, Reads, not_understood, numbers, unreadable
from ._registry import (
    ACTIONS,
    GoalRoute,
    action_spec,
    goal_routes,
    markdown_table,
    names,
    specs,
    stopping_names,
    with_effect,
)
from ._spec import (
    ActionSpec,
    Builder,
    Effect,
    EstopSignal,
    Halt,
    HitlDefault,
    Hold,
    Invariant,
    MessageKit,
    NoRoute,
    PathPoint,
    Publish,
    RosRoute,
    SendGoal,
)
from .arm_joint import ArmJointParams
from .dock import DockParams
from .lock import LockParams
from .move import MoveParams, RampedMove
from .navigate import NavigateParams
from .stop import NoParams, StopParams

if TYPE_CHECKING:
    ActionName = str
    GateableName = str
else:  # Literals of the registry's names: msgspec validates them and JSON Schema lists them
    ActionName = Literal[names()]
    GateableName = Literal[tuple(s.name for s in specs() if s.hitl.gateable)]

__all__ = [
    "ACTIONS",
    "READS",
    "ActionName",
    "ActionSpec",
    "ArmJointParams",
    "Builder",
    "DockParams",
    "Effect",
    "EstopSignal",
    "GateableName",
    "GoalRoute",
    "Halt",
    "HitlDefault",
    "Hold",
    "Invariant",
    "LockParams",
    "MessageKit",
    "MoveParams",
    "NavigateParams",
    "NoParams",
    "NoRoute",
    "PathPoint",
    "Publish",
    "RampedMove",
    "Reads",
    "RosRoute",
    "SendGoal",
    "StopParams",
    "action_spec",
    "goal_routes",
    "markdown_table",
    "names",
    "not_understood",
    "numbers",
    "specs",
    "stopping_names",
    "unreadable",
    "with_effect",
]
