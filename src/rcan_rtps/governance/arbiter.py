"""The base arbiter: who drives the base — velocity streams, goals, locks and priorities.

`VelocityStreams` (streams.py) holds the state: the one active stream, the goals holding the
base, the engaged locks. This module is what the governor asks of it for a command: start a
stream behind its write-ahead entry, hold an accepted goal (cancelling what it replaces),
engage or release a lock (cancelling the goals below it), and audit every end it causes.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Callable, Mapping
from typing import Any

from rcan_rtps.rcan import ActionParams, Effect, NormalizedCommand, Outcome
from rcan_rtps.rcan.actions import LockParams, MoveParams

from . import outcomes
from .audit import AuditEvent, AuditReceipt, AuditRecord
from .estop import EstopMachine
from .outcomes import Rejection
from .priorities import MotionPriorities
from .rbac import Principal
from .steps import (
    Decision,
    DispatchResult,
    Steps,
    decision,
    executed,
    record,
    refused_event,
)
from .streams import (
    EndReason,
    HeldGoal,
    Replaces,
    StopMark,
    Stream,
    StreamEnded,
    Velocity,
    VelocityStreams,
)

log = logging.getLogger("rcan_rtps.governance.governor")
Sending = Callable[[Principal, NormalizedCommand], None]
ENDED_BY_KEPT = 1024  # cancelled goals whose end is still awaited, remembered at most


class BaseArbiter:
    """`sending` is told just before motion reaches the robot (its owner's session opens)."""

    def __init__(self, steps: Steps, streams: VelocityStreams, priorities: MotionPriorities,
                 latch: EstopMachine, sending: Sending,
                 held_locks: Mapping[str, str] | None = None,
                 stream_ended: Callable[[StreamEnded], None] | None = None) -> None:
        self._steps = steps
        self.streams = streams
        self.priorities = priorities
        self._latch = latch
        self._sending = sending
        self._held_at_start = dict(held_locks or {})  # lock → holder, as the log left them
        self.lock_holders: dict[str, str] = {}  # engaged locks → who engaged them
        # Goals the arbiter cancelled → why, by whom (for their GOAL_FINISHED); bounded: a goal
        # whose server vanished never reports its end.
        self._ended_by: OrderedDict[str, str] = OrderedDict()
        # Told of each end once it is audited (`Events.stream_ended`: an INVOKE waiting for it).
        self._told: Callable[[StreamEnded], None] = stream_ended or (lambda ended: None)
        streams.on_end = self._stream_ended

    def admits(self, priority: int) -> Rejection | None:
        """None if motion at `priority` may take the base now, else why not."""
        return self.streams.admits(priority)

    def retake_locks(self) -> list[str]:
        """Engage the locks the log says were held; those no longer configured are released
        (their names returned, for BRIDGE_STARTED)."""
        released = []
        for name, holder in sorted(self._held_at_start.items()):
            level = self.priorities.lock(name)
            if level is None:
                released.append(name)
                continue
            self.streams.lock(name, level, holder)
            self.lock_holders[name] = holder
            log.warning("motion lock %r (engaged by %s) held again after the restart",
                        name, holder)
        return released

    # -- goals ------------------------------------------------------------------------------

    def hold_goal(self, goal_id: str | None, owner: Principal, priority: int,
                  message_id: str, stops: StopMark) -> Rejection | None:
        """An accepted goal holds the base: the stream and the goals it replaces end. If a
        stop of it came since it was decided (`stops`: its `streams.mark`), or a higher stream,
        goal or lock took the base while it was being sent, it is cancelled (the refusal
        returned): a stop's cancel reaches only the goals a server has."""
        if goal_id is None:
            return None
        goal = HeldGoal(goal_id, owner.name, priority, message_id)
        refused = self.streams.admits(priority, since=stops)
        if refused is not None:
            self.cancel_goals([goal], owner, why=refused.reason or "refused")
            return refused
        self.streams.end(EndReason.REPLACED, owner.name)  # a stream would fight the goal
        self.cancel_goals(self.streams.goal_started(goal), owner)
        return None

    def cancel_goals(self, goals: list[HeldGoal], by: Principal, *,
                     why: str = "replaced") -> None:
        """Cancel goals the arbiter took off the base (never awaited by the command); their
        GOAL_FINISHED entries say by whom."""
        for goal in goals:
            reason = why if goal.owner == by.name or why != "replaced" else "preempted"
            self._remember_end(goal.goal_id, f"{reason} by {by.name}")
            log.warning("cancelling goal %s of %s: %s by %s", goal.goal_id, goal.owner,
                        reason, by.name, extra={"principal": by.name})
            self._steps.spawn(self._cancel_goal(goal.goal_id))

    async def cancel_requested(self, goal_id: str, principal: Principal, *,
                               message_id: str | None, why: str) -> Decision:
        """Cancel one goal at its sender's request (an INVOKE_CANCEL of the INVOKE that started
        it, or that INVOKE's timeout, §19): the entry first, then the cancel; the goal's
        GOAL_FINISHED says by whom. The caller has checked the goal is `principal`'s."""
        entry = AuditRecord(event=AuditEvent.COMMAND_DISPATCHED, principal=principal.name,
                            role=principal.role.name, message_id=message_id,
                            action_type="cancel_goal", params={"goal_id": goal_id, "why": why},
                            outcome=Outcome.EXECUTED.value)
        receipt = await self._steps.write_ahead(entry)
        if receipt is None:
            return decision(outcomes.AUDIT_UNAVAILABLE, message_id=message_id)
        self._remember_end(goal_id, f"{why} by {principal.name}")
        try:
            cancelling = await self._steps.dispatcher.cancel_goal(goal_id)
        except Exception:
            log.exception("cancelling goal %s failed", goal_id)
            cancelling = False
        if not cancelling:
            self._ended_by.pop(goal_id, None)
            failed = outcomes.robot_unavailable("goal_not_cancelled")
            await self._steps.record_event(AuditRecord(
                event=AuditEvent.COMMAND_FAILED, principal=principal.name,
                role=principal.role.name, message_id=message_id, action_type="cancel_goal",
                params={"goal_id": goal_id}, outcome=failed.outcome.value,
                deny_reason=failed.deny_reason))
            return decision(failed, message_id=message_id)
        return Decision(outcome=Outcome.EXECUTED, http_status=200, audit_id=receipt.audit_id,
                        message_id=message_id, goal_id=goal_id)

    def _remember_end(self, goal_id: str, by: str) -> None:
        """Who ended a goal, for its GOAL_FINISHED; the oldest let go past ENDED_BY_KEPT (a
        goal whose server vanished never reports its end)."""
        self._ended_by[goal_id] = by
        self._ended_by.move_to_end(goal_id)
        while len(self._ended_by) > ENDED_BY_KEPT:
            self._ended_by.popitem(last=False)

    async def _cancel_goal(self, goal_id: str) -> None:
        try:
            if not await self._steps.dispatcher.cancel_goal(goal_id):
                log.warning("goal %s was not cancelled (already over?)", goal_id)
        except Exception:
            log.exception("cancelling goal %s failed", goal_id)

    def goal_ended(self, goal_id: str) -> str | None:
        """A goal ended: the base is free of it; returns who ended it, if the arbiter did."""
        self.streams.goal_ended(goal_id)
        return self._ended_by.pop(goal_id, None)

    # -- velocity streams -------------------------------------------------------------------

    async def stream(self, command: NormalizedCommand, principal: Principal,
                     owner: Principal, params: ActionParams, applied: dict[str, Any],
                     event: AuditEvent, pending_id: str | None, priority: int,
                     stops: StopMark) -> Decision:
        """A move: its write-ahead entry (naming the stream it replaces), then the stream —
        unless a stop of it came since it was decided (`stops`: its `streams.mark`).

        The claim is made with no await before the entry is sealed, so claims and entries
        come in the same order; a move that does not start releases its claim."""
        steps = self._steps
        replaces = self.streams.claim(owner.name, command.message_id, priority)
        if replaces is not None:  # recorded here: a replaced stream's end costs no entry
            applied = {**applied, "replaces": replaces.entry()}
        entry = record(event, command, principal, Outcome.EXECUTED, applied=applied,
                       pending_id=pending_id, ros2_topic=steps.route(command))
        try:
            receipt = await steps.write_ahead(entry)
            if receipt is None:
                return decision(outcomes.AUDIT_UNAVAILABLE, message_id=command.message_id)
            # Checked again after the write, with no await between this check and the publish.
            halted = self.streams.halted_since(stops)
            if halted is not None:
                return await steps.failed(command, principal, halted)
            return await self._start_stream(command, owner, params, priority, stops,
                                             (applied, receipt), replaces)
        finally:
            self.streams.release(owner.name, command.message_id)

    async def _start_stream(self, command: NormalizedCommand, principal: Principal,
                            params: ActionParams, priority: int, stops: StopMark,
                            audited: tuple[dict[str, Any], AuditReceipt],
                            replaces: Replaces | None) -> Decision:
        """After the write-ahead entry: the first sample, then the stream takes over.

        No await between the admission check, the first sample (the dispatcher publishes
        motion before its first await) and `start`: the stream state cannot change in between.
        """
        assert isinstance(params, MoveParams), "only a move is streamed"
        steps = self._steps
        self.streams.release(principal.name, command.message_id)  # refused or started: done
        refused = self.streams.admits(priority)
        if refused is not None:
            return await steps.failed(command, principal, refused)
        target = Velocity.of(params)
        first = self.streams.first_sample(target)
        self._sending(principal, command)
        result, failure = await steps.dispatch(command, first.params())
        if failure is not None:
            return await steps.failed(command, principal, failure)
        stream = Stream(action=command.action, owner=principal.name, priority=priority,
                        target=target, message_id=command.message_id,
                        duration_s=params.duration_s, stops=stops)
        refused = self.streams.start(stream, first, by=principal.name, recorded=replaces)
        if refused is not None:
            return await steps.failed(command, principal, refused)
        self.cancel_goals(self.streams.take_goals(below=priority + 1), principal)
        return executed(command, audited[0], audited[1], result)

    def _stream_ended(self, ended: StreamEnded) -> None:
        if not ended.recorded:  # else the replacing move's entry says so (`applied.replaces`)
            self._record_end(ended)
        self._told(ended)

    def _record_end(self, ended: StreamEnded) -> None:
        stream = ended.stream
        params: dict[str, Any] = {"reason": ended.reason.value, "ended_by": ended.by,
                                  "samples": stream.samples,
                                  "seconds": round(ended.at - stream.started_at, 3)}
        if ended.why is not None:
            params["why"] = ended.why
        entry = AuditRecord(
            event=AuditEvent.STREAM_ENDED, principal=stream.owner, action_type=stream.action,
            message_id=stream.message_id, params=params,
            applied={"last": ended.last._asdict(), "zero_sent": ended.zeroed})
        # Sealed in the step that ended it (a stop's halt, the e-stop's reflex), not a task's
        # step later: the log lists it where the robot got its zero, before the stop's entry.
        self._steps.record_now(entry)

    # -- locks ------------------------------------------------------------------------------

    async def lock(self, command: NormalizedCommand, principal: Principal,
                   params: ActionParams, event: AuditEvent, pending_id: str | None) -> Decision:
        """Engage or release a configured lock: only at or below the sender's priority."""
        assert isinstance(params, LockParams), "a lock names its lock"
        steps = self._steps
        level = self.priorities.lock(params.name)
        refused = (outcomes.UNKNOWN_LOCK if level is None else outcomes.LOWER_PRIORITY
                   if self.priorities.of(principal) < level else None)
        if refused is not None or level is None:
            return await steps.refuse(command, principal, refused or outcomes.UNKNOWN_LOCK,
                                      event=refused_event(event), pending_id=pending_id)
        applied = {"name": params.name, "priority": level}
        entry = record(event, command, principal, Outcome.EXECUTED, applied=applied,
                       pending_id=pending_id)
        receipt = await steps.write_ahead(entry)
        if receipt is None:
            return decision(outcomes.AUDIT_UNAVAILABLE, message_id=command.message_id)
        if command.spec.effect is Effect.LOCK:
            lower = self.streams.lock(params.name, level, principal.name)
            self.lock_holders[params.name] = principal.name
            self.cancel_goals(lower, principal, why=f"locked out by {params.name!r}")
        else:
            self.streams.unlock(params.name)
            self.lock_holders.pop(params.name, None)
        return executed(command, applied, receipt, DispatchResult(ok=True))
