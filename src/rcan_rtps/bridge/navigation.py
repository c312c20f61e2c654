"""Goals on one action server (nav2 NavigateToPose, DockRobot, ...), tracked for
GET /api/goals/{goal_id}; `bridge.goals` holds one tracker per goal route.

Each accepted goal gets a watcher task that records feedback (as plain values) and the
final result, so the API reads goal progress without touching DDS. The bridge's `Events` hear
of every change (`goal`, e.g. WebSocket goal events), of the active goals changing (`robot`,
STATUS) and of each goal's end, once (`goal_finished`, e.g. the audit log).
"""

from __future__ import annotations

import asyncio
import logging
import time
import uuid
from typing import TYPE_CHECKING, Any

import msgspec

from ..api.ports import GoalState, GoalView
from ..events import Events
from ..rcan import Navigation
from ..ros.actions import ActionClient
from ..ros.actions import GoalState as RosGoalState
from ..ros.errors import ActionError, WireError
from ..ros.participant import RosNode
from ..ros.services import RequestMapping

if TYPE_CHECKING:
    from ..ros.action_goals import ClientGoal  # loaded by the first goal

log = logging.getLogger(__name__)
NAVIGATE_TO_POSE = "nav2_msgs/action/NavigateToPose"
_STATES: dict[RosGoalState, GoalState] = {
    RosGoalState.UNKNOWN: "unknown", RosGoalState.ACCEPTED: "accepted",
    RosGoalState.EXECUTING: "executing", RosGoalState.CANCELING: "canceling",
    RosGoalState.SUCCEEDED: "succeeded", RosGoalState.CANCELED: "canceled",
    RosGoalState.ABORTED: "aborted", RosGoalState.REJECTED: "rejected",
    RosGoalState.SERVER_LOST: "lost",
}
_TERMINAL = {"succeeded", "canceled", "aborted", "rejected", "lost"}
RESULT_TIMEOUT_S = 3600.0
CANCEL_READY_PERIOD_S = 1.0  # s: how often a tracker looks whether a server (re)appeared


def _ms() -> int:
    return int(time.time() * 1000)


class GoalFinished(msgspec.Struct, frozen=True):
    """A goal reached a terminal state; `message_id` is the command that sent it."""

    view: GoalView
    message_id: str | None


def _seconds(duration: Any) -> float | None:
    if not isinstance(duration, dict):
        return None
    return round(float(duration.get("sec", 0)) + float(duration.get("nanosec", 0)) / 1e9, 3)


def navigation_summary(view: GoalView) -> Navigation:
    """NavigateToPose feedback (as plain values) as STATUS shows it."""
    feedback = view.feedback or {}
    left = feedback.get("distance_remaining")
    recoveries = feedback.get("number_of_recoveries")
    return Navigation(
        goal_id=view.goal_id, state=view.state,
        distance_remaining=round(float(left), 3) if isinstance(left, (int, float)) else None,
        eta_s=_seconds(feedback.get("estimated_time_remaining")),
        recoveries=recoveries if isinstance(recoveries, int) else None,
        navigation_time_s=_seconds(feedback.get("navigation_time")))


class GoalTracker:
    """Sends goals to one action server (of one type) and follows them."""

    def __init__(self, node: RosNode, action: str, type_name: str = NAVIGATE_TO_POSE, *,
                 keep: int = 200, mapping: RequestMapping = RequestMapping.AUTO,
                 events: Events | None = None) -> None:
        self.node = node
        self.client = ActionClient(node, action, type_name, mapping=mapping)
        self._views: dict[str, GoalView] = {}
        self._watchers: set[asyncio.Task[None]] = set()
        self._keep = keep
        self._message_ids: dict[str, str | None] = {}  # goal → the command that sent it
        self._handles: dict[str, ClientGoal] = {}  # goals not yet finished
        # Told when the active goals change (`robot`), of any change (`goal`, a copy) and of
        # each goal's end, once (`goal_finished`).
        self.events = events or Events()
        self._cancel_ready_for = 0  # the server match the cancel client was prepared for
        self._preparing: asyncio.Task[None] | None = None

    @property
    def action_name(self) -> str:
        return self.client.name

    @property
    def type_name(self) -> str:
        return self.client.type_name

    async def send(self, goal: dict[str, Any], timeout: float, *,
                   message_id: str | None = None, command: str | None = None) -> str:
        """Sends a goal (for the command `message_id` of action `command`); its id once
        accepted. Raises on rejection, or when no server answers within `timeout`."""
        handle = await self.client.send_goal(goal, timeout=timeout)
        if not handle.accepted:
            raise ActionError(f"{self.client.name} rejected the goal")
        goal_id = str(uuid.UUID(bytes=handle.goal_id))
        now = _ms()
        self._views[goal_id] = GoalView(goal_id=goal_id, action=self.client.name,
                                        action_type=self.client.type_name, command=command,
                                        state="accepted", created_ms=now, updated_ms=now)
        self._message_ids[goal_id] = message_id
        self._handles[goal_id] = handle
        self._track(asyncio.create_task(self._watch(goal_id, handle)))
        self._forget_old()
        self._tell()
        self._tell_event(self._views[goal_id])
        return goal_id

    async def _watch(self, goal_id: str, handle: ClientGoal) -> None:
        """Follows a goal: its feedback (on a task of its own, as feedback sent before the end
        may come after it, docs/design/zero-loss.md) and its end, shown with its result as
        soon as the server has it."""
        self._track(asyncio.create_task(self._follow_feedback(goal_id, handle)))
        try:
            await handle.ended()
            outcome = await handle.result(timeout=RESULT_TIMEOUT_S)
        except (WireError, OSError) as exc:
            self._update(goal_id, "unknown", detail=str(exc))
            return
        except Exception as exc:  # what a broken server sent: the goal must not vanish
            log.warning("goal %s on %s: %s", goal_id, self.client.name, exc)
            self._update(goal_id, "unknown", detail=f"{type(exc).__name__}: {exc}")
            return
        result = None
        if outcome.result is not None:
            result = self.node.values.to_plain(self.client.types.result.name, outcome.result)
        self._update(goal_id, _STATES[outcome.state], result=result, detail=outcome.detail or None)

    async def _follow_feedback(self, goal_id: str, handle: ClientGoal) -> None:
        values, feedback_type = self.node.values, self.client.types.feedback.name
        try:
            async for feedback in handle.feedback():
                self._update(goal_id, self._in_progress(goal_id, handle),
                             feedback=values.to_plain(feedback_type, feedback))
        except (WireError, OSError) as exc:  # the goal's end says what became of it
            log.info("goal %s on %s: feedback ended: %s", goal_id, self.client.name, exc)
        except Exception as exc:  # a feedback a broken server sent; its end still counts
            log.warning("goal %s on %s: feedback: %s: %s", goal_id, self.client.name,
                        type(exc).__name__, exc)

    def _track(self, task: asyncio.Task[None]) -> None:
        self._watchers.add(task)
        task.add_done_callback(self._watchers.discard)

    def _in_progress(self, goal_id: str, handle: ClientGoal) -> GoalState:
        """The state to show with feedback: a goal's end is shown with its result (and
        audited with it) once fetched, never by feedback read after its status ended."""
        state = _STATES[handle.state]
        view = self._views.get(goal_id)
        return view.state if state in _TERMINAL and view is not None else state

    def _update(self, goal_id: str, state: GoalState, **changes: Any) -> None:
        view = self._views.get(goal_id)
        if view is None:
            return
        for key, value in changes.items():
            if value is not None:
                setattr(view, key, value)
        view.state, state_before = state, view.state
        view.updated_ms = _ms()
        if state != state_before:
            self._tell()
        self._tell_event(view)
        if state in _TERMINAL and state_before not in _TERMINAL:
            self._handles.pop(goal_id, None)
            finished = GoalFinished(view=msgspec.structs.replace(view),
                                    message_id=self._message_ids.get(goal_id))
            self.events.goal_finished.emit(finished)

    def _tell(self) -> None:
        self.events.robot.emit()

    def _tell_event(self, view: GoalView) -> None:
        if self.events.goal.heard:
            self.events.goal.emit(msgspec.structs.replace(view))

    def navigation(self) -> Navigation | None:
        """The newest active goal and its progress, for STATUS."""
        active = [self._views[g] for g in self.active()]
        if not active:
            return None
        view = max(active, key=lambda v: v.created_ms)
        return navigation_summary(view)

    async def cancel_all(self) -> int:
        """Cancels every goal on the server, whoever sent it: `stop` means stop."""
        if not self.client.server_present():
            return 0  # nothing to cancel, and no reason to wait for a server to appear
        try:
            return await self.client.cancel_all(timeout=2.0, server_wide=True)
        except WireError:
            log.info("no action server on %s: no goals to cancel", self.client.name)
            return 0

    async def cancel(self, goal_id: str) -> bool:
        """Cancels one goal this bridge sent; True if the server is canceling it."""
        handle = self._handles.get(goal_id)
        if handle is None:
            return False
        try:
            return await handle.cancel(timeout=2.0)
        except WireError as exc:
            log.warning("cancelling goal %s failed: %s", goal_id, exc)
            return False

    def warn_cancelling(self, why: str) -> None:
        """Logs each active goal about to be cancelled, and why."""
        for goal_id in self.active():
            feedback = self._views[goal_id].feedback or {}
            left = feedback.get("distance_remaining")
            where = f", {left:.2f} m from its target" if isinstance(left, float) else ""
            log.warning("cancelling %s goal %s on %s%s: %s", self.type_name.rsplit("/", 1)[-1],
                        goal_id, self.client.name, where, why)

    def active(self) -> list[str]:
        return [g for g, v in self._views.items() if v.state not in _TERMINAL]

    def goal(self, goal_id: str) -> GoalView | None:
        return self._views.get(goal_id)

    def goals(self) -> list[GoalView]:
        return sorted(self._views.values(), key=lambda v: v.created_ms)

    def _forget_old(self) -> None:
        finished = [g for g, v in self._views.items() if v.state in _TERMINAL]
        for goal_id in finished[: max(0, len(self._views) - self._keep)]:
            self._views.pop(goal_id, None)
            self._message_ids.pop(goal_id, None)
            self._handles.pop(goal_id, None)

    def keep_cancel_ready(self, period: float = CANCEL_READY_PERIOD_S) -> None:
        """From now on, whenever a server appears (or comes back), makes its cancel client
        ready, so that a stop's server-wide cancel makes no endpoints and waits for no
        discovery: goals sent by others (RViz, a script) are cancelled by a stop, and the
        first stop after a server appeared must not be its cancel client's first use."""
        if self._preparing is None:
            self._preparing = asyncio.get_running_loop().create_task(
                self._keep_cancel_ready(period))

    async def _keep_cancel_ready(self, period: float) -> None:
        while True:
            matches = self.client.status_matches()  # one C call: cheap at idle
            if matches != self._cancel_ready_for and self.client.server_present():
                try:
                    await self.client.prepare_cancel()
                    self._cancel_ready_for = matches
                except WireError as exc:  # not answered in time: tried again next period
                    log.debug("%s: cancel client not ready yet: %s", self.client.name, exc)
            await asyncio.sleep(period)

    @property
    def cancel_ready(self) -> bool:
        """Whether the cancel client was made ready for the server now on the graph."""
        return self._cancel_ready_for == self.client.status_matches() != 0

    async def close(self) -> None:
        """Stops following goals (they go on on the server) and leaves; idempotent."""
        if self._preparing is not None:
            self._preparing.cancel()
            await asyncio.gather(self._preparing, return_exceptions=True)
        for task in list(self._watchers):
            task.cancel()
        await asyncio.gather(*self._watchers, return_exceptions=True)
        self.client.close()
