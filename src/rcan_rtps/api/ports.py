"""What the HTTP layer needs from the robot side, as protocols the bridge implements.

The API never touches DDS: it asks a `RobotView` for STATUS and goal progress. Commands
go through the governor, whose `Dispatcher` is the bridge's translation to ROS 2.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Literal, Protocol

import msgspec

from ..rcan import Status
from ._errors import ApiServerError

GoalState = Literal["accepted", "executing", "canceling", "succeeded", "canceled",
                    "aborted", "rejected", "unknown", "lost"]


class GoalView(msgspec.Struct, kw_only=True):
    """GET /api/goals/{goal_id}: a goal (navigation, docking, ...) as the bridge tracks it."""

    goal_id: str
    action: str  # the ROS action server it was sent to, e.g. /robot1/dock_robot
    action_type: str | None = None  # its ROS type, e.g. nav2_msgs/action/DockRobot
    command: str | None = None  # the RCAN action whose command sent it, e.g. dock
    state: GoalState
    feedback: dict[str, Any] | None = None
    result: dict[str, Any] | None = None
    detail: str | None = None
    created_ms: int
    updated_ms: int


class RobotView(Protocol):
    def status(self, *, pending_auth: int) -> Status:
        """The robot's STATUS now; the API supplies the count of pending approvals."""
        ...

    def watch(self, changed: Callable[[], None]) -> None:
        """Call `changed` (from any thread) whenever what STATUS is made of may have changed;
        the API's STATUS owner recomputes then instead of anyone polling."""
        ...

    def watch_goals(self, changed: Callable[[GoalView], None]) -> None:
        """Call `changed` on the event loop with a copy of a goal's view at each change:
        feedback, state, its end."""
        ...

    def goal(self, goal_id: str) -> GoalView | None: ...

    def goals(self) -> list[GoalView]: ...


class ImageFrame(msgspec.Struct, frozen=True, kw_only=True):
    """A camera's latest frame as a client sees it: an image file and what it shows."""

    mime: str  # image/png (raw frames), image/jpeg or image/png (compressed ones)
    data: bytes
    width: int | None  # None for a compressed frame (its file says)
    height: int | None
    age_s: float  # since it arrived


class ImageUnavailable(ApiServerError):
    """No frame to show: `reason` is `image_not_found` (no such name), `no_frame_yet`, or
    `unsupported_image` (an encoding that cannot be shown)."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


class ImageSource(Protocol):
    """The configured camera topics (`bridge.ros2.images`)."""

    def names(self) -> list[str]: ...

    async def frame(self, name: str) -> ImageFrame:
        """The newest frame; raises ImageUnavailable."""
        ...
