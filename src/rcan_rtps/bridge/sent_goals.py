"""The goals one `GoalTracker` (navigation.py) sent, each followed to its end: loaded with the
tracker's first goal.

Until a bridge is asked to `navigate` or `dock`, its trackers only list goals (none) and
cancel every goal of their server (a stop): that half is navigation.py, loaded at start. A
goal's watcher records its feedback (as plain values) and its result, so the API reads goal
progress without touching DDS; the bridge's `Events` hear of every change (`goal`), of the
active goals changing (`robot`, STATUS) and of each goal's end, once (`goal_finished`, the
audit log).

A goal whose send gave up (no answer in time, the send cancelled: its command failed) is
cancelled by the action client should its server accept it after all (`ros.action_goals`,
`GoalSender._give_up`); such a late goal is shown and audited here like any goal's end, with
the command that sent it, and logged as a warning.
"""

from __future__ import annotations

import asyncio
import logging
import uuid
from typing import Any

import msgspec

from ..api.ports import GoalState, GoalView
from ..events import Events
from ..rcan import Navigation
from ..ros.action_goals import ClientGoal, LateGoal
from ..ros.actions import ActionClient
from ..ros.actions import GoalState as RosGoalState
from ..ros.errors import ActionError, WireError
from .navigation import TERMINAL, now_ms

log = logging.getLogger(__name__)
_STATES: dict[RosGoalState, GoalState] = {
    RosGoalState.UNKNOWN: "unknown", RosGoalState.ACCEPTED: "accepted",
    RosGoalState.EXECUTING: "executing", RosGoalState.CANCELING: "canceling",
    RosGoalState.SUCCEEDED: "succeeded", RosGoalState.CANCELED: "canceled",
    RosGoalState.ABORTED: "aborted", RosGoalState.REJECTED: "rejected",
    RosGoalState.SERVER_LOST: "lost",
}
RESULT_TIMEOUT_S = 3600.0
# Sends given up on whose command is remembered, should their goal be accepted late (the
# action client watches as many: `ros.action_goals.MAX_GIVEN_UP`, and sends no goal while it
# does; past it, sends that were on their way then, the oldest forgotten first).
KEEP_GIVEN_UP = 64


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


class SentGoals:
    """Sends goals through `client` and follows each to its end, keeping its view in `views`
    (the tracker's, which the API reads) and telling `events`; keeps the newest `keep`
    views of ended goals."""

    def __init__(self, client: ActionClient, views: dict[str, GoalView], events: Events,
                 keep: int) -> None:
        self.client = client
        self._views = views
        self.events = events
        self._keep = keep
        self._watchers: set[asyncio.Task[None]] = set()
        self._message_ids: dict[str, str | None] = {}  # goal → the command that sent it
        self._handles: dict[str, ClientGoal] = {}  # goals not yet finished
        # goal → (the command that sent it, its action) for sends that gave up
        self._given_up: dict[str, tuple[str | None, str | None]] = {}
        client.on_late_goal = self._late_goal

    async def send(self, goal: dict[str, Any], timeout: float, *,
                   message_id: str | None = None, command: str | None = None,
                   goal_id: str | None = None) -> str:
        """Sends a goal (for the command `message_id` of action `command`, with the id
        `goal_id` if given); its id once accepted. Raises on rejection, or when no server
        answers within `timeout`."""
        chosen = uuid.UUID(goal_id).bytes if goal_id is not None else uuid.uuid4().bytes
        try:
            handle = await self.client.send_goal(goal, timeout=timeout, goal_id=chosen)
        except BaseException:  # (cancelled too: its caller went away) it may come late
            if self.client.watching_late(chosen):  # (not: refused before it went out)
                self._remember_given_up(str(uuid.UUID(bytes=chosen)), message_id, command)
            raise
        if not handle.accepted:
            raise ActionError(f"{self.client.name} rejected the goal")
        goal_id = str(uuid.UUID(bytes=handle.goal_id))
        now = now_ms()
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

    def _remember_given_up(self, goal_id: str, message_id: str | None,
                           command: str | None) -> None:
        self._given_up[goal_id] = (message_id, command)
        while len(self._given_up) > KEEP_GIVEN_UP:
            del self._given_up[next(iter(self._given_up))]

    def watch_left(self, goal_id: str, timeout: float, *, message_id: str | None,
                   command: str | None) -> None:
        """A goal a crashed run left, its send perhaps given up: watched for as one whose
        send gave up here (`ActionClient.watch_late`), for max(LATE_WATCH_S, `timeout`)."""
        chosen = uuid.UUID(goal_id).bytes
        self.client.watch_late(chosen, timeout)
        if self.client.watching_late(chosen):
            self._remember_given_up(goal_id, message_id, command)

    def unsettled(self) -> list[tuple[str, str | None, str | None]]:
        """(goal id, the command that sent it, its action) of each goal whose send gave up
        that its server may still accept or run (`ActionClient.unsettled_late`)."""
        ids = [str(uuid.UUID(bytes=g)) for g in self.client.unsettled_late()]
        return [(g, *self._given_up.get(g, (None, None))) for g in ids]

    def not_seen_ended(self, server_present: bool) -> list[tuple[str, str | None, str | None]]:
        """(goal id, the command that sent it, its action) of each goal of this run whose end
        was not seen and that a stop's server-wide cancel may not have reached: its server
        lost from sight, or its end unknown — or, the server absent now, any not ended. A
        server that comes back may run them: a clean stop names them for the next start."""
        unseen = ("lost", "unknown")
        return [(goal_id, self._message_ids.get(goal_id), view.command)
                for goal_id, view in self._views.items()
                if view.state in unseen or (not server_present and view.state not in TERMINAL)]

    def _late_goal(self, late: LateGoal) -> None:
        """The server accepted a goal after its send had given up (its command was answered
        failed), and the client cancelled it: shown among the goals and audited
        (GOAL_FINISHED, with the command that sent it), so that no goal ran unrecorded."""
        goal_id = str(uuid.UUID(bytes=late.goal_id))
        message_id, command = self._given_up.pop(goal_id, (None, None))
        state = _STATES[late.state]
        ended = state if state in TERMINAL else "unknown"
        by = "cancelled by the bridge" if late.canceled else "not cancelled by the bridge"
        now_in = f"ended {state}" if state in TERMINAL else \
            f"{late.state.name.lower()}, not seen ended"
        detail = (f"accepted by {self.client.name} after its send had given up (the command "
                  f"failed); {by}; {now_in}")
        log.warning("goal %s (command %s): %s", goal_id, message_id, detail)
        now = now_ms()
        view = GoalView(goal_id=goal_id, action=self.client.name,
                        action_type=self.client.type_name, command=command, state=ended,
                        detail=detail, created_ms=now, updated_ms=now)
        if state in TERMINAL:  # (an end not seen is not listed as a goal still running)
            self._views[goal_id] = view
            self._message_ids[goal_id] = message_id
            self._forget_old()
        self._tell_event(view)
        self.events.goal_finished.emit(GoalFinished(view=msgspec.structs.replace(view),
                                                    message_id=message_id))

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
            values, result_type = self.client.node.values, self.client.types.result.name
            result = values.to_plain(result_type, outcome.result)
        self._update(goal_id, _STATES[outcome.state], result=result, detail=outcome.detail or None)

    async def _follow_feedback(self, goal_id: str, handle: ClientGoal) -> None:
        values, feedback_type = self.client.node.values, self.client.types.feedback.name
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
        return view.state if state in TERMINAL and view is not None else state

    def _update(self, goal_id: str, state: GoalState, **changes: Any) -> None:
        view = self._views.get(goal_id)
        if view is None:
            return
        for key, value in changes.items():
            if value is not None:
                setattr(view, key, value)
        view.state, state_before = state, view.state
        view.updated_ms = now_ms()
        if state != state_before:
            self._tell()
        self._tell_event(view)
        if state in TERMINAL and state_before not in TERMINAL:
            self._handles.pop(goal_id, None)
            finished = GoalFinished(view=msgspec.structs.replace(view),
                                    message_id=self._message_ids.get(goal_id))
            self.events.goal_finished.emit(finished)

    def _tell(self) -> None:
        self.events.robot.emit()

    def _tell_event(self, view: GoalView) -> None:
        if self.events.goal.heard:
            self.events.goal.emit(msgspec.structs.replace(view))

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

    def _forget_old(self) -> None:
        finished = [g for g, v in self._views.items() if v.state in TERMINAL]
        for goal_id in finished[: max(0, len(self._views) - self._keep)]:
            self._views.pop(goal_id, None)
            self._message_ids.pop(goal_id, None)
            self._handles.pop(goal_id, None)

    async def close(self) -> None:
        """Stops following the goals (they go on on the server)."""
        for task in list(self._watchers):
            task.cancel()
        await asyncio.gather(*self._watchers, return_exceptions=True)
