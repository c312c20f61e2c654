"""`bridge.skills`, and the INVOKEs under way once one came.

INVOKE, INVOKE_CANCEL and AUTHORIZE (`_invoke`) are rare on most robots, and a bridge with no
skills configured answers every INVOKE `not_found`: the module that runs them is imported,
and its state made, by the first request that needs it (GET /api/skills, or one of those
messages), not at start (issue 27: idle memory). Until then no INVOKE is under way, so there
is nothing the state could have missed.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

from rcan_rtps.config import SkillConfig

from .ports import GoalView, RobotView

if TYPE_CHECKING:
    from rcan_rtps.events import Events
    from rcan_rtps.governance.streams import StreamEnded

    from ._invoke import Invocations


class Skills:
    """The skills an INVOKE may name, made into `_invoke.Invocations` on first use."""

    def __init__(self, skills: Mapping[str, SkillConfig], robot: RobotView | None,
                 events: Events | None = None) -> None:
        self._skills = dict(skills)
        self._robot = robot
        self._made: Invocations | None = None
        if robot is not None:  # now: the robot's channels take no subscriber once started
            robot.watch_goals(self._goal_changed)
        if events is not None and self._skills:  # the governor's, likewise
            events.stream_ended.subscribe(self._stream_ended)

    def _goal_changed(self, view: GoalView) -> None:
        if self._made is not None:  # else no INVOKE is waiting for any goal
            self._made.goal_changed(view)

    def _stream_ended(self, ended: StreamEnded) -> None:
        if self._made is not None:  # else no INVOKE is waiting for any stream
            self._made.stream_ended(ended)

    def invocations(self) -> Invocations:
        if self._made is None:
            from ._invoke import Invocations

            self._made = Invocations(self._skills, self._robot)
        return self._made


NO_SKILLS = Skills({}, None)  # where no skills were given: every INVOKE is not_found
