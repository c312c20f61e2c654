"""INVOKE / INVOKE_CANCEL (RCAN §19) and AUTHORIZE (§16.4), over the governor.

An INVOKE names a skill of `bridge.skills`; the skill's action, with its fixed parameters and
those the invoker may set, becomes a command the governor decides like any other (roles,
invariants, HiTL, audit: nothing is bypassed). Its reply is an INVOKE_RESULT: at once for a
command that is done when it is executed or refused; for one that starts a goal (navigate,
dock), when the goal ends, or at `timeout_ms` (the goal is then cancelled: `timeout`); for an
arm's trajectory, which reports no end, when its time is up (a stop that held it before makes
it a `failure`), or at `timeout_ms` (the arm is then held where it is); for a `move`, when its
velocity stream ends (`success` by its own `duration_s`; anything else that ended it — a stop,
an e-stop, another move, a lost session or robot — makes it a `failure` naming that), or at
`timeout_ms` (the stream is then ended, zero sent). A held INVOKE (HiTL) is answered 202
`pending` like any held command, and its INVOKE_RESULT follows once its hold ends
(`_reviewed`): approved, it is answered as any INVOKE so decided (its `timeout_ms` counting
from the approval); denied `failure`; expired `timeout`; withdrawn `failure` naming who or what
withdrew it (a stop of the robot, its connection closing, its issuer), or `cancelled` by its
INVOKE_CANCEL. On the WebSocket that is a second outcome frame; over REST, whose request was
answered with the 202, it is in the log alone. An approval is also answered to its approver.
An INVOKE whose client leaves before its answer (its WebSocket closes, its HTTP request is hung
up on: the wait for its answer is cancelled) leaves nobody to answer for its motion: that is
stopped as its INVOKE_CANCEL would stop it (`why: INVOKE's client left`), in a task of its own,
and the INVOKE is answered in the log alone, `failure`. A held INVOKE whose client leaves stays
held: its hold's end answers it, in the log (its held motion is withdrawn as the connection
closes: `Governor.connection_closed`).

INVOKE_CANCEL names an INVOKE of its own sender by msg_id: a goal it started is cancelled
through the governor (audited), an arm it moves is held where it is (audited:
`hold_trajectory`), the velocity stream it drives is ended, zero sent (audited: its
STREAM_ENDED `cancelled`, `why: INVOKE_CANCEL`), and the INVOKE is answered `cancelled`; a
held one is withdrawn.
One already answered is left alone (§19.4: the earlier result stands, and is repeated); one
never seen is `not_found`.

Each INVOKE_RESULT that answers an INVOKE is audited before it is sent (an INVOKE_RESULT entry
with the INVOKE's msg_id as `invoke_id` and `message_id`, §19.5's `status` and the decision's
`outcome`): with the decision entries the INVOKE's command made, the whole lifecycle INVOKE →
INVOKE_RESULT can be read back from the log (rcan-spec's conformance case L3-INVOKE-001).
"""

from __future__ import annotations

import asyncio
import functools
import logging
import time
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Coroutine, Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar

import msgspec

from rcan_rtps.config import SkillConfig
from rcan_rtps.governance import Governor, Principal, Rejection, outcomes
from rcan_rtps.governance.governor import Decision
from rcan_rtps.governance.review import Ended, ReviewMessage
from rcan_rtps.governance.streams import EndReason, StreamEnded
from rcan_rtps.rcan import (
    STATUS_OF,
    Authorization,
    DecisionBody,
    ErrorCode,
    Invoke,
    InvokeCancel,
    InvokeResult,
    InvokeStatus,
    Outcome,
    SchemaValidationError,
    invoke_caps,
    invoke_command,
    skill_error,
)

from ._bodies import SkillList, SkillView
from .ports import GoalView, RobotView

log = logging.getLogger(__name__)
T = TypeVar("T")
Reply = tuple[int, object]
TERMINAL = frozenset({"succeeded", "canceled", "aborted", "rejected", "lost"})
FINISHED_KEPT = 1024  # answered INVOKEs remembered for a late INVOKE_CANCEL
SKILL_NOT_FOUND = Rejection(404, Outcome.DENIED, ErrorCode.COMMAND_REJECTED, "skill_not_found")
INVOKE_NOT_FOUND = Rejection(404, Outcome.DENIED, ErrorCode.COMMAND_REJECTED,
                             "invoke_not_found")
INVOKE_FINISHED = Rejection(409, Outcome.DENIED, ErrorCode.COMMAND_REJECTED, "invoke_finished")
INVOKE_RUNNING = Rejection(409, Outcome.DENIED, ErrorCode.MESSAGE_ID_CONFLICT, "invoke_running")
NOT_YOUR_PRINCIPAL_ID = Rejection(403, Outcome.DENIED, ErrorCode.INSUFFICIENT_PRIVILEGES,
                                  "principal_id_not_yours")
# Governor refusals that are the §19 statuses' own, not a plain failure.
_CONFLICTS = {"lower_priority", "motion_locked"}
_STATUS_OF_KIND: dict[str, InvokeStatus] = {
    "not_found": "not_found", "invalid_params": "invalid_params", "conflict": "failure"}
# Why an INVOKE ends the stream of its move (its STREAM_ENDED's `why`).
BY_INVOKE_CANCEL = "INVOKE_CANCEL"
BY_INVOKE_TIMEOUT = "INVOKE timeout"
BY_CLIENT_LEFT = "INVOKE's client left"
# What ended a move's stream before it was done, for its INVOKE's `failure`.
_STREAM_ENDED_BY = {
    EndReason.REPLACED: "another move of its sender's replaced it",
    EndReason.PREEMPTED: "a higher-priority move or a motion lock preempted it",
    EndReason.STOPPED: "a stop ended it",
    EndReason.ESTOPPED: "an e-stop ended it",
    EndReason.SESSION_LOST: "its sender's control session was lost",
    EndReason.CANCELLED: "its sender's client cancelled a motion command",
    EndReason.ROBOT_LOST: "the robot could not be sent its velocity",
    EndReason.BRIDGE_STOPPED: "the bridge stopped",
}


@dataclass
class _Running:
    """An INVOKE that has not been answered yet."""

    skill: str
    invoke_id: str
    started: float = field(default_factory=time.monotonic)
    goal_id: str | None = None
    pending_id: str | None = None  # held for a human, until its hold ends (`_reviewed`)
    client_left: bool = False  # its client left while it was held: nobody hears its answer
    # What its hold's end decided (`_reviewed`): an approval's decision, which its motion runs
    # under and its answer reports — also one made as its client leaves (`_client_left`).
    reviewed: Decision | None = None
    cancelled: bool = False  # by its INVOKE_CANCEL: a canceled goal is then `cancelled`
    ended: asyncio.Future[GoalView] = field(
        default_factory=lambda: asyncio.get_running_loop().create_future())
    # An arm's trajectory it sent (the command's message id), and its hold by INVOKE_CANCEL.
    trajectory: str | None = None
    held: asyncio.Future[Decision] = field(
        default_factory=lambda: asyncio.get_running_loop().create_future())
    # A move's velocity stream (the command's message id), and its end, once heard.
    stream: str | None = None
    stream_end: asyncio.Future[StreamEnded] = field(
        default_factory=lambda: asyncio.get_running_loop().create_future())
    answering: bool = False  # its one INVOKE_RESULT is on its way to the log
    answered: asyncio.Future[InvokeResult] = field(
        default_factory=lambda: asyncio.get_running_loop().create_future())


@dataclass(frozen=True)
class Started:
    """An INVOKE decided: its reply now, or `finish()`, a future of its answer for its one
    waiter (a goal, a stream or a trajectory under way), or both (held for a human: 202
    `pending` now, its INVOKE_RESULT once its hold ends). Cancelling that future — its client
    left — stops the INVOKE's motion and answers it in the log (`Invocations._answering`)."""

    reply: Reply | None = None
    finish: Callable[[], asyncio.Future[Reply]] | None = None


class Invocations:
    """The skills the config declares, and the INVOKEs under way, by (principal, msg_id).
    Made by the first use (`_skills.Skills`, which hands it each goal change)."""

    def __init__(self, skills: Mapping[str, SkillConfig], robot: RobotView | None) -> None:
        self.skills = dict(skills)
        self._robot = robot
        self._running: dict[tuple[str, str], _Running] = {}
        self._by_goal: dict[str, _Running] = {}
        self._by_stream: dict[tuple[str, str], _Running] = {}  # by (owner, message id)
        self._finished: OrderedDict[tuple[str, str], InvokeResult] = OrderedDict()
        # INVOKEs being decided and answered: tasks of their own, which the cancellation of
        # what waits for them (a client gone) cannot cut off before the answer is in the log.
        self._tasks: set[asyncio.Future[Any]] = set()

    def listed(self, governor: Governor) -> SkillList:
        """What GET /api/skills says: the §18/§19.7 `invoke` capability and each skill."""
        return SkillList(
            caps=invoke_caps(self.skills),
            skills={name: _view(self.skills[name], governor) for name in sorted(self.skills)})

    # -- INVOKE ---------------------------------------------------------------------------

    async def start(self, governor: Governor, principal: Principal, invoke: Invoke) -> Started:
        """Decide the INVOKE. Once it is a command, it arrives at the governor in this step
        and is decided and answered in tasks of their own: a caller cancelled meanwhile (its
        WebSocket closed while the INVOKE was decided, or in the very step its decision came)
        cuts off its wait, never the INVOKE's answer (red team 15: no INVOKE_RESULT entry was
        written). Nobody waits for that answer then: an INVOKE under way is one whose client
        left (`_answering`), its motion stopped and its answer in the log alone."""
        skill = self.skills.get(invoke.skill)
        if skill is None:
            return Started(reply=await self._refused(
                governor, principal, invoke, SKILL_NOT_FOUND, "not_found",
                f"no skill {invoke.skill!r} here (this robot's: "
                f"{', '.join(sorted(self.skills)) or 'none'})"))
        key = (principal.name, invoke.msg_id)
        if key in self._running:
            return Started(reply=await self._refused(
                governor, principal, invoke, INVOKE_RUNNING, "conflict",
                f"an INVOKE with msg_id {invoke.msg_id!r} is still running"))
        given = sorted(set(invoke.params) - set(skill.allow))
        try:
            if given:
                raise SchemaValidationError(f"$.params.{given[0]}", "not a parameter this "
                                            f"skill lets the invoker set (allowed: "
                                            f"{', '.join(skill.allow) or 'none'})")
            command = invoke_command(invoke, skill.action, {**skill.params, **invoke.params})
        except SchemaValidationError as exc:
            return Started(reply=await self._refused(
                governor, principal, invoke, outcomes.schema_failed(exc.path),
                "invalid_params", exc.detail, path=exc.path))
        running = self._running[key] = _Running(skill=invoke.skill, invoke_id=invoke.msg_id)
        if command.spec.streamed:  # listened for now: a move to a standstill ends as it starts
            running.stream = command.message_id
            self._by_stream[principal.name, command.message_id] = running
        deciding = governor.decide_soon(command, principal)  # arrived: a stop from now wins
        started = self._keep(asyncio.ensure_future(self._once_decided(
            governor, principal, invoke, key, running, deciding)))
        try:
            return await asyncio.shield(started)
        except asyncio.CancelledError:
            started.add_done_callback(_nobody_waits)
            raise

    async def _once_decided(self, governor: Governor, principal: Principal, invoke: Invoke,
                            key: tuple[str, str], running: _Running,
                            deciding: Awaitable[Decision]) -> Started:
        try:
            decision = await deciding
        except BaseException:
            self._forget(key, running)
            self._forget_stream(principal, running)
            raise
        return await self._decided(governor, principal, invoke, key, running, decision)

    async def _decided(self, governor: Governor, principal: Principal, invoke: Invoke,
                       key: tuple[str, str], running: _Running, decision: Decision) -> Started:
        if decision.outcome is Outcome.PENDING_AUTH and decision.pending_id is not None:
            return await self._held(governor, principal, invoke, key, running, decision,
                                    decision.pending_id)
        finish = await self._under_way(governor, principal, invoke, key, running, decision)
        if finish is not None:
            return self._answering(governor, principal, key, running, decision, finish)
        return Started(reply=await self._answered_now(governor, principal, key, running,
                                                      decision, _decided_status(decision)))

    async def _answered_now(self, governor: Governor, principal: Principal,
                            key: tuple[str, str], running: _Running, decision: Decision,
                            status: InvokeStatus, message: str | None = None) -> Reply:
        """An INVOKE done once decided (nothing of it runs on): answered now."""
        self._forget(key, running)
        self._forget_stream(principal, running)
        result = self._result(running, decision, status, message)
        return decision.http_status, await self._answer(governor, principal, key, running,
                                                        result)

    async def _held(self, governor: Governor, principal: Principal, invoke: Invoke,
                    key: tuple[str, str], running: _Running, decision: Decision,
                    pending_id: str) -> Started:
        """Held for a human: 202 `pending` now, its INVOKE_RESULT once its hold ends
        (`_reviewed`). An INVOKE_CANCEL that came while it was being held withdraws it now
        (a reviewer must never approve what its invoker cancelled), and both are answered
        `cancelled` then."""
        running.pending_id = pending_id
        ended = governor.held_ended(pending_id)
        body = decision.body()
        body.msg_id, body.status = invoke.msg_id, "pending"
        if ended is None:  # a retry's, answered from a decision whose hold is long forgotten
            self._forget(key, running)
            self._forget_stream(principal, running)
            return Started(reply=(decision.http_status, body))
        reviewed = self._reviewed(governor, principal, invoke, key, running, decision, ended)
        if running.cancelled:
            await governor.withdraw(pending_id, principal, BY_INVOKE_CANCEL)
            return Started(reply=await reviewed)
        return Started(reply=(decision.http_status, body), finish=self._answering(
            governor, principal, key, running, decision, reviewed).finish)

    async def _reviewed(self, governor: Governor, principal: Principal, invoke: Invoke,
                        key: tuple[str, str], running: _Running, held: Decision,
                        ended: asyncio.Future[Ended]) -> Reply:
        """A held INVOKE's answer, once its hold ends (`HitlDesk.ended`). Approved and
        executed, it goes on as an INVOKE so decided (a goal, a move, an arm's trajectory
        answered when done), its skill's time counted from the approval; else it is
        answered now (`_review_status`)."""
        try:
            end = await asyncio.shield(ended)  # (others may await the same future)
        except asyncio.CancelledError:
            if not ended.cancelled():  # this task itself was cancelled
                raise
            return await self._answered_now(governor, principal, key, running, held,
                                            "failure", "its review failed (see the bridge's "
                                            "log): it did not run")
        running.pending_id, running.reviewed = None, end.decision
        decision = end.decision
        if decision.outcome is Outcome.EXECUTED:
            running.started = time.monotonic()  # its skill runs from its approval
            finish = await self._under_way(governor, principal, invoke, key, running,
                                           decision)
            if finish is not None and running.client_left:
                finish.close()  # nobody is left to answer for its motion: it is stopped
                self._forget(key, running)
                self._left_behind(governor, principal, key, running, decision)
                return decision.http_status, await asyncio.shield(running.answered)
            if finish is not None:
                return await finish
        status, message = _review_status(running, end)
        return await self._answered_now(governor, principal, key, running, decision, status,
                                        message)

    async def _under_way(self, governor: Governor, principal: Principal, invoke: Invoke,
                         key: tuple[str, str], running: _Running, decision: Decision
                         ) -> Coroutine[object, object, Reply] | None:
        """The answer of an INVOKE whose skill runs on once decided — a move's stream, an
        arm's trajectory, a goal — to await (what it waits for, listened for now); None when
        nothing of it runs on."""
        if running.stream is not None:
            if self._stream_started(governor, principal, running, decision):
                return self._finish_stream(governor, principal, invoke, key, running, decision)
            self._forget_stream(principal, running)
        if (decision.outcome is Outcome.EXECUTED and decision.runs_for_s is not None
                and decision.message_id is not None):  # an arm's trajectory runs on
            running.trajectory = decision.message_id
            if running.cancelled:  # cancelled while it was being decided
                running.held.set_result(await governor.hold_trajectory(
                    decision.message_id, principal, message_id=None, why=BY_INVOKE_CANCEL))
            return self._finish_trajectory(governor, principal, invoke, key, running, decision)
        if decision.outcome is not Outcome.EXECUTED or decision.goal_id is None:
            return None
        running.goal_id = decision.goal_id
        self._by_goal[decision.goal_id] = running
        view = None if self._robot is None else self._robot.goal(decision.goal_id)
        if view is not None:
            self.goal_changed(view)
        if running.cancelled:  # cancelled while its goal was being sent
            await governor.cancel_goal(decision.goal_id, principal, message_id=None,
                                       why=BY_INVOKE_CANCEL)
        return self._finish(governor, principal, invoke, key, running, decision)

    def _answering(self, governor: Governor, principal: Principal, key: tuple[str, str],
                   running: _Running, decision: Decision,
                   finish: Coroutine[object, object, Reply]) -> Started:
        """An INVOKE under way: `finish`, its answer, runs from now on in a task of its own
        (its waiter may be cancelled, or never scheduled at all); `Started.finish` hands its
        one waiter a future of it. That future cancelled before the answer is on its way
        (its client left: its WebSocket closed, its HTTP request hung up), its motion is
        stopped as its INVOKE_CANCEL would stop it and it is answered in the log —
        `failure`, its client gone — so that every INVOKE's lifecycle ends in an
        INVOKE_RESULT entry (§19.5)."""
        answer = self._keep(asyncio.ensure_future(finish))

        def waiter() -> asyncio.Future[Reply]:
            waiting: asyncio.Future[Reply] = asyncio.get_running_loop().create_future()
            answer.add_done_callback(functools.partial(_handed_on, waiting))

            def given_up(waited: asyncio.Future[Reply]) -> None:
                if waited.cancelled():
                    self._client_left(governor, principal, key, running, decision, answer)

            waiting.add_done_callback(given_up)
            return waiting

        return Started(finish=waiter)

    def _client_left(self, governor: Governor, principal: Principal, key: tuple[str, str],
                     running: _Running, decision: Decision, answer: asyncio.Future[Reply]
                     ) -> None:
        if running.answering or self._running.get(key) is not running:
            return  # its one answer is made, or on its way to the log: it stands
        if running.pending_id is not None:  # held: its hold's end answers it (`_reviewed`)
            running.client_left = True
            return
        del self._running[key]
        answer.cancel()  # its own wait ends; what it would have done, done here
        self._left_behind(governor, principal, key, running, running.reviewed or decision)
        if running.goal_id is not None:  # (the cancelled task may never have run)
            self._by_goal.pop(running.goal_id, None)
        self._forget_stream(principal, running)

    def _keep(self, task: asyncio.Future[T]) -> asyncio.Future[T]:
        """`task`, referenced until it is done (the loop holds tasks weakly)."""
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    def _left_behind(self, governor: Governor, principal: Principal, key: tuple[str, str],
                     running: _Running, decision: Decision) -> None:
        """An INVOKE whose client left before its answer: motion nobody is left to answer for
        must not run on until its session times out. Its stream ends now (zero, no await);
        its arm's hold, its goal's cancel and its answer are a task of their own, which the
        cancelled waiter cannot cut off."""
        ended = (running.stream is not None and not running.stream_end.done()
                 and governor.end_stream(running.stream, principal, why=BY_CLIENT_LEFT))
        self._keep(asyncio.ensure_future(self._stopped_then_answered(
            governor, principal, key, running, decision, ["its velocity stream ended, zero "
                                                          "sent"] if ended else [])))

    async def _stopped_then_answered(self, governor: Governor, principal: Principal,
                                     key: tuple[str, str], running: _Running,
                                     decision: Decision, stopped: list[str]) -> InvokeResult:
        """Its arm held, its goal cancelled (each audited, as an INVOKE_CANCEL's), then its
        answer. An INVOKE_CANCEL under way stops them itself: never held or cancelled twice."""
        try:
            if running.cancelled:
                stopped.append("its INVOKE_CANCEL stops its motion")
            else:
                stopped += await self._stop_left(governor, principal, running, decision)
        except Exception:  # nobody awaits this task: the log has it, and it is answered
            log.exception("stopping the motion of INVOKE %s, whose client left, failed",
                          running.invoke_id, extra={"principal": principal.name})
            stopped.append("stopping its motion failed (see the bridge's log)")
        done = "; ".join(stopped) or "not followed on"
        result = self._result(running, decision, "failure",
                              f"its client left before it was done: {done}")
        return await self._answer(governor, principal, key, running, result)

    async def _stop_left(self, governor: Governor, principal: Principal, running: _Running,
                         decision: Decision) -> list[str]:
        stopped = []
        if (running.trajectory is not None and not running.held.done()
                and governor.trajectory_running(running.trajectory, principal)):
            held = await governor.hold_trajectory(running.trajectory, principal,
                                                  message_id=decision.message_id,
                                                  why=BY_CLIENT_LEFT)
            stopped.append(f"the arm held where it was ({held.outcome.value})")
        if (running.goal_id is not None and not running.ended.done()
                and governor.goal_held(running.goal_id)):
            cancelled = await governor.cancel_goal(running.goal_id, principal,
                                                   message_id=decision.message_id,
                                                   why=BY_CLIENT_LEFT)
            stopped.append(f"its goal cancelled ({cancelled.outcome.value})")
        return stopped

    async def _finish(self, governor: Governor, principal: Principal, invoke: Invoke,
                      key: tuple[str, str], running: _Running, decision: Decision) -> Reply:
        """Wait for the goal's end (or `timeout_ms`: then cancel it), and answer."""
        assert running.goal_id is not None
        left = invoke.timeout_ms / 1000 - (time.monotonic() - running.started)
        try:
            view = await asyncio.wait_for(asyncio.shield(running.ended), max(left, 0.0))
        except asyncio.TimeoutError:
            cancel = await governor.cancel_goal(running.goal_id, principal,
                                                message_id=decision.message_id,
                                                why="INVOKE timeout")
            result = self._result(running, decision, "timeout",
                                  f"not done within {invoke.timeout_ms} ms: goal cancelled"
                                  f" ({cancel.outcome.value})")
        else:
            result = self._ended(running, decision, view)
        finally:
            self._forget(key, running)
            self._by_goal.pop(running.goal_id, None)
        return 200, await self._answer(governor, principal, key, running, result)

    async def _finish_trajectory(self, governor: Governor, principal: Principal,
                                 invoke: Invoke, key: tuple[str, str], running: _Running,
                                 decision: Decision) -> Reply:
        """An arm's trajectory reports no end (a topic, not an action): it is done when its
        time is up, unless a stop held it before; held by its INVOKE_CANCEL, `cancelled`;
        past `timeout_ms` first, held then (`timeout`)."""
        assert running.trajectory is not None and decision.runs_for_s is not None
        since = time.monotonic() - running.started
        left = invoke.timeout_ms / 1000 - since
        try:
            try:
                held = await asyncio.wait_for(asyncio.shield(running.held),
                                              max(min(decision.runs_for_s - since, left), 0.0))
            except asyncio.TimeoutError:
                result = await self._trajectory_over(governor, principal, running, decision,
                                                     timed_out=decision.runs_for_s - since > left,
                                                     timeout_ms=invoke.timeout_ms)
            else:
                result = self._result(running, decision, "cancelled" if held.outcome is
                                      Outcome.EXECUTED else "failure", held.reason or
                                      "held where it was by INVOKE_CANCEL")
        finally:
            self._forget(key, running)
        return 200, await self._answer(governor, principal, key, running, result)

    async def _trajectory_over(self, governor: Governor, principal: Principal,
                               running: _Running, decision: Decision, *, timed_out: bool,
                               timeout_ms: int) -> InvokeResult:
        assert running.trajectory is not None
        if running.cancelled and not governor.trajectory_running(running.trajectory, principal):
            # Its INVOKE_CANCEL's hold is made (at once), its entry still on its way to the
            # log: no stop's, and no second hold.
            return self._result(running, decision, "cancelled",
                                "held where it was by INVOKE_CANCEL")
        if timed_out:
            held = await governor.hold_trajectory(running.trajectory, principal,
                                                  message_id=decision.message_id,
                                                  why="INVOKE timeout")
            return self._result(running, decision, "timeout",
                                f"not done within {timeout_ms} ms: the arm held where it was "
                                f"({held.outcome.value})")
        if governor.trajectory_running(running.trajectory, principal):
            return self._result(running, decision, "success")
        return self._result(running, decision, "failure",
                            "a stop held the arm before its trajectory's time was up")

    def _stream_started(self, governor: Governor, principal: Principal, running: _Running,
                        decision: Decision) -> bool:
        """Whether the INVOKE's move started a stream its answer waits for: executed, and
        its end heard or the stream running (else the decision repeated an earlier one's,
        whose stream ended before this INVOKE listened: answered as decided). Cancelled while
        it was being decided, it is ended now."""
        assert running.stream is not None
        if decision.outcome is not Outcome.EXECUTED:
            return False
        if running.stream_end.done():
            return True
        if not governor.stream_running(running.stream, principal):
            return False
        if running.cancelled:  # its INVOKE_CANCEL came while it was being decided
            governor.end_stream(running.stream, principal, why=BY_INVOKE_CANCEL)
        return True

    async def _finish_stream(self, governor: Governor, principal: Principal, invoke: Invoke,
                             key: tuple[str, str], running: _Running,
                             decision: Decision) -> Reply:
        """A move is done when its velocity stream ends (`stream_ended`); past `timeout_ms`
        first, the stream is ended then, zero sent (`timeout`). Under way until it is answered:
        an INVOKE_CANCEL meanwhile gets that answer (not `not_found`)."""
        assert running.stream is not None
        left = invoke.timeout_ms / 1000 - (time.monotonic() - running.started)
        try:
            try:
                ended = await asyncio.wait_for(asyncio.shield(running.stream_end),
                                               max(left, 0.0))
            except asyncio.TimeoutError:
                governor.end_stream(running.stream, principal, why=BY_INVOKE_TIMEOUT)
                result = self._result(running, decision, "timeout",
                                      f"not done within {invoke.timeout_ms} ms: its velocity "
                                      "stream ended, zero sent")
            else:
                result = self._stream_result(running, decision, ended)
            return 200, await self._answer(governor, principal, key, running, result)
        finally:
            self._forget(key, running)
            self._forget_stream(principal, running)

    def _stream_result(self, running: _Running, decision: Decision,
                       ended: StreamEnded) -> InvokeResult:
        if ended.reason is EndReason.COMPLETED:  # its duration is over
            return self._result(running, decision, "success")
        if ended.reason is EndReason.CANCELLED and ended.why == BY_INVOKE_CANCEL:
            return self._result(running, decision, "cancelled",
                                "its velocity stream ended by the client's INVOKE_CANCEL, "
                                "zero sent")
        why = _STREAM_ENDED_BY.get(ended.reason, ended.reason.value)
        by = f" ({ended.by})" if ended.by else ""
        return self._result(running, decision, "failure",
                            f"the move ended before it was done: {why}{by}")

    def stream_ended(self, ended: StreamEnded) -> None:
        """Each end of a velocity stream (`Events.stream_ended`, through `_skills.Skills`)."""
        running = self._by_stream.get((ended.stream.owner, ended.stream.message_id))
        if running is not None and not running.stream_end.done():
            running.stream_end.set_result(ended)

    def _forget(self, key: tuple[str, str], running: _Running) -> None:
        """`running` is no longer under way; a later INVOKE of its msg_id (its client left
        this one) that took its key stays."""
        if self._running.get(key) is running:
            del self._running[key]

    def _forget_stream(self, principal: Principal, running: _Running) -> None:
        if running.stream is None:
            return
        by = (principal.name, running.stream)
        if self._by_stream.get(by) is running:  # (as `_forget`)
            del self._by_stream[by]

    def _ended(self, running: _Running, decision: Decision, view: GoalView) -> InvokeResult:
        if view.state == "succeeded":
            return self._result(running, decision, "success", result=view.result)
        if view.state == "canceled" and running.cancelled:
            return self._result(running, decision, "cancelled",
                                "aborted by the client's INVOKE_CANCEL")
        why = f"goal {view.state}" + (f": {view.detail}" if view.detail else "")
        return self._result(running, decision, "failure", why, result=view.result)

    def goal_changed(self, view: GoalView) -> None:
        """Each change of a goal (`RobotView.watch_goals`, through `_skills.Skills`)."""
        running = self._by_goal.get(view.goal_id)
        if running is not None and view.state in TERMINAL and not running.ended.done():
            running.ended.set_result(view)

    # -- INVOKE_CANCEL --------------------------------------------------------------------

    async def cancel(self, governor: Governor, principal: Principal,
                     cancel: InvokeCancel) -> Reply:
        refused = _addressed(governor, cancel.ruri, cancel.principal_id, principal)
        if refused is not None:
            return await _refuse(governor, principal, refused, cancel.message_id)
        key = (principal.name, cancel.invoke_id)  # §19.4: only its own invoker cancels it
        running = self._running.get(key)
        if running is None:
            return await self._not_running(governor, principal, cancel, key)
        # Another INVOKE_CANCEL of it under way (a client retrying) does what it takes
        # already: this one waits for the answer with it, never holding or withdrawing twice
        # (the INVOKE would be answered twice).
        already, running.cancelled = running.cancelled, True
        if not already:
            answer = await self._cancelling(governor, principal, cancel, key, running)
            if answer is not None:
                return _as_cancels(answer, cancel)
        try:  # the INVOKE's own answer, once its goal has wound down
            answered = await asyncio.wait_for(asyncio.shield(running.answered),
                                              cancel.cancel_timeout_ms / 1000)
        except asyncio.TimeoutError:
            return 202, InvokeResult(type="INVOKE_RESULT", status="cancelled",
                                     invoke_id=running.invoke_id, payload={},
                                     skill=running.skill, reply_to=running.invoke_id,
                                     reason="cancelling", msg_id=cancel.message_id)
        return _as_cancels((200, answered), cancel)

    async def _cancelling(self, governor: Governor, principal: Principal,
                          cancel: InvokeCancel, key: tuple[str, str],
                          running: _Running) -> Reply | None:
        """What an INVOKE_CANCEL does to its INVOKE: its reply if that is the answer (a cancel
        refused), else None (the INVOKE's own answer is waited for). A held one is withdrawn,
        and answered `cancelled` as its hold ends (`_reviewed`); one whose review ends it
        first (an approval under way, say) is answered by that, its motion cancelled as it
        starts (`_under_way`)."""
        if running.pending_id is not None:
            await governor.withdraw(running.pending_id, principal, cancel.reason,
                                    said_by=ReviewMessage(message_id=cancel.message_id))
            return None
        if running.goal_id is not None:
            decision = await governor.cancel_goal(running.goal_id, principal,
                                                  message_id=cancel.message_id,
                                                  why=BY_INVOKE_CANCEL)
            if decision.outcome is not Outcome.EXECUTED:  # it runs on: a retry may cancel it
                return _cancel_refused(running, decision, cancel)
        if running.stream is not None and not running.stream_end.done():
            # Only this INVOKE's stream: one that replaced it runs on. Not yet started (being
            # decided), it is ended once it starts (`_stream_started`).
            governor.end_stream(running.stream, principal, why=BY_INVOKE_CANCEL)
        if running.trajectory is not None and not running.held.done():
            held = await governor.hold_trajectory(running.trajectory, principal,
                                                  message_id=cancel.message_id,
                                                  why=BY_INVOKE_CANCEL)
            if held.outcome is not Outcome.EXECUTED:  # it runs on: its end is answered then
                return _cancel_refused(running, held, cancel)
            running.held.set_result(held)
        return None

    async def _not_running(self, governor: Governor, principal: Principal,
                           cancel: InvokeCancel, key: tuple[str, str]) -> Reply:
        earlier = self._finished.get(key)
        rejection = INVOKE_NOT_FOUND if earlier is None else INVOKE_FINISHED
        decision = await governor.reject_request(principal, rejection,
                                                 message_id=cancel.message_id)
        if earlier is None:
            return decision.http_status, InvokeResult(
                type="INVOKE_RESULT", status="not_found", invoke_id=cancel.invoke_id,
                payload={}, reply_to=cancel.invoke_id,
                error=skill_error("not_found", f"no INVOKE {cancel.invoke_id!r} of yours is "
                                  "running"),
                outcome=decision.outcome.value, audit_id=decision.audit_id,
                error_code=rejection.error_code.value, reason=rejection.reason,
                msg_id=cancel.message_id)
        # §19.4: the earlier INVOKE_RESULT stands; it is repeated, with this refusal's entry.
        return decision.http_status, msgspec.structs.replace(
            earlier, reason=rejection.reason, audit_id=decision.audit_id,
            msg_id=cancel.message_id)

    # -- answers --------------------------------------------------------------------------

    def _result(self, running: _Running, decision: Decision, status: InvokeStatus,
                message: str | None = None, *, result: dict[str, object] | None = None,
                kind: str | None = None) -> InvokeResult:
        error = None
        if status != "success":
            error = skill_error(kind or _kind(status, decision),
                                message or decision.reason or status)
        body = decision.body()
        return InvokeResult(
            type="INVOKE_RESULT", status=status, invoke_id=running.invoke_id,
            payload=result or {}, skill=running.skill, reply_to=running.invoke_id,
            duration_ms=int((time.monotonic() - running.started) * 1000), result=result,
            error=error, outcome=body.outcome, audit_id=body.audit_id,
            message_id=body.message_id, msg_id=running.invoke_id, error_code=body.error_code,
            reason=body.reason, applied=body.applied, goal_id=body.goal_id,
            ros2_topic=body.ros2_topic, warnings=body.warnings)

    async def _answer(self, governor: Governor, principal: Principal, key: tuple[str, str],
                      running: _Running, result: InvokeResult) -> InvokeResult:
        """The INVOKE's one INVOKE_RESULT (§19.1): audited, remembered for a late
        INVOKE_CANCEL, handed to a cancel waiting for it. Only the first answer counts: an
        INVOKE answered as its client left may have been answered by its own end in that
        very step (a task cancelled as what it waits for is done runs on: `wait_for`)."""
        if running.answering:
            return await asyncio.shield(running.answered)
        running.answering = True
        await _audit(governor, principal, result)
        self._finished[key] = result
        self._finished.move_to_end(key)
        while len(self._finished) > FINISHED_KEPT:
            self._finished.popitem(last=False)
        if not running.answered.done():
            running.answered.set_result(result)
        return result

    async def _refused(self, governor: Governor, principal: Principal, invoke: Invoke,
                       rejection: Rejection, kind: str, message: str, *,
                       path: str | None = None) -> Reply:
        """An INVOKE refused before it became a command: audited, answered INVOKE_RESULT; in
        a task of its own, whose entries a caller cancelled meanwhile does not cut off."""
        return await asyncio.shield(self._keep(asyncio.ensure_future(self._refusal(
            governor, principal, invoke, rejection, kind, message, path=path))))

    async def _refusal(self, governor: Governor, principal: Principal, invoke: Invoke,
                       rejection: Rejection, kind: str, message: str, *,
                       path: str | None) -> Reply:
        decision = await governor.reject_request(principal, rejection, message_id=invoke.msg_id,
                                                 rcan=invoke.envelope.audit_facts())
        result = InvokeResult(
            type="INVOKE_RESULT", status=_STATUS_OF_KIND[kind], invoke_id=invoke.msg_id,
            payload={}, skill=invoke.skill, reply_to=invoke.msg_id,
            error=skill_error(kind, message), outcome=decision.outcome.value,
            audit_id=decision.audit_id, message_id=invoke.msg_id, msg_id=invoke.msg_id,
            error_code=rejection.error_code.value, reason=message if path else rejection.reason,
            path=path)
        await _audit(governor, principal, result)
        return decision.http_status, result


# -- AUTHORIZE --------------------------------------------------------------------------------


async def authorize(governor: Governor, principal: Principal, message: Authorization) -> Reply:
    """AUTHORIZE (§16.4) is `/api/hitl/authorize` or `/deny` in a message: the governor checks
    the reviewer's role, counts n-of-m approvals and audits, as for those endpoints."""
    # (refused, it is audited with its envelope's facts: whose key signed it, if one did)
    facts = message.envelope.audit_facts()
    refused = _addressed(governor, message.ruri, message.principal_id, principal)
    if refused is not None:
        return await _refuse(governor, principal, refused, message.message_id, facts)
    pending_id = message.pending_id
    if pending_id is None:
        assert message.thought_id is not None
        pending_id = governor.pending_for_thought(message.thought_id)
        if pending_id is None:
            return await _refuse(governor, principal, outcomes.PENDING_NOT_FOUND,
                                 message.message_id, facts)
    review = governor.authorize if message.verdict == "approve" else governor.deny
    said_by = ReviewMessage(message_id=message.message_id, rcan=facts,
                            command_message_id=message.command_message_id)
    decision = await review(pending_id, principal, message.reason, said_by=said_by)
    return decision.http_status, _body(decision.body(), message.message_id)


def _addressed(governor: Governor, ruri: str | None, principal_id: str | None,
               principal: Principal) -> Rejection | None:
    """A message for another robot, or one that names another principal as its sender."""
    if principal_id is not None and principal_id != principal.name:
        return NOT_YOUR_PRINCIPAL_ID
    return governor.not_this_robot(ruri)


async def _refuse(governor: Governor, principal: Principal, rejection: Rejection,
                  msg_id: str | None, rcan: dict[str, Any] | None = None) -> Reply:
    decision = await governor.reject_request(principal, rejection, message_id=msg_id,
                                             rcan=rcan)
    return decision.http_status, _body(decision.body(), msg_id)


def _as_cancels(reply: Reply, cancel: InvokeCancel) -> Reply:
    """The INVOKE's INVOKE_RESULT as its INVOKE_CANCEL's answer: with the cancel's own id as
    `msg_id`, when it has one (RCANResponse's echo of the message it answers; `reply_to`
    names the INVOKE), as its 202 and 409 answers have."""
    status, body = reply
    if isinstance(body, InvokeResult) and cancel.message_id is not None:
        return status, msgspec.structs.replace(body, msg_id=cancel.message_id)
    return reply


def _cancel_refused(running: _Running, refused: Decision, cancel: InvokeCancel) -> Reply:
    """An INVOKE_CANCEL whose cancel of the goal, or hold of the arm, was refused: the
    INVOKE runs on (a retry may cancel it), and the cancel is answered with the refusal."""
    running.cancelled = False
    return refused.http_status, _body(refused.body(), cancel.message_id)


def _body(body: DecisionBody, msg_id: str | None) -> DecisionBody:
    body.msg_id, body.status = msg_id or body.message_id, STATUS_OF[body.outcome]
    return body


def _handed_on(waiting: asyncio.Future[Reply], answer: asyncio.Future[Reply]) -> None:
    """An INVOKE's answer task done: its waiter gets what it gave (an error nobody waits for
    any more is logged here)."""
    if answer.cancelled():  # its client left (the waiter was cancelled first), or shutdown
        waiting.cancel()
        return
    error = answer.exception()
    if waiting.done():
        if error is not None:
            log.error("answering an INVOKE whose client left failed", exc_info=error)
    elif error is not None:
        waiting.set_exception(error)
    else:
        waiting.set_result(answer.result())


def _nobody_waits(deciding: asyncio.Future[Started]) -> None:
    """An INVOKE decided after its caller was cancelled (its client left): one under way is
    left as a client that leaves leaves it (`Invocations._answering`); one answered at once
    is answered in the log already."""
    if deciding.cancelled():
        return
    error = deciding.exception()
    if error is not None:
        log.error("an INVOKE whose client left failed", exc_info=error)
    elif (started := deciding.result()).finish is not None:
        started.finish().cancel()


def _view(skill: SkillConfig, governor: Governor) -> SkillView:
    return SkillView(action=skill.action, role=governor.role_for(skill.action).name,
                     params=dict(skill.params), allow=list(skill.allow),
                     description=skill.description)


async def _audit(governor: Governor, principal: Principal, result: InvokeResult) -> None:
    """The INVOKE_RESULT entry of an INVOKE's answer."""
    facts: dict[str, object] = {"skill": result.skill, "duration_ms": result.duration_ms,
                                "goal_id": result.goal_id, "result": result.result}
    if result.error is not None:
        facts["error"] = {"code": result.error.code, "name": result.error.name}
    await governor.invoke_result(
        principal, invoke_id=result.invoke_id, status=result.status, outcome=result.outcome,
        facts={k: v for k, v in facts.items() if v is not None},
        detail=None if result.error is None else result.error.message)


def _review_status(running: _Running, end: Ended) -> tuple[InvokeStatus, str | None]:
    """A held INVOKE's status once its hold ended, and its error's message: expired
    `timeout`; withdrawn by its INVOKE_CANCEL `cancelled`; withdrawn otherwise or denied
    `failure`, naming who or what did it (a stop's withdrawal says which stop); approved,
    as any decision (`_decided_status`: a refusal of it as it ran is a `failure`)."""
    decision, review = end.decision, end.review
    if decision.reason == outcomes.PENDING_EXPIRED.reason:
        return "timeout", "no approval came within its HiTL timeout: it expired"
    if review is None or review.decision == "approve":
        return _decided_status(decision), None
    if review.decision == "withdraw" and running.cancelled:
        return "cancelled", "withdrawn by INVOKE_CANCEL"
    verb = "withdrawn" if review.decision == "withdraw" else "denied"
    if review.reason is not None and review.reason.startswith(f"{verb}:"):
        return "failure", review.reason  # the governor's words: which stop withdrew it
    return "failure", f"{verb} by '{review.principal}'" + (
        f": {review.reason}" if review.reason else "")


def _decided_status(decision: Decision) -> InvokeStatus:
    if decision.outcome is Outcome.EXECUTED:
        return "success"
    if decision.error_code is ErrorCode.INSUFFICIENT_PRIVILEGES:
        return "unauthorized"
    return "failure"


def _kind(status: InvokeStatus, decision: Decision) -> str:
    if status == "failure" and decision.reason in _CONFLICTS:
        return "conflict"
    return status


NO_SKILLS = Invocations({}, None)  # where no skills were given: every INVOKE is not_found
