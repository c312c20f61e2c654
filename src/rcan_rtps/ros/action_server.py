"""The server side of ROS 2 actions (`ActionServer`, Cyclone mapping; see `actions.py`).

Apart from the client: a bridge only sends goals, so it never loads this (the simulated
robot and tests serve actions with it; issue 27, idle memory).
"""

from __future__ import annotations

import asyncio
import itertools
import logging
from collections.abc import Awaitable, Callable, Mapping
from typing import Any

from cyclonedds.idl import IdlStruct

from . import qos as qos_mod
from .actions import CANCEL_TYPE, KEEP_FINISHED, STATUS_TYPE, UUID_TYPE, GoalState, _stamp
from .names import action_names
from .participant import RosNode
from .rostime import now_msg
from .service_server import ServiceServer

log = logging.getLogger(__name__)


class ServerGoal:
    """A goal being executed by an `ActionServer`."""

    def __init__(self, server: ActionServer, goal_id: bytes, goal: IdlStruct) -> None:
        self.server = server
        self.goal_id = goal_id
        self.goal = goal
        self.stamp = now_msg()
        self.state = GoalState.ACCEPTED
        self.cancel_requested = asyncio.Event()
        self.done: asyncio.Future[IdlStruct] = asyncio.get_running_loop().create_future()
        self._end: GoalState | None = None

    def publish_feedback(self, feedback: IdlStruct | Mapping[str, Any]) -> None:
        self.server._publish_feedback(self, feedback)

    def abort(self) -> None:
        self._end = GoalState.ABORTED

    def canceled(self) -> None:
        self._end = GoalState.CANCELED


Execute = Callable[[ServerGoal], Awaitable["IdlStruct | Mapping[str, Any] | None"]]


class ActionServer:
    """Serves one action (Cyclone mapping). `execute(goal)` returns the result; call
    `goal.abort()` or `goal.canceled()` before returning to end it otherwise."""

    def __init__(self, node: RosNode, action: str, type_name: str, execute: Execute, *,
                 accept: Callable[[IdlStruct], Awaitable[bool]] | None = None,
                 result_timeout: float = 900.0, keep_finished: int = KEEP_FINISHED) -> None:
        self.node = node
        self.name = node.resolve(action)
        self.types = node.store.action(type_name)
        self.type_name = self.types.name
        self._execute = execute
        self._accept = accept
        self._result_timeout = result_timeout
        self._keep_finished = keep_finished
        self._goals: dict[bytes, ServerGoal] = {}
        # Ended goals still kept, oldest first → when their result expires (loop time); one
        # timeout for all, so the oldest always expires first.
        self._finished: dict[bytes, float] = {}
        # One timer, at the oldest kept goal's expiry: a timer per ended goal outlived the goal
        # (let go of past keep_finished) for the whole result timeout, ~0.6 kB each — a robot
        # taking goals and stops back to back grew by that much a goal for 15 minutes.
        self._expiry: asyncio.TimerHandle | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._closed = False
        names = action_names(self.name)
        self._status = node.create_publisher(names["status"], STATUS_TYPE, qos_mod.ACTION_STATUS)
        self._feedback = node.create_publisher(
            names["feedback"], self.type_name + "_FeedbackMessage", qos_mod.DEFAULT)
        self._services = [
            ServiceServer(node, names["send_goal"], self.type_name + "_SendGoal",
                          self._on_send_goal),
            ServiceServer(node, names["get_result"], self.type_name + "_GetResult",
                          self._on_get_result),
            ServiceServer(node, names["cancel_goal"], CANCEL_TYPE, self._on_cancel),
        ]
        self._publish_status()

    async def _on_send_goal(self, request: Any) -> dict[str, Any]:
        goal_id = bytes(request.goal_id.uuid)
        accepted = goal_id not in self._goals and (
            self._accept is None or await self._accept(request.goal))
        if not accepted:
            return {"accepted": False}
        goal = self._goals[goal_id] = ServerGoal(self, goal_id, request.goal)
        self._publish_status()
        # Executes after this reply is written, like rclpy.
        task = asyncio.get_running_loop().create_task(self._run(goal))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return {"accepted": True, "stamp": goal.stamp}

    async def _run(self, goal: ServerGoal) -> None:
        await asyncio.sleep(0)
        if goal.state is GoalState.ACCEPTED:
            goal.state = GoalState.EXECUTING
            self._publish_status()
        try:
            result = await self._execute(goal)
            end = goal._end or GoalState.SUCCEEDED
        except asyncio.CancelledError:
            raise
        except Exception:
            log.exception("action %s: execute failed; the goal is aborted", self.name)
            result, end = None, GoalState.ABORTED
        message = result if isinstance(result, IdlStruct) else \
            self.node.values.build(self.types.result.name, result or {})
        goal.state = end
        goal.done.set_result(message)
        self._finished[goal.goal_id] = asyncio.get_running_loop().time() + self._result_timeout
        while len(self._finished) > self._keep_finished:  # the oldest ended go first
            self._forget(next(iter(self._finished)))
        self._publish_status()
        self._arm_expiry()

    def _arm_expiry(self) -> None:
        """The timer for the oldest ended goal kept, unless one is set (it re-arms itself)."""
        if self._expiry is None and self._finished and not self._closed:
            due = next(iter(self._finished.values()))
            self._expiry = asyncio.get_running_loop().call_at(due, self._expire, due)

    def _expire(self, due: float) -> None:
        """Lets go of the ended goals whose result timed out by `due` (what the timer was set
        for: a loop may run it a clock tick early), then waits for the next."""
        self._expiry = None
        expired = [g for g, _ in itertools.takewhile(lambda kept: kept[1] <= due,
                                                     self._finished.items())]
        for goal_id in expired:
            self._forget(goal_id)
        if expired:
            self._publish_status()
        self._arm_expiry()

    def _forget(self, goal_id: bytes) -> None:
        del self._finished[goal_id]
        self._goals.pop(goal_id, None)

    @property
    def goals_kept(self) -> int:
        """Goals the server still knows: those running, and the newest ended ones."""
        return len(self._goals)

    async def _on_get_result(self, request: Any) -> Any:
        response: Any = self.node.types.struct(self.types.get_result.response.name)
        goal = self._goals.get(bytes(request.goal_id.uuid))
        if goal is None:
            return response(status=int(GoalState.UNKNOWN),
                            result=self.node.values.build(self.types.result.name, {}))
        result = await goal.done
        return response(status=int(goal.state), result=result)

    async def _on_cancel(self, request: Any) -> dict[str, Any]:
        goal_id = bytes(request.goal_info.goal_id.uuid)
        stamp = _stamp(request.goal_info.stamp)
        if any(goal_id):
            chosen = [g for g in (self._goals.get(goal_id),) if g is not None]
        else:  # zero id: every goal, or those accepted at or before a non-zero stamp
            chosen = [g for g in self._goals.values()
                      if stamp == (0, 0) or (g.stamp["sec"], g.stamp["nanosec"]) <= stamp]
        if not chosen:
            return {"return_code": 2 if any(goal_id) else 0}  # ERROR_UNKNOWN_GOAL_ID
        canceling = [g for g in chosen if not g.state.terminal]
        for goal in canceling:
            goal.state = GoalState.CANCELING
            goal.cancel_requested.set()
        if canceling:
            self._publish_status()
            return {"return_code": 0, "goals_canceling": [
                {"goal_id": {"uuid": g.goal_id}, "stamp": g.stamp} for g in canceling]}
        return {"return_code": 3}  # ERROR_GOAL_TERMINATED

    def _publish_feedback(self, goal: ServerGoal, feedback: IdlStruct | Mapping[str, Any]
                          ) -> None:
        body = feedback if isinstance(feedback, IdlStruct) else \
            self.node.values.build(self.types.feedback.name, feedback)
        message_cls: Any = self.node.types.struct(self.types.feedback_message.name)
        message = message_cls(goal_id=self.node.values.build(UUID_TYPE, {"uuid": goal.goal_id}),
                              feedback=body)
        self._feedback.publish(message)

    def _publish_status(self) -> None:
        if self._closed:  # a result expiring after close
            return
        self._status.publish({"status_list": [
            {"goal_info": {"goal_id": {"uuid": g.goal_id}, "stamp": g.stamp},
             "status": int(g.state)} for g in self._goals.values()]})

    async def close(self) -> None:
        """Cancels the goals being executed, then deletes the endpoints; idempotent."""
        self._closed = True
        if self._expiry is not None:
            self._expiry.cancel()
            self._expiry = None
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for service in self._services:
            await service.close()
        self._status.close()
        self._feedback.close()
