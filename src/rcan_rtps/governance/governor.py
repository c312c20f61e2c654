"""The one entry point: authenticated command in, decision out, audited before it acts.

Order (§3.1): RBAC → rate limit → idempotency → §8 invariants → §9 HiTL → robot ready →
§6 audit (durable) → dispatch. Write-ahead: a command's decision entry is on disk before anything
reaches the robot; a send that then fails adds a COMMAND_FAILED entry. If the entry cannot be
written, nothing is sent.

The e-stop lane: `estop` and `stop` are never rate-limited and never answered from another
command's idempotency entry. E-stop and clear are one serialized state machine (`estop.py`).
"""

from __future__ import annotations

import asyncio
import functools
import logging
import uuid
from collections.abc import Callable, Coroutine, Mapping
from pathlib import Path
from typing import Any, Protocol, cast

import msgspec

from rcan_rtps.config import RcanConfig
from rcan_rtps.rcan import (
    ActionParams,
    Approval,
    DecisionBody,
    Effect,
    ErrorCode,
    InvalidRuriError,
    NormalizedCommand,
    Outcome,
    PendingAuth,
    Role,
    RoleName,
    parse_ruri,
)
from rcan_rtps.rcan.actions import LockParams, MoveParams, with_effect

from .._listeners import tell_all
from . import outcomes
from .ai import AiPolicy
from .audit import AuditEvent, AuditLog, AuditReceipt, AuditRecord
from .clock import Clock, SystemClock, now_ms
from .errors import AuditError, EstopStateError
from .estop import EstopMachine, EstopRepeats, LatchFile
from .hitl import Escalate, Held, HitlPolicy, Notifier, PendingCommand, PendingStore, Verdict
from .idempotency import Conflict, Idempotency
from .invariants import Check, Violation, safety_policy
from .outcomes import Rejection
from .priorities import MotionPriorities
from .rbac import Principal, RateLimiter, RolePolicy
from .resume import resume
from .sessions import Sessions
from .streams import (
    AccelLimits,
    EndReason,
    HeldGoal,
    Replaces,
    Stream,
    StreamEnded,
    Velocity,
    VelocityStreams,
)

log = logging.getLogger(__name__)
SWEEP_INTERVAL_S = 0.05  # session-loss halt latency is timeout + at most this
# Commands decided at once; the rest wait their turn without using the event loop, so a flood
# of requests cannot queue the e-stop lane (which never waits here) behind itself. The limit
# also caps how many audit entries share one fsync: 16 measured ~4 entries per fsync against
# ~2 at 8, and ~20 % less CPU per command, for an e-stop p99 under 500 clients of ~28 ms
# (18 ms at 8, 60 ms at 32; target 50 ms).
MAX_IN_FLIGHT = 16


class DispatchResult(msgspec.Struct, frozen=True, kw_only=True):
    """What the bridge reports after handing a command to ROS 2."""

    ok: bool
    ros2_topic: str | None = None
    goal_id: str | None = None
    detail: str | None = None


class Dispatcher(Protocol):
    """The hook the bridge plugs in; `applied` is what may be sent (clamped, checked), typed
    as the action's parameters all the way to the ROS message."""

    def route(self, command: NormalizedCommand) -> str | None:
        """Where `command` will go (a topic or action name), for its write-ahead entry."""
        ...

    async def ready(self, command: NormalizedCommand) -> str | None:
        """None if the robot can take `command` now, else why not (ROBOT_UNAVAILABLE)."""
        ...

    async def dispatch(
        self, command: NormalizedCommand, applied: ActionParams
    ) -> DispatchResult:
        """Send `command`; motion is published before the first await (after `ready`)."""
        ...

    def send_velocity(self, velocity: MoveParams) -> str | None:
        """Publish one sample of a velocity stream now; None if sent, else why not."""
        ...

    async def cancel_goal(self, goal_id: str) -> bool:
        """Cancel one goal `dispatch` started; True if its server is canceling it."""
        ...

    def signal_estop(self) -> None:
        """Publish the e-stop signal now (no await): the moment the latch engages, beside the
        zero velocity; the e-stop's dispatch then tells the robot again and halts it."""
        ...


class Decision(msgspec.Struct, frozen=True, kw_only=True):
    outcome: Outcome
    http_status: int
    error_code: ErrorCode | None = None
    reason: str | None = None
    applied: dict[str, Any] | None = None
    audit_id: str | None = None
    message_id: str | None = None
    pending_id: str | None = None
    expires_at_ms: int | None = None
    ros2_topic: str | None = None
    goal_id: str | None = None
    warnings: list[str] | None = None  # a stop executed in spite of these problems

    def body(self) -> DecisionBody:
        return DecisionBody(
            outcome=self.outcome.value,
            audit_id=self.audit_id, message_id=self.message_id,
            error_code=self.error_code.value if self.error_code else None, reason=self.reason,
            applied=self.applied, pending_id=self.pending_id, expires_at_ms=self.expires_at_ms,
            goal_id=self.goal_id, ros2_topic=self.ros2_topic, warnings=self.warnings,
        )


class Governor:
    def __init__(self, *, audit: AuditLog, dispatcher: Dispatcher, roles: RolePolicy,
                 limiter: RateLimiter, safety: Check, latch: EstopMachine, hitl: HitlPolicy,
                 clock: Clock, hitl_timeout_s: float = 300.0,
                 require_distinct_approver: bool = False, session_timeout_s: float = 2.0,
                 unattended_move_s: float | None = None,
                 robot_ruri: str | None = None, notifier: Notifier | None = None,
                 streams: VelocityStreams | None = None,
                 priorities: MotionPriorities | None = None,
                 held_locks: Mapping[str, str] | None = None,
                 ai: AiPolicy | None = None) -> None:
        self.audit = audit
        self.latch = latch
        self._dispatcher = dispatcher
        self._roles = roles
        self._limiter = limiter
        self._safety = safety
        self._hitl = hitl
        self._ai = ai or AiPolicy()
        self._clock = clock
        self._pending = PendingStore()
        self._idem: Idempotency[tuple[str, str], Decision] = Idempotency(clock)
        self._latch_file_missing = latch.file.missing()
        self._hitl_ttl_ms = int(hitl_timeout_s * 1000)
        self._distinct = require_distinct_approver
        self._sessions = Sessions(clock, session_timeout_s, unattended_move_s)
        self._robot = parse_ruri(robot_ruri).robot if robot_ruri else None
        self._notifier = notifier
        self._tasks: set[asyncio.Task[Any]] = set()
        self._admission = asyncio.Semaphore(MAX_IN_FLIGHT)
        self._sweeper: asyncio.Task[None] | None = None
        self.started = False  # BRIDGE_STARTED is durable
        self._stopped = False
        self.safe_stop_listeners: list[Callable[[Principal], None]] = []
        # Told just before a lost session's halt, while its goals are still active.
        self.session_lost_listeners: list[Callable[[Principal], None]] = []
        # Told when what STATUS shows of governance changes: the latch, pending approvals.
        self.status_listeners: list[Callable[[], None]] = []
        # The one owner of the velocity streams; an e-stop ends them first thing.
        self.streams = streams or VelocityStreams(dispatcher, latch)
        self.streams.on_end = self._stream_ended
        self._priorities = priorities or MotionPriorities()
        self._held_at_start = dict(held_locks or {})  # lock → holder, as the log left them
        self._lock_holders: dict[str, str] = {}  # engaged locks → who engaged them
        self._repeats = EstopRepeats()
        # The ESTOP entry holding the latch, while no clear was audited after it.
        self._latched_by: AuditReceipt | None = None
        self._ended_by: dict[str, str] = {}  # goals the arbiter cancelled → why, by whom
        latch.listeners.insert(0, self.streams.on_latch)
        latch.listeners.insert(1, self._signal_estop)
        latch.listeners.append(self._status_changed)

    @classmethod
    def from_config(cls, config: RcanConfig, *, audit: AuditLog, dispatcher: Dispatcher,
                    clock: Clock | None = None, notifier: Notifier | None = None) -> Governor:
        bridge, clock = config.bridge, clock or SystemClock()
        beside_audit = Path(bridge.audit.path).parent / "estop.state"
        latch_file = LatchFile(Path(bridge.safety.estop_state_path or beside_audit))
        # A missing latch file is a first start only if the audit log is new as well.
        latched, reason = latch_file.load(first_start=audit.head.last_seq == 0)
        resumed = resume(audit.path)
        if resumed.latched and not latched:  # the stricter of file and signed chain
            latched, reason = True, (
                f"the audit log's last e-stop (by {resumed.latched_by}) was never cleared, "
                f"though {latch_file.path} says it was: latched until cleared")
        if reason:
            log.error("%s", reason)
        latch = EstopMachine(latch_file, latched=latched, reason=reason)
        safety = bridge.safety
        streams = VelocityStreams(dispatcher, latch, rate_hz=bridge.ros2.cmd_rate_hz,
                                  accel=AccelLimits(safety.max_linear_accel,
                                                    safety.max_angular_accel))
        return cls(
            audit=audit, dispatcher=dispatcher, clock=clock, latch=latch, notifier=notifier,
            roles=RolePolicy({a: Role[r] for a, r in bridge.rbac.action_roles.items()}),
            limiter=RateLimiter(clock),
            safety=safety_policy(safety, latch, bridge.ros2.nav_frame_id, streams,
                                 arms=bridge.ros2.arms),
            streams=streams, priorities=MotionPriorities(bridge.motion),
            hitl=HitlPolicy(bridge.hitl, Role[bridge.rbac.hitl_approver_role]),
            hitl_timeout_s=bridge.hitl.timeout_seconds,
            require_distinct_approver=bridge.hitl.require_distinct_approver,
            session_timeout_s=bridge.safety.session_timeout_s,
            unattended_move_s=bridge.safety.unattended_move_s,
            robot_ruri=config.robot.ruri, held_locks=resumed.locks,
            ai=AiPolicy(bridge.ai.agents),
        )

    # -- lifecycle --------------------------------------------------------------------------

    async def start(self) -> None:
        """BRIDGE_STARTED (durable), then a latched start tells the robot again."""
        params: dict[str, Any] = {"estop_latched": self.latch.latched}
        if self.latch.reason:
            params["estop_reason"] = self.latch.reason
        released = self._retake_locks()
        params["locks"] = dict(self._lock_holders)
        if released:
            params["locks_released"] = released
        await self.audit.append(AuditRecord(event=AuditEvent.BRIDGE_STARTED, params=params))
        self.started = True
        if self._latch_file_missing and not self.latch.latched:  # first start: record it
            await self.latch.file.write(False, "first start", now_ms(self._clock))
        if self.latch.latched:  # latched now; the robot is told without delaying the start
            self._spawn(_awaited(self.latch.engage(self._republish_estop)))
        self._sweeper = asyncio.create_task(self._sweep_forever())

    async def _republish_estop(self) -> None:
        _, failure = await self._dispatch(_bridge_command(Effect.ESTOP))
        if failure is not None:
            log.error("latched at start, but the robot could not be told (%s)", failure.reason)

    async def stop(self) -> None:
        """BRIDGE_STOPPED once the sweeper, the tasks and the latch are done. Idempotent."""
        if self._stopped:
            return
        self._stopped = True
        self.end_streams()
        if self._sweeper is not None:
            self._sweeper.cancel()
            await asyncio.gather(self._sweeper, return_exceptions=True)
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self.latch.close()
        await self._record_repeats()
        params = {"estop_latched": self.latch.latched, "locks": dict(self._lock_holders)}
        await self.audit.append(AuditRecord(event=AuditEvent.BRIDGE_STOPPED, params=params))

    def _retake_locks(self) -> list[str]:
        """Engage the locks the log says were held; those no longer configured are released
        (their names returned, for BRIDGE_STARTED)."""
        released = []
        for name, holder in sorted(self._held_at_start.items()):
            level = self._priorities.lock(name)
            if level is None:
                released.append(name)
                continue
            self.streams.lock(name, level, holder)
            self._lock_holders[name] = holder
            log.warning("motion lock %r (engaged by %s) held again after the restart",
                        name, holder)
        return released

    # -- commands ---------------------------------------------------------------------------

    async def decide(self, command: NormalizedCommand, principal: Principal) -> Decision:
        """Decide, act and audit; a caller that goes away does not stop the decision."""
        effect = command.spec.effect
        if command.spec.stopping:
            command = self._forgiven(command, principal)
        if effect is Effect.ESTOP:  # any authenticated principal; latched right here
            decision = await asyncio.shield(
                self.latch.engage(lambda: self._estop(command, principal)))
        elif effect is Effect.HALT:  # the e-stop lane: no admission queue
            decision = await self._detached(self._decide(command, principal))
        else:
            async with self._admission:
                return await self._detached(self._decide(command, principal))
        if command.warnings:  # executed anyway: the caller learns what was wrong
            return msgspec.structs.replace(decision, warnings=list(command.warnings))
        return decision

    def _signal_estop(self) -> None:
        """The latch's listener: the robot hears of an e-stop as it latches, before any await
        (no loop turn, no disk), like the zero velocity the streams send from theirs."""
        if self.latch.latched:
            self._dispatcher.signal_estop()

    def _forgiven(self, command: NormalizedCommand, principal: Principal) -> NormalizedCommand:
        """A stop whose role claim or RURI would refuse another command: those become
        warnings, and the stop goes ahead (an authenticated request that says stop, stops)."""
        warnings = list(command.warnings)
        if _claims_more(command.claimed_role, principal.role):
            warnings.append(f"role claim {command.claimed_role!r} ignored: the role comes "
                            f"from authentication ({principal.role.name})")
        ruri = command.ruri
        if ruri is not None and self._robot is not None:
            try:
                if parse_ruri(ruri).robot != self._robot:
                    warnings.append(f"addressed to {ruri}, not this robot ({self._robot})")
            except InvalidRuriError as exc:
                warnings.append(f"ruri ignored: {exc.rule}")
        ai_problem = self._ai.warning(command, principal)
        if ai_problem is not None:
            warnings.append(ai_problem)
        if len(warnings) == len(command.warnings):
            return command
        return msgspec.structs.replace(command, warnings=tuple(warnings), claimed_role=None,
                                       ruri=None)

    async def reject_request(self, principal: Principal | None, rejection: Rejection, *,
                             message_id: str | None = None) -> Decision:
        """A request refused before it became a command (schema, size, credentials).

        Unauthenticated requests are not audited: anyone could fill the disk with them.
        """
        if principal is None:
            return _decision(rejection, message_id=message_id)
        record = AuditRecord(
            event=AuditEvent.COMMAND_REJECTED, principal=principal.name, role=principal.role.name,
            message_id=message_id, outcome=rejection.outcome.value,
            deny_reason=rejection.deny_reason,
        )
        return _decision(rejection, await self.audit.append(record), message_id=message_id)

    async def _decide(self, command: NormalizedCommand, principal: Principal) -> Decision:
        refused = self._precheck(command, principal)
        if refused is not None:
            return await self._refuse(command, principal, refused)
        if command.spec.effect is Effect.HALT or not command.client_message_id:
            return await self._govern(command, principal)  # never swallowed, never retried
        key = (principal.name, command.message_id)
        earlier = self._idem.claim(key, _fingerprint(command))
        if isinstance(earlier, Conflict):
            return await self._refuse(command, principal, outcomes.MESSAGE_ID_CONFLICT)
        if earlier is not None:  # a retry: the first outcome, nothing executed twice
            return await earlier
        try:
            decision = await self._govern(command, principal)
        except BaseException as exc:
            self._idem.abandon(key, exc)
            raise
        self._idem.resolve(key, decision)
        return decision

    def _precheck(self, command: NormalizedCommand, principal: Principal) -> Rejection | None:
        if _claims_more(command.claimed_role, principal.role):
            return outcomes.INSUFFICIENT_PRIVILEGES
        if not self._roles.allows(principal.role, command.action):
            return outcomes.INSUFFICIENT_PRIVILEGES
        if command.ruri is not None and self._robot is not None:
            try:
                if parse_ruri(command.ruri).robot != self._robot:
                    return outcomes.NOT_THIS_ROBOT
            except InvalidRuriError as exc:
                return outcomes.invalid_ruri(exc.rule)
        if not command.spec.stopping:  # a stop's AI problems are warnings (`_forgiven`)
            refused = self._ai.check(command, principal)
            if refused is not None:
                return refused
        if command.spec.effect is not Effect.HALT and not self._limiter.allow(principal):
            return outcomes.RATE_LIMITED  # a stop is never rate-limited
        return None

    async def _govern(self, command: NormalizedCommand, principal: Principal) -> Decision:
        try:
            applied = self._safety(command, command.params)
        except Violation as violation:
            return await self._refuse(command, principal, violation.rejection)
        gate = self._hitl.gate(command)
        if isinstance(gate, Rejection):
            return await self._refuse(command, principal, gate)
        if isinstance(gate, Escalate):
            return await self._hold(command, principal, gate.approver_role)
        # A command still being carried out (waiting for a subscriber, say) is not silence.
        with self._sessions.in_flight(principal):
            decision = await self._execute(command, principal, applied,
                                           AuditEvent.COMMAND_DISPATCHED)
        self._opened(principal, command, decision)
        self._sessions.heartbeat(principal)
        return decision

    def _opened(self, principal: Principal, command: NormalizedCommand,
                decision: Decision) -> None:
        """An executed stop ends its sender's control session (motion opens one as it is
        sent: `_sending`)."""
        if decision.outcome is Outcome.EXECUTED and command.spec.stopping:
            self._sessions.touch(principal, command.spec)

    def _sending(self, owner: Principal, command: NormalizedCommand) -> None:
        """Motion is about to reach the robot: its owner holds a control session from now on.
        A command refused before this point opens none, so its sender's silence can never
        halt someone else's motion."""
        timed = command.spec.streamed and getattr(command.params, "duration_s", None) is not None
        self._sessions.touch(owner, command.spec, timed=timed)

    # -- the e-stop lane (run by the e-stop machine, one transition at a time) ------------

    async def _estop(self, command: NormalizedCommand, principal: Principal) -> Decision:
        """Latched already; tell the robot, with latch file and audit entry made durable
        beside it. An e-stop always reaches the robot: if the latch file or the audit log
        cannot be written, it is still published, and the failure is logged and answered.
        """
        if self._latched_by is not None:
            return await self._estop_again(command, principal)
        at = now_ms(self._clock)
        record = _record(AuditEvent.ESTOP, command, principal, Outcome.EXECUTED, applied={},
                         ros2_topic=self._route(command), sent_first=True)
        self.streams.take_goals()  # the e-stop cancels every goal
        # The robot is told first (the dispatch's first step publishes, before any await);
        # latch file and audit entry are made durable beside it, both before the reply.
        sent, persisted, receipt = await asyncio.gather(
            self._dispatch(command, command.params),
            self.latch.file.write(True, principal.name, at),
            self.audit.append(record, urgent=True),
            return_exceptions=True)
        if isinstance(persisted, BaseException):
            log.error("e-stop latched in memory only: %s", persisted,
                      extra={"principal": principal.name})
        result, failure = _sent(sent)
        if isinstance(receipt, BaseException):
            log.error("e-stop sent but not audited: %s", receipt,
                      extra={"principal": principal.name})
            return _decision(outcomes.AUDIT_UNAVAILABLE, message_id=command.message_id)
        self._latched_by = receipt
        if failure is not None:
            return await self._failed(command, principal, failure)
        return _executed(command, {}, receipt, result)

    async def _estop_again(self, command: NormalizedCommand, principal: Principal) -> Decision:
        """An e-stop while an audited one holds the latch: the robot is told again, and the
        caller answered with the entry that latched it; the repeats are recorded together."""
        assert self._latched_by is not None
        result, failure = await self._dispatch(command, command.params)
        self._repeats.add(principal.name, now_ms(self._clock), failed=failure is not None,
                          warnings=command.warnings)
        if failure is not None:
            return _decision(failure, message_id=command.message_id)
        return Decision(outcome=Outcome.EXECUTED, http_status=200, applied={},
                        audit_id=self._latched_by.audit_id, message_id=command.message_id,
                        reason="already_latched", ros2_topic=result.ros2_topic)

    async def _record_repeats(self) -> None:
        """One ESTOP_REPEATED entry per principal for the repeats counted so far."""
        estop = with_effect(Effect.ESTOP).name
        for name, tally in self._repeats.take().items():
            params = msgspec.structs.asdict(tally)
            if not tally.warnings:
                del params["warnings"]
            await self._record_event(AuditRecord(
                event=AuditEvent.ESTOP_REPEATED, principal=name, action_type=estop,
                params=params, outcome=Outcome.EXECUTED.value))

    async def _clear_estop(self, command: NormalizedCommand, principal: Principal,
                           event: AuditEvent, pending_id: str | None) -> Decision:
        """Audited, persisted, unlatched (unless an e-stop came after it), published."""
        why = await self._ready(command)
        if why is not None:
            return await self._refuse(command, principal, outcomes.robot_unavailable(why),
                                      pending_id=pending_id)
        await self._record_repeats()  # the e-stops it clears come first in the log
        record = _record(AuditEvent.ESTOP_CLEARED, command, principal, Outcome.EXECUTED,
                         applied={}, pending_id=pending_id, ros2_topic=self._route(command))
        receipt = await self._write_ahead(record)
        if receipt is None:
            return _decision(outcomes.AUDIT_UNAVAILABLE, message_id=command.message_id)
        self._latched_by = None  # an e-stop after this clear is a new one, audited in full
        try:
            await self.latch.file.write(False, principal.name, now_ms(self._clock))
        except EstopStateError:
            log.exception("e-stop clear not persisted: staying latched",
                          extra={"principal": principal.name, "audit_id": receipt.audit_id})
            return await self._failed(command, principal, outcomes.ESTOP_STATE_UNWRITABLE)
        if not self.latch.unlatch():  # an e-stop is next in line: the robot stays stopped
            return _executed(command, {}, receipt, DispatchResult(ok=True))
        result, failure = await self._dispatch(command, command.params)
        if failure is not None:
            return await self._failed(command, principal, failure)
        return _executed(command, {}, receipt, result)

    # -- executing -------------------------------------------------------------------------

    async def _execute(self, command: NormalizedCommand, principal: Principal,
                       params: ActionParams, event: AuditEvent,
                       pending_id: str | None = None, issuer: Principal | None = None
                       ) -> Decision:
        """`issuer`: whose command it is, when `principal` approved it (HiTL)."""
        applied = msgspec.structs.asdict(params)
        spec = command.spec
        if spec.effect is Effect.CLEAR_ESTOP:
            return await self.latch.clear(
                lambda: self._clear_estop(command, principal, event, pending_id))
        if spec.effect in (Effect.LOCK, Effect.UNLOCK):
            return await self._lock(command, principal, params, event, pending_id)
        if spec.effect is Effect.HALT:  # zero at once, before the stop is even audited
            self.streams.end(EndReason.STOPPED, principal.name)
            return await self._halt(command, principal, params, event)
        motion = spec.motion
        if motion and self.latch.latched:
            return await self._refuse(command, principal, outcomes.ESTOP_ACTIVE, event=event,
                                      pending_id=pending_id)
        owner = issuer or principal  # a stream is its issuer's, at the issuer's priority
        priority = self._priorities.of(owner)
        # Streams and goals both drive the base: the same priorities and locks hold.
        refused = self.streams.admits(priority) if spec.streamed or spec.starts_goal else None
        if refused is not None:
            return await self._refuse(command, principal, refused, event=_refused(event),
                                      pending_id=pending_id)
        why = await self._ready(command)
        if why is not None:
            return await self._refuse(command, principal, outcomes.robot_unavailable(why),
                                      event=event, pending_id=pending_id)
        # An e-stop that latched while this command waited wins.
        if motion and self.latch.latched:
            return await self._refuse(command, principal, outcomes.ESTOP_ACTIVE, event=event,
                                      pending_id=pending_id)
        if spec.streamed:
            return await self._stream(command, principal, owner, params, applied, event,
                                      pending_id, priority)
        record = _record(event, command, principal, Outcome.EXECUTED, applied=applied,
                         pending_id=pending_id, ros2_topic=self._route(command))
        receipt = await self._write_ahead(record)
        if receipt is None:
            return _decision(outcomes.AUDIT_UNAVAILABLE, message_id=command.message_id)
        # Checked again after the write, with no await between this check and the publish.
        if motion and self.latch.latched:
            return await self._failed(command, principal, outcomes.ESTOP_ACTIVE)
        if motion:
            self._sending(owner, command)
        result, failure = await self._dispatch(command, params)
        if failure is not None:
            return await self._failed(command, principal, failure)
        if spec.starts_goal and self.latch.latched:
            # Accepted while an e-stop latched: the e-stop's cancel may have missed this goal.
            await self._dispatch(_bridge_command(Effect.HALT))
        elif spec.starts_goal:
            refused = self._hold_goal(result.goal_id, owner, priority, command.message_id)
            if refused is not None:
                return await self._failed(command, principal, refused)
        return _executed(command, applied, receipt, result)

    def _hold_goal(self, goal_id: str | None, owner: Principal, priority: int,
                   message_id: str) -> Rejection | None:
        """An accepted goal holds the base: the stream and the goals it replaces end. If a
        higher stream, goal or lock took the base while it was being sent, it is cancelled
        (the refusal returned)."""
        if goal_id is None:
            return None
        goal = HeldGoal(goal_id, owner.name, priority, message_id)
        refused = self.streams.admits(priority)
        if refused is not None:
            self._cancel_goals([goal], owner, why=refused.reason or "refused")
            return refused
        self.streams.end(EndReason.REPLACED, owner.name)  # a stream would fight the goal
        self._cancel_goals(self.streams.goal_started(goal), owner)
        return None

    def _cancel_goals(self, goals: list[HeldGoal], by: Principal, *,
                      why: str = "replaced") -> None:
        """Cancel goals the arbiter took off the base (never awaited by the command); their
        GOAL_FINISHED entries say by whom."""
        for goal in goals:
            reason = why if goal.owner == by.name or why != "replaced" else "preempted"
            self._ended_by[goal.goal_id] = f"{reason} by {by.name}"
            log.warning("cancelling goal %s of %s: %s by %s", goal.goal_id, goal.owner,
                        reason, by.name, extra={"principal": by.name})
            self._spawn(self._cancel_goal(goal.goal_id))

    async def _cancel_goal(self, goal_id: str) -> None:
        try:
            if not await self._dispatcher.cancel_goal(goal_id):
                log.warning("goal %s was not cancelled (already over?)", goal_id)
        except Exception:
            log.exception("cancelling goal %s failed", goal_id)

    async def _halt(self, command: NormalizedCommand, principal: Principal,
                    params: ActionParams, event: AuditEvent) -> Decision:
        """A stop: zero velocity and goal cancels go out first, its entry is made durable
        beside them (never before: stopping does not wait for the disk), then the reply."""
        applied: dict[str, Any] = {}  # nothing of the body reaches the robot (a reason is kept)
        record = _record(event, command, principal, Outcome.EXECUTED, applied=applied,
                         ros2_topic=self._route(command), sent_first=True)
        self.streams.take_goals()  # the halt cancels every goal
        sent, receipt = await asyncio.gather(self._dispatch(command, params),
                                             self._write_ahead(record, urgent=True))
        result, failure = sent
        if receipt is None:
            return _decision(outcomes.AUDIT_UNAVAILABLE, message_id=command.message_id)
        if failure is not None:
            return await self._failed(command, principal, failure)
        return _executed(command, applied, receipt, result)

    # -- velocity streams and locks ---------------------------------------------------------

    async def _stream(self, command: NormalizedCommand, principal: Principal,
                      owner: Principal, params: ActionParams, applied: dict[str, Any],
                      event: AuditEvent, pending_id: str | None, priority: int) -> Decision:
        """A move: its write-ahead entry (naming the stream it replaces), then the stream.

        The claim is made with no await before the entry is sealed, so claims and entries
        come in the same order; a move that does not start releases its claim."""
        replaces = self.streams.claim(owner.name, command.message_id, priority)
        if replaces is not None:  # recorded here: a replaced stream's end costs no entry
            applied = {**applied, "replaces": replaces.entry()}
        record = _record(event, command, principal, Outcome.EXECUTED, applied=applied,
                         pending_id=pending_id, ros2_topic=self._route(command))
        try:
            receipt = await self._write_ahead(record)
            if receipt is None:
                return _decision(outcomes.AUDIT_UNAVAILABLE, message_id=command.message_id)
            # Checked again after the write, with no await between this check and the publish.
            if self.latch.latched:
                return await self._failed(command, principal, outcomes.ESTOP_ACTIVE)
            return await self._start_stream(command, owner, params, priority,
                                            (applied, receipt), replaces)
        finally:
            self.streams.release(owner.name, command.message_id)

    async def _start_stream(self, command: NormalizedCommand, principal: Principal,
                            params: ActionParams, priority: int,
                            audited: tuple[dict[str, Any], AuditReceipt],
                            replaces: Replaces | None) -> Decision:
        """After the write-ahead entry: the first sample, then the stream takes over.

        No await between the admission check, the first sample (the dispatcher publishes
        motion before its first await) and `start`: the stream state cannot change in between.
        """
        assert isinstance(params, MoveParams), "only a move is streamed"
        self.streams.release(principal.name, command.message_id)  # refused or started: done
        refused = self.streams.admits(priority)
        if refused is not None:
            return await self._failed(command, principal, refused)
        target = Velocity.of(params)
        first = self.streams.first_sample(target)
        self._sending(principal, command)
        result, failure = await self._dispatch(command, first.params())
        if failure is not None:
            return await self._failed(command, principal, failure)
        stream = Stream(action=command.action, owner=principal.name, priority=priority,
                        target=target, message_id=command.message_id,
                        duration_s=params.duration_s)
        refused = self.streams.start(stream, first, by=principal.name, recorded=replaces)
        if refused is not None:
            return await self._failed(command, principal, refused)
        self._cancel_goals(self.streams.take_goals(below=priority + 1), principal)
        return _executed(command, audited[0], audited[1], result)

    def _stream_ended(self, ended: StreamEnded) -> None:
        if ended.recorded:  # the replacing move's entry says so (`applied.replaces`)
            return
        stream = ended.stream
        record = AuditRecord(
            event=AuditEvent.STREAM_ENDED, principal=stream.owner, action_type=stream.action,
            message_id=stream.message_id,
            params={"reason": ended.reason.value, "ended_by": ended.by,
                    "samples": stream.samples,
                    "seconds": round(ended.at - stream.started_at, 3)},
            applied={"last": ended.last._asdict(), "zero_sent": ended.zeroed})
        self._spawn(self._write_ahead(record))

    def end_streams(self) -> None:
        """The bridge is stopping: zero now, before the robot is halted and the log closed."""
        self.streams.end(EndReason.BRIDGE_STOPPED)

    async def _lock(self, command: NormalizedCommand, principal: Principal,
                    params: ActionParams, event: AuditEvent,
                    pending_id: str | None) -> Decision:
        """Engage or release a configured lock: only at or below the sender's priority."""
        assert isinstance(params, LockParams), "a lock names its lock"
        level = self._priorities.lock(params.name)
        refused = (outcomes.UNKNOWN_LOCK if level is None else outcomes.LOWER_PRIORITY
                   if self._priorities.of(principal) < level else None)
        if refused is not None or level is None:
            return await self._refuse(command, principal, refused or outcomes.UNKNOWN_LOCK,
                                      event=_refused(event), pending_id=pending_id)
        applied = {"name": params.name, "priority": level}
        record = _record(event, command, principal, Outcome.EXECUTED, applied=applied,
                         pending_id=pending_id)
        receipt = await self._write_ahead(record)
        if receipt is None:
            return _decision(outcomes.AUDIT_UNAVAILABLE, message_id=command.message_id)
        if command.spec.effect is Effect.LOCK:
            lower = self.streams.lock(params.name, level, principal.name)
            self._lock_holders[params.name] = principal.name
            self._cancel_goals(lower, principal, why=f"locked out by {params.name!r}")
        else:
            self.streams.unlock(params.name)
            self._lock_holders.pop(params.name, None)
        return _executed(command, applied, receipt, DispatchResult(ok=True))

    async def _write_ahead(self, record: AuditRecord, *, urgent: bool = False
                           ) -> AuditReceipt | None:
        """The decision entry, durable; None if it cannot be written (then nothing is sent).
        `urgent`: a stop's, whose group commit waits for no more entries."""
        try:
            return await self.audit.append(record, urgent=urgent)
        except AuditError:
            log.exception("audit write failed: %s not sent", record.action_type,
                          extra={"principal": record.principal})
            return None

    def _route(self, command: NormalizedCommand) -> str | None:
        try:
            return self._dispatcher.route(command)
        except Exception:  # only the audit entry's ros2_topic is missing then
            log.exception("no route for %s", command.action)
            return None

    async def _ready(self, command: NormalizedCommand) -> str | None:
        try:
            return await self._dispatcher.ready(command)
        except Exception as exc:  # a broken readiness check counts as "not ready"
            log.exception("readiness check for %s failed", command.action)
            return f"readiness check failed: {exc!r}"

    async def _dispatch(self, command: NormalizedCommand, applied: ActionParams | None = None
                        ) -> tuple[DispatchResult, Rejection | None]:
        try:
            result = await self._dispatcher.dispatch(
                command, command.params if applied is None else applied)
        except Exception as exc:  # a bridge fault is an outcome (failed), never a crash
            log.exception("dispatch of %s failed", command.action)
            return DispatchResult(ok=False, detail=repr(exc)), outcomes.DISPATCH_ERROR
        if result.ok:
            return result, None
        return result, outcomes.robot_unavailable(result.detail)

    async def _failed(self, command: NormalizedCommand, principal: Principal,
                      rejection: Rejection) -> Decision:
        """After a write-ahead entry: the send did not happen or failed (COMMAND_FAILED)."""
        return await self._refuse(command, principal, rejection, event=AuditEvent.COMMAND_FAILED)

    async def _refuse(self, command: NormalizedCommand, principal: Principal,
                      rejection: Rejection, *, event: AuditEvent = AuditEvent.COMMAND_REJECTED,
                      pending_id: str | None = None) -> Decision:
        record = _record(event, command, principal, rejection.outcome, rejection=rejection,
                         pending_id=pending_id)
        receipt = await self._write_ahead(record)
        if receipt is None:
            return _decision(outcomes.AUDIT_UNAVAILABLE, message_id=command.message_id)
        return _decision(rejection, receipt, message_id=command.message_id)

    # -- HiTL -------------------------------------------------------------------------------

    async def _hold(self, command: NormalizedCommand, principal: Principal,
                    approver_role: Role) -> Decision:
        pending = PendingCommand(
            pending_id=uuid.uuid4().hex, command=command, issuer=principal,
            approver_role=approver_role,
            expires_at_ms=now_ms(self._clock) + self._hitl_ttl_ms,
            approvals_required=self._hitl.approvals(command.action),
        )
        record = _record(AuditEvent.PENDING_AUTH, command, principal, Outcome.PENDING_AUTH,
                         pending_id=pending.pending_id)
        receipt = await self.audit.append(record)
        self._pending.put(pending)  # only once its PENDING_AUTH entry is durable
        self._status_changed()
        if self._notifier is not None:
            self._spawn(self._notifier.notify(pending.message()))  # never awaited here
        return Decision(outcome=Outcome.PENDING_AUTH, http_status=202,
                        audit_id=receipt.audit_id, message_id=command.message_id,
                        pending_id=pending.pending_id, expires_at_ms=pending.expires_at_ms)

    async def authorize(self, pending_id: str, approver: Principal,
                        reason: str | None = None) -> Decision:
        """One approval; the command runs once it has as many distinct ones as it needs."""
        return await self._detached(self._resolve(pending_id, approver, "approve", reason))

    async def deny(self, pending_id: str, approver: Principal,
                   reason: str | None = None) -> Decision:
        """Any approver's denial ends it, whatever approvals it had."""
        return await self._detached(self._resolve(pending_id, approver, "deny", reason))

    async def withdraw(self, pending_id: str, principal: Principal,
                       reason: str | None = None) -> Decision:
        """Its issuer takes a pending command back (an approver may too): never executed."""
        return await self._detached(self._resolve(pending_id, principal, "withdraw", reason))

    def pending(self) -> list[PendingAuth]:
        return [held.message() for held in self._pending.list()]

    async def _resolve(self, pending_id: str, reviewer: Principal, verdict: Verdict,
                       reason: str | None) -> Decision:
        held = self._pending.get(pending_id)
        if held is None:
            return await self._refuse_hitl(verdict, reviewer, outcomes.PENDING_NOT_FOUND,
                                           pending_id)
        async with held.lock:  # one review at a time: each counted once, released once
            reviewed = await self._review(held, reviewer, verdict, reason)
        if isinstance(reviewed, Decision):
            return reviewed
        command, pending = reviewed, held.pending  # out of the store, with every review
        self._status_changed()
        if verdict != "approve":
            denied = verdict == "deny"
            return await self._refuse(
                command, reviewer, outcomes.HITL_DENIED if denied else outcomes.HITL_WITHDRAWN,
                event=AuditEvent.HITL_DENIED if denied else AuditEvent.HITL_WITHDRAWN,
                pending_id=pending_id)
        try:  # the state *now* decides, not the state when the command arrived
            applied = self._safety(command, command.params)
        except Violation as violation:
            return await self._refuse(command, reviewer, violation.rejection,
                                      event=AuditEvent.HITL_AUTHORIZED, pending_id=pending_id)
        decision = await self._execute(command, reviewer, applied, AuditEvent.HITL_AUTHORIZED,
                                       pending_id, issuer=pending.issuer)
        self._opened(pending.issuer, command, decision)
        return decision

    async def _review(self, held: Held, reviewer: Principal, verdict: Verdict,
                      reason: str | None) -> Decision | NormalizedCommand:
        """Under `held.lock`: refused, or counted (an approval of several: still pending), or
        taken from the store and returned with every review so far, to run or discard."""
        pending = held.pending
        if self._pending.get(pending.pending_id) is not held:  # resolved while this waited
            return await self._refuse_hitl(verdict, reviewer, outcomes.PENDING_NOT_FOUND,
                                           pending.pending_id)
        if pending.expires_at_ms <= now_ms(self._clock):
            await self.expire_pending()
            return await self._refuse_hitl(verdict, reviewer, outcomes.PENDING_EXPIRED,
                                           pending.pending_id)
        refused = self._may_review(held, reviewer, verdict)
        if refused is not None:
            return await self._refuse_hitl(verdict, reviewer, refused, pending.pending_id)
        review = Approval(principal=reviewer.name, role=cast(RoleName, reviewer.role.name),
                          decision=verdict, at_ms=now_ms(self._clock), reason=reason)
        if verdict == "approve" and held.missing > 1:
            return await self._count_approval(held, reviewer, review)
        self._pending.take(pending.pending_id)
        return held.reviewed(review)

    def _may_review(self, held: Held, reviewer: Principal, verdict: Verdict
                    ) -> Rejection | None:
        pending = held.pending
        issuer = reviewer.name == pending.issuer.name
        if reviewer.role < pending.approver_role and not (verdict == "withdraw" and issuer):
            return outcomes.INSUFFICIENT_PRIVILEGES
        if verdict != "approve":
            return None
        if issuer and (self._distinct or pending.approvals_required > 1):
            return outcomes.SELF_APPROVAL  # n-of-m: the issuer is never one of the n
        if held.approved_by(reviewer.name):
            return outcomes.ALREADY_APPROVED
        return None

    async def _count_approval(self, held: Held, approver: Principal,
                              review: Approval) -> Decision:
        """An approval while more are needed: on record (HITL_APPROVAL) before it counts."""
        pending = held.pending
        record = _record(AuditEvent.HITL_APPROVAL, held.reviewed(review), approver,
                         Outcome.PENDING_AUTH, pending_id=pending.pending_id)
        receipt = await self._write_ahead(record)
        if receipt is None:  # an approval that is not on record does not count
            return _decision(outcomes.AUDIT_UNAVAILABLE, message_id=pending.command.message_id)
        held.approvals.append(review)
        self._status_changed()
        return Decision(outcome=Outcome.PENDING_AUTH, http_status=202,
                        audit_id=receipt.audit_id, message_id=pending.command.message_id,
                        pending_id=pending.pending_id, expires_at_ms=pending.expires_at_ms)

    async def _refuse_hitl(self, verdict: Verdict, reviewer: Principal, rejection: Rejection,
                           pending_id: str) -> Decision:
        verb = "hitl_authorize" if verdict == "approve" else f"hitl_{verdict}"
        record = AuditRecord(event=AuditEvent.COMMAND_REJECTED, principal=reviewer.name,
                             role=reviewer.role.name, action_type=verb, pending_id=pending_id,
                             outcome=rejection.outcome.value, deny_reason=rejection.deny_reason)
        return _decision(rejection, await self.audit.append(record))

    async def expire_pending(self) -> list[Decision]:
        """Discard and audit (HITL_EXPIRED, with any approvals it had) every pending command
        past its TTL."""
        decisions = []
        expired = self._pending.take_expired(now_ms(self._clock))
        if expired:
            self._status_changed()
        for held in expired:
            p = held.pending
            decisions.append(await self._refuse(held.reviewed(), p.issuer,
                                                outcomes.PENDING_EXPIRED,
                                                event=AuditEvent.HITL_EXPIRED,
                                                pending_id=p.pending_id))
        return decisions

    def _status_changed(self) -> None:
        tell_all(self.status_listeners, log, "STATUS")

    # -- goals the robot carries out -------------------------------------------------------

    def goal_finished(self, goal_id: str, outcome: str, *, server: str,
                      message_id: str | None, detail: str | None = None) -> None:
        """A goal the bridge sent ended (succeeded, aborted, canceled, …): audited.

        `message_id` links it to the COMMAND_DISPATCHED entry that sent it."""
        self.streams.goal_ended(goal_id)  # the base is free of it
        detail = self._ended_by.pop(goal_id, None) or detail
        if self._stopped:  # BRIDGE_STOPPED is the last entry
            log.info("goal %s %s after the bridge stopped: not audited", goal_id, outcome)
            return
        record = AuditRecord(event=AuditEvent.GOAL_FINISHED, message_id=message_id,
                             params={"goal_id": goal_id}, outcome=outcome,
                             deny_reason=detail, ros2_topic=server)
        self._spawn(self._record_event(record))

    async def _record_event(self, record: AuditRecord) -> None:
        try:
            await self.audit.append(record)
        except AuditError:
            log.exception("audit write failed: %s not recorded", record.event.value)

    # -- sessions (§10.8) -------------------------------------------------------------------

    def heartbeat(self, principal: Principal) -> None:
        self._sessions.heartbeat(principal)

    async def safe_stop(self, principal: Principal, why: str = "session ended") -> Decision:
        """Session lost: zero velocity and cancel goals (a `stop`), audited as such.

        What the principal drives stops; if someone else holds the base (a higher stream or
        goal, still attended), only the principal's own goals are cancelled: its silence must
        not halt another principal's motion."""
        self.streams.end_of(principal.name, EndReason.SESSION_LOST)  # zero first, at once
        own = self.streams.take_goals(owner=principal.name)
        if self.streams.driven_by_other_than(principal.name):
            return await self._own_stop(principal, why, own)
        log.warning("control session of '%s' lost (%s): halting the robot (safe stop)",
                    principal.name, why)
        self.streams.take_goals()  # the halt cancels every goal
        for listener in self.session_lost_listeners:  # e.g. log the goals being cancelled
            listener(principal)
        stop = _bridge_command(Effect.HALT)
        record = _record(AuditEvent.NETWORK_LOSS_SAFE_STOP, stop, principal, Outcome.EXECUTED,
                         applied={}, ros2_topic=self._route(stop), sent_first=True)
        # Halted first, and even if the audit cannot be written: stopping is never held back.
        (result, failure), receipt = await asyncio.gather(
            self._dispatch(stop), self._write_ahead(record, urgent=True))
        for listener in self.safe_stop_listeners:  # e.g. STATUS shows `safe_stop`
            listener(principal)
        if receipt is None:
            return _decision(outcomes.AUDIT_UNAVAILABLE, message_id=stop.message_id)
        if failure is not None:
            return await self._failed(stop, principal, failure)
        return _executed(stop, {}, receipt, result)

    async def _own_stop(self, principal: Principal, why: str,
                        goals: list[HeldGoal]) -> Decision:
        log.warning("control session of '%s' lost (%s): its goals cancelled; the base stays "
                    "with who holds it", principal.name, why)
        self._cancel_goals(goals, principal, why="session lost")
        stop = _bridge_command(Effect.HALT)
        applied = {"scope": "own", "goals_cancelled": [g.goal_id for g in goals]}
        record = _record(AuditEvent.NETWORK_LOSS_SAFE_STOP, stop, principal, Outcome.EXECUTED,
                         applied=applied, sent_first=True)
        receipt = await self._write_ahead(record, urgent=True)
        if receipt is None:
            return _decision(outcomes.AUDIT_UNAVAILABLE, message_id=stop.message_id)
        return _executed(stop, applied, receipt, DispatchResult(ok=True))

    async def end_session(self, principal: Principal) -> Decision | None:
        """The principal's connection closed: if it held a control session, safe stop now.

        Returns the safe stop's decision, or None when there was no session to end.
        """
        if not self._sessions.end(principal):
            return None
        # Detached: the closing connection's handler may be cancelled; the stop must not be.
        return await self._detached(self.safe_stop(principal, "its connection closed"))

    async def sweep(self) -> None:
        """One round of housekeeping: expire HiTL requests, stop for lost sessions, record
        e-stop repeats that waited long enough."""
        await self.expire_pending()
        if self._repeats.due(now_ms(self._clock)):  # in order with the latch's transitions
            await self.latch.then(self._record_repeats)
        lost = self._sessions.take_lost()
        # Concurrently: one slow halt (say, a goal server that never answers) must not
        # delay the next principal's, nor the next sweep.
        await asyncio.gather(*(
            self._spawn(self.safe_stop(p, f"no command or heartbeat for {allowed:g} s"))
            for p, allowed in lost))

    async def _sweep_forever(self) -> None:
        while True:
            await asyncio.sleep(SWEEP_INTERVAL_S)
            try:
                await self.sweep()
            except Exception:
                log.exception("governance sweep failed")

    def _detached(self, decision: Coroutine[Any, Any, Decision]) -> asyncio.Future[Decision]:
        """`decision` in a task of its own, and a future of its outcome to await: a caller that
        is cancelled cancels only that future, never the decision (like `shield(task)`, but the
        task resolves the future itself: no shield callbacks, two loop turns fewer a command)."""
        outcome: asyncio.Future[Decision] = asyncio.get_running_loop().create_future()
        task = asyncio.ensure_future(_resolve_into(decision, outcome))
        self._tasks.add(task)
        task.add_done_callback(functools.partial(_settled, self._tasks, decision, outcome))
        return outcome

    def _spawn(self, coro: Coroutine[Any, Any, Any]) -> asyncio.Task[Any]:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task


async def _resolve_into(decision: Coroutine[Any, Any, Decision],
                        outcome: asyncio.Future[Decision]) -> None:
    """Runs `decision` to its end and hands its result or error to `outcome`, unless the caller
    has given up on it (then an error is logged: nobody else would see it)."""
    try:
        result = await decision
    except asyncio.CancelledError:  # the task itself was cancelled: `_settled` tells the caller
        raise
    except BaseException as exc:
        if outcome.done():
            log.error("a decision failed after its caller left", exc_info=exc)
        else:
            outcome.set_exception(exc)
        if not isinstance(exc, Exception):  # KeyboardInterrupt, SystemExit: not ours to keep
            raise
    else:
        if not outcome.done():
            outcome.set_result(result)


def _settled(running: set[asyncio.Task[Any]], decision: Coroutine[Any, Any, Decision],
             outcome: asyncio.Future[Decision], task: asyncio.Task[None]) -> None:
    running.discard(task)
    if not outcome.done():  # cancelled (maybe before it ever ran): the caller must not hang
        outcome.cancel()
        decision.close()  # a no-op once it ran; else no "never awaited" warning


def _claims_more(claimed: Any, role: Role) -> bool:
    """A body's role claim is refused unless it names a role no higher than the real one."""
    if claimed is None:
        return False
    if isinstance(claimed, str) and claimed in Role.__members__:
        return Role[claimed] > role
    if isinstance(claimed, int) and not isinstance(claimed, bool) and claimed in (1, 2, 3, 4, 5):
        return Role(claimed) > role
    return True  # unintelligible claims are treated as claiming more


def _record(event: AuditEvent, command: NormalizedCommand, principal: Principal,
            outcome: Outcome, *, applied: dict[str, Any] | None = None,
            rejection: Rejection | None = None, ros2_topic: str | None = None,
            pending_id: str | None = None, sent_first: bool | None = None) -> AuditRecord:
    ai = msgspec.structs.asdict(command.ai) if command.ai is not None else None
    return AuditRecord(
        event=event, principal=principal.name, role=principal.role.name,
        message_id=command.message_id, action_type=command.action, params=command.requested,
        applied=applied, outcome=outcome.value,
        deny_reason=rejection.deny_reason if rejection else None, ai=ai,
        ros2_topic=ros2_topic, pending_id=pending_id,
        warnings=list(command.warnings) or None, sent_first=sent_first,
        # A held command's reviews (who approved, denied or withdrew it, and why).
        approvals=[msgspec.to_builtins(a) for a in command.approvals] or None,
        rcan=command.envelope.audit_facts() if command.envelope is not None else None,
    )


def _sent(outcome: tuple[DispatchResult, Rejection | None] | BaseException
          ) -> tuple[DispatchResult, Rejection | None]:
    """A dispatch's result out of `gather(..., return_exceptions=True)`."""
    if isinstance(outcome, BaseException):  # `_dispatch` catches Exception: this is worse
        raise outcome
    return outcome


async def _awaited(future: asyncio.Future[Any]) -> Any:
    return await future


def _refused(event: AuditEvent) -> AuditEvent:
    """The event of a refusal: an approval's own (HITL_AUTHORIZED), else COMMAND_REJECTED."""
    return AuditEvent.COMMAND_REJECTED if event is AuditEvent.COMMAND_DISPATCHED else event


def _bridge_command(effect: Effect) -> NormalizedCommand:
    """A command the bridge issues itself (a safe stop, an e-stop re-published at start)."""
    spec = with_effect(effect)
    return NormalizedCommand(action=spec.name, params=spec.params(), requested={},
                             message_id=str(uuid.uuid4()))


def _fingerprint(command: NormalizedCommand) -> bytes:
    """What makes a retry the same command: action, parameters and target robot."""
    return msgspec.json.encode({"action": command.action, "params": command.requested,
                                "ruri": command.ruri}, order="sorted")


def _executed(command: NormalizedCommand, applied: dict[str, Any], receipt: AuditReceipt,
              result: DispatchResult) -> Decision:
    return Decision(outcome=Outcome.EXECUTED, http_status=200, applied=applied,
                    audit_id=receipt.audit_id, message_id=command.message_id,
                    ros2_topic=result.ros2_topic, goal_id=result.goal_id)


def _decision(rejection: Rejection, receipt: AuditReceipt | None = None, *,
              message_id: str | None = None) -> Decision:
    return Decision(outcome=rejection.outcome, http_status=rejection.http_status,
                    error_code=rejection.error_code, reason=rejection.reason,
                    audit_id=receipt.audit_id if receipt else None, message_id=message_id)
