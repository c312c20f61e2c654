"""The one entry point: authenticated command in, decision out, audited before it acts.

The governor is the pipeline. Order (§3.1): RBAC → rate limit → idempotency → §8 invariants →
§9 HiTL → robot ready → §6 audit (durable) → dispatch. Write-ahead: a command's decision entry
is on disk before anything reaches the robot; a send that then fails adds a COMMAND_FAILED
entry. If the entry cannot be written, nothing is sent. Stops are the exception: they go out
first and are made durable beside the send, before the reply (docs/governance.md).

What it calls, each a module of its own: the e-stop lane (`estop_lane`, run one transition at a
time by the latch, `estop`), the base arbiter (`arbiter`: streams, goals, locks, priorities),
the HiTL desk (`review`), control sessions (`sessions`); `steps` is how each of them audits,
sends and refuses. Who is told of what is one `Events` object (`rcan_rtps.events`).

The e-stop lane: `estop` and `stop` are never rate-limited and never answered from another
command's idempotency entry.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import uuid
from collections.abc import Awaitable, Callable, Coroutine, Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import msgspec

from rcan_rtps.config import RcanConfig, estop_state_file
from rcan_rtps.rcan import (
    ActionParams,
    Effect,
    InvalidRuriError,
    NormalizedCommand,
    Outcome,
    PendingAuth,
    Role,
    parse_ruri,
)
from rcan_rtps.rcan.actions import Publish

from ..events import Events
from . import outcomes
from .ai import AiPolicy
from .arbiter import BaseArbiter
from .audit import AuditEvent, AuditLog, AuditRecord, Checkpoint
from .clock import Clock, SystemClock, latest_wall, now_ms
from .estop import EstopMachine, LatchFile
from .estop_lane import EstopLane
from .hitl import Escalate, HitlPolicy, Notifier, PendingCommand, Verdict
from .idempotency import Conflict, DecidedBefore, Idempotency
from .invariants import Check, Violation, safety_policy
from .left import LeftRunning
from .log_tail import logged_ids
from .outcomes import Rejection
from .priorities import MotionPriorities
from .rbac import Principal, RateLimiter, RolePolicy
from .review import CREDENTIAL_EXPIRED, NO_MESSAGE, Ended, HitlDesk, PendingRecord, ReviewMessage
from .sessions import Sessions
from .steps import (
    ArmsHeld,
    Decision,
    Dispatcher,
    DispatchResult,
    LeftHalted,
    Steps,
    ai_facts,
    bridge_command,
    decision,
    executed,
    record,
    refused_event,
    sent,
)
from .streams import AccelLimits, EndReason, HeldGoal, StopMark, VelocityStreams

if TYPE_CHECKING:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

    from .thoughts import ThoughtLog

__all__ = ["MAX_IN_FLIGHT", "ArmsHeld", "Decision", "DispatchResult", "Dispatcher", "Governor"]

log = logging.getLogger(__name__)
RUNS_ON_KEPT = 8  # per topic: as many as the dispatcher may hold (bridge.arm_holds.MAX_SETS)
SWEEP_INTERVAL_S = 0.05  # session-loss halt latency is timeout + at most this
# Commands decided at once; the rest wait their turn without using the event loop, so a flood
# of requests cannot queue the e-stop lane (which never waits here) behind itself. The limit
# also caps how many audit entries share one fsync: 16 measured ~4 entries per fsync against
# ~2 at 8, and ~20 % less CPU per command, for an e-stop p99 under 500 clients of ~28 ms
# (18 ms at 8, 60 ms at 32; target 50 ms).
MAX_IN_FLIGHT = 16
# The reasons of the withdrawals of held motion that the governor makes for its issuer.
CANCELLED_BY_CLIENT = "withdrawn: its client cancelled a motion command of its issuer's"
STOPPED_WHILE_HELD = ("withdrawn: its issuer's motion was stopped while it was being held "
                      "(a motion command cancelled by its client, its connection closed, "
                      "or a stop)")
# `{}`: the stop — "a stop by 'ops'", "an e-stop", "a halt for the lost control session of …".
ROBOT_STOPPED = "withdrawn: the robot was stopped while it was held ({})"
CONNECTION_CLOSED = "withdrawn: a connection of its issuer's closed while it was held"
# `{}`: why the session was lost ("no command or heartbeat for 2 s", "its connection closed").
SESSION_LOST = "withdrawn: its issuer's control session was lost while it was held ({})"
BRIDGE_STOPPING = "withdrawn: the bridge stopped while it was held"
ESTOPPED_WHILE_HELD = "withdrawn: an e-stop came while it was held"


# Which held commands a withdrawal takes (`Governor._withdraw_held`).
def _is_motion(command: NormalizedCommand) -> bool:
    return command.spec.motion


def _is_clear(command: NormalizedCommand) -> bool:
    return command.spec.effect is Effect.CLEAR_ESTOP


def _any(command: NormalizedCommand) -> bool:
    return True


class ClientCancel(NamedTuple):
    """What `Governor.motion_cancelled` did: the principal's motion held for a human that it
    withdrew (pending ids: never to run), and the stop of its motion to await."""

    withdrawn: tuple[str, ...]
    stopping: Awaitable[Decision | None]


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
                 events: Events | None = None,
                 ai: AiPolicy | None = None,
                 left_running: LeftRunning | None = None, left_by_crash: bool = True) -> None:
        self.audit = audit
        # What the previous run left running, having not ended with BRIDGE_STOPPED (a crash)
        # — or, `left_by_crash` False, the goals its BRIDGE_STOPPED named (their send gave
        # up; the server had not accepted them yet): taken back by `start` (`_halting`,
        # recorded by `_took_back`).
        self.left_running = left_running or LeftRunning()
        self._left_by_crash = left_by_crash
        self.latch = latch
        self.events = events or Events()
        self._steps = Steps(audit, dispatcher)
        # Whose command sent what runs on, per topic (`DispatchResult.runs_for_s`: an arm's
        # trajectory; the next on a topic may not replace it: its controller may refuse that
        # one): a stop of its sender's motion alone holds it, and while it runs, its sender
        # drives. Per topic: message id → owner, those still running, at most RUNS_ON_KEPT.
        self._runs_on: dict[str, dict[str, str]] = {}
        self._tasks = self._steps.tasks
        self._dispatcher = dispatcher
        self._roles = roles
        self._limiter = limiter
        self._safety = safety
        self._hitl = hitl
        self._ai = ai or AiPolicy()
        self._clock = clock
        self._idem: Idempotency[tuple[str, str], Decision] = Idempotency(clock)
        self._latch_file_missing = latch.file.missing()
        self._sessions = Sessions(clock, session_timeout_s, unattended_move_s)
        self._robot = parse_ruri(robot_ruri).robot if robot_ruri else None
        self._thoughts: ThoughtLog | None = None  # §16.5: made by the first AI command
        self._admission = asyncio.Semaphore(MAX_IN_FLIGHT)
        self._sweeper: asyncio.Task[None] | None = None
        self.started = False  # BRIDGE_STARTED is durable
        self._stopping = False  # `stop` began
        self._stopped = False
        # The one owner of the velocity streams; an e-stop ends them first thing.
        self.streams = streams or VelocityStreams(dispatcher, latch)
        self._base = BaseArbiter(self._steps, self.streams, priorities or MotionPriorities(),
                                 latch, self._sending, held_locks,
                                 stream_ended=self.events.stream_ended.emit)
        self._estops = EstopLane(self._steps, latch, self.streams, clock)
        self._desk = HitlDesk(self._steps, hitl, clock, timeout_s=hitl_timeout_s,
                              require_distinct_approver=require_distinct_approver,
                              notifier=notifier, changed=self.events.governance.emit,
                              run_approved=self._run_approved)
        latch.bind(self._latch_flipped)

    @classmethod
    def from_config(cls, config: RcanConfig, *, audit: AuditLog, dispatcher: Dispatcher,
                    clock: Clock | None = None, notifier: Notifier | None = None,
                    events: Events | None = None) -> Governor:
        bridge, clock = config.bridge, clock or SystemClock()
        latch_file = LatchFile(Path(estop_state_file(bridge)))
        # A missing latch file is a first start only if the audit log is new as well.
        latched, reason = latch_file.load(first_start=audit.head.last_seq == 0)
        # The replay runs once, here: a bridge lets go of its module once started
        # (`rcan_rtps._modules.START_ONLY`; idle memory, issue 27).
        from .resume import resume

        resumed = resume(audit.path, now_ms=now_ms(clock), boot=clock.boot(),
                         pubkey=audit.public_key)
        audit.on_checkpoint(functools.partial(_write_start_point, audit.path,
                                              audit.public_key, audit.sign_resume_point))
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
            roles=RolePolicy.from_config(bridge.rbac),
            limiter=RateLimiter(clock),
            safety=safety_policy(safety, latch, bridge.ros2.nav_frame_id, streams,
                                 arms=bridge.ros2.arms),
            streams=streams, priorities=MotionPriorities(bridge.motion),
            hitl=HitlPolicy.from_config(bridge.hitl, bridge.rbac),
            hitl_timeout_s=bridge.hitl.timeout_seconds,
            require_distinct_approver=bridge.hitl.require_distinct_approver,
            session_timeout_s=bridge.safety.session_timeout_s,
            unattended_move_s=bridge.safety.unattended_move_s,
            robot_ruri=config.robot.ruri, held_locks=resumed.locks, events=events,
            ai=AiPolicy(bridge.ai.agents), left_running=resumed.left,
            left_by_crash=resumed.crashed,
        )

    # -- lifecycle --------------------------------------------------------------------------

    async def start(self) -> None:
        """BRIDGE_STARTED (durable), then a latched start tells the robot again. After a crash
        (the previous run did not end with BRIDGE_STOPPED), the motion it left is taken back
        first, and recorded before this returns (`_took_back`)."""
        # A stop goes out before its entry is durable (stops never wait for the disk): the
        # halt of what the crashed run left starts now, before BRIDGE_STARTED is written, and
        # its entry follows BRIDGE_STARTED once the halt is done — BRIDGE_STARTED stays a
        # run's first entry (the boundary `resume` reads back to), and the entry can say what
        # was taken back and what could not be.
        halting = self._steps.spawn(self._halting(self.left_running)) \
            if self.left_running else None
        params: dict[str, Any] = {"estop_latched": self.latch.latched}
        if self.left_running:  # a crash during the halt: the next start takes it up from here
            params["left_running"] = self.left_running.facts()
        if self.latch.reason:
            params["estop_reason"] = self.latch.reason
        self._idem.remember_decided(self._decided_before())
        released = self._base.retake_locks()
        params["locks"] = dict(self._base.lock_holders)
        if released:
            params["locks_released"] = released
        await self.audit.append(AuditRecord(event=AuditEvent.BRIDGE_STARTED, params=params))
        self.started = True
        if self._latch_file_missing and not self.latch.latched:  # first start: record it
            await self.latch.file.write(False, "first start", now_ms(self._clock))
        if self.latch.latched:  # latched now; the robot is told without delaying the start
            self._steps.spawn(_awaited(self.latch.engage(self._estops.republish)))
        if halting is not None:
            await self._took_back(self.left_running, await halting)
        self._sweeper = asyncio.create_task(self._sweep_forever())

    def _decided_before(self) -> Iterator[tuple[tuple[str, str], float]]:
        """((principal, message_id), age in s) of what the log shows decided within the
        idempotency ttl: before this start, by an earlier run."""
        now = self._clock.time()
        for msg_id, principal, logged_s in logged_ids(self.audit.path,
                                                     since_s=now - self._idem.ttl_s):
            yield (principal, msg_id), now - logged_s

    async def _halting(self, left: LeftRunning) -> LeftHalted:
        why = ("did not stop cleanly (no BRIDGE_STOPPED)" if self._left_by_crash else
               "stopped with goals its server might still accept")
        log.warning("the previous run %s: taking back the motion it left (%d arm "
                    "trajectories, %d goals, %d velocity streams)", why,
                    len(left.arms), len(left.goals), len(left.streams))
        try:
            return await self._dispatcher.halt_left(left)
        except Exception as exc:  # recorded as not taken back; never raised into the start
            log.exception("taking back the motion a crashed run left failed")
            return LeftHalted(zero_reached=False, goals_not_cancelled=(repr(exc),),
                              arms=ArmsHeld(not_held=(repr(exc),)),
                              still_left=tuple([*(a.message_id for a in left.arms),
                                                *(g.message_id for g in left.goals)]))

    async def _took_back(self, left: LeftRunning, halted: LeftHalted) -> None:
        """The one entry of the halt of a crashed run's motion: a NETWORK_LOSS_SAFE_STOP of
        scope `crash` (every session of that run was lost) — or `stopped`, of the goals a
        clean stop left — what it found and what it did. Failed when an arm that may still
        move could not be held (loudly: nobody else will)."""
        applied: dict[str, Any] = {
            "scope": "crash" if self._left_by_crash else "stopped", "left": left.facts(),
            "zero_reached": halted.zero_reached,
            "goals_cancelled": list(halted.goals_cancelled), **_arms_applied(halted.arms)}
        if halted.goals_not_cancelled:
            applied["goals_not_cancelled"] = list(halted.goals_not_cancelled)
        if halted.still_left:  # the next start after another crash tries these again
            applied["still_left"] = list(halted.still_left)
        for why in halted.arms.not_held:
            log.error("an arm the crashed run left moving may still move: %s", why)
        for why in halted.goals_not_cancelled:
            log.warning("a goal the crashed run left: %s", why)
        stop = bridge_command(Effect.HALT)
        failed = "; ".join(halted.arms.not_held) or None
        entry = AuditRecord(
            event=AuditEvent.NETWORK_LOSS_SAFE_STOP, message_id=stop.message_id,
            action_type=stop.action, params={}, applied=applied,
            outcome=(Outcome.FAILED if failed else Outcome.EXECUTED).value,
            deny_reason=f"arms not held: {failed}" if failed else None,
            ros2_topic=self._steps.route(stop), sent_first=True)
        await self._steps.record_event(entry)

    async def stop(self) -> None:
        """BRIDGE_STOPPED once the held commands are withdrawn (`withdraw_all_held`) and the
        sweeper, the tasks and the latch are done. Idempotent."""
        if self._stopping:
            return
        self._stopping = True
        self.end_streams()
        await self.withdraw_all_held()  # what was held since the run's stop path did it
        self._stopped = True
        if self._sweeper is not None:
            self._sweeper.cancel()
            await asyncio.gather(self._sweeper, return_exceptions=True)
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self.latch.close()
        await self._estops.record_repeats()
        params: dict[str, Any] = {"estop_latched": self.latch.latched,
                                  "locks": dict(self._base.lock_holders)}
        # The bridge's halt had their server canceling everything it had: these it had not
        # accepted yet, and their watches end with the bridge. The next start cancels them.
        watched = LeftRunning(goals=self._steps.goals_watched())
        if watched:
            log.warning("stopping with %d goals whose send gave up not yet seen ended (their "
                        "server may accept them late): the next start cancels them",
                        len(watched.goals))
            params["left_running"] = watched.facts()
        await self.audit.append(AuditRecord(event=AuditEvent.BRIDGE_STOPPED, params=params))

    def _latch_flipped(self) -> None:
        """The latch's reflex, at the flip and before any await (no loop turn, no disk): an
        e-stop zeroes the stream and publishes the e-stop Bool; then STATUS is told. Each
        step is tried on its own: one failing must not keep the next from the robot."""
        for step in (self.streams.on_latch, self._signal_estop, self._estop_withdraws,
                     self.events.governance.emit):
            try:
                step()
            except Exception:
                log.exception("e-stop reflex step %s failed", getattr(step, "__name__", step))

    def _signal_estop(self) -> None:
        if self.latch.latched:
            self._dispatcher.signal_estop()

    def _estop_withdraws(self) -> None:
        if self.latch.latched:  # a stop of the robot (`VelocityStreams.on_latch`)
            self._robot_stopped("an e-stop")

    def _estop_withdraws_clears(self) -> None:
        """An e-stop (a repeat while latched too) withdraws every clear_estop held for a human,
        in its step: each was asked for before this e-stop, and approved later it would
        release the robot from an e-stop nobody asked it to clear — as a clear under way that
        an e-stop overtakes is refused (`EstopMachine.overtaken`). `_run_approved` refuses
        one this misses (held as the e-stop came, say)."""
        self._withdraw_held(None, ESTOPPED_WHILE_HELD, which=_is_clear, what="e-stop clear")

    # -- commands ---------------------------------------------------------------------------

    async def decide(self, command: NormalizedCommand, principal: Principal) -> Decision:
        """Decide, act and audit; a caller that goes away does not stop the decision."""
        effect = command.spec.effect
        if command.spec.stopping:
            command = self._forgiven(command, principal)
        if effect is Effect.ESTOP:  # any authenticated principal; latched right here
            estopping = self.latch.engage(lambda: self._estops.estop(command, principal))
            self._estop_withdraws_clears()
            decided = await asyncio.shield(estopping)
        elif effect is Effect.HALT:  # the e-stop lane: no admission queue
            decided = await self._detached(self._decide(command, principal))
        else:
            arrived, done = self._arrival(command, principal)
            decided = await self._admitted(command, principal, arrived, done)
        return self._as_told(command, principal, decided)

    def decide_soon(self, command: NormalizedCommand, principal: Principal
                    ) -> asyncio.Future[Decision]:
        """`decide`, for a caller that must learn the decision even if it is cancelled
        meanwhile (an INVOKE whose client left is still answered in the log, §19.5): the
        command arrives now, in the caller's step, as in `decide` (a stop, or its
        connection's close, from the next step on wins over it), and is decided in a task
        of its own; the future returned is shielded from the caller's cancellation."""
        if command.spec.stopping:
            return asyncio.shield(self._steps.spawn(self.decide(command, principal)))
        # In this step, as `decide` makes it; its task is never cancelled (the caller's
        # cancel stops at the shield), so `_admitted` ends what `_arrival` began.
        arrival = self._arrival(command, principal)
        return asyncio.shield(self._steps.spawn(self._admitted_told(command, principal,
                                                                    *arrival)))

    async def _admitted_told(self, command: NormalizedCommand, principal: Principal,
                             arrived: StopMark | None, done: Callable[[], None] | None
                             ) -> Decision:
        decided = await self._admitted(command, principal, arrived, done)
        return self._as_told(command, principal, decided)

    def _as_told(self, command: NormalizedCommand, principal: Principal,
                 decided: Decision) -> Decision:
        """The decision as its caller is told it: its thought remembered, its warnings."""
        if command.ai is not None:
            self._remember_thought(command, principal, decided)
        if command.warnings:  # executed anyway: the caller learns what was wrong
            return msgspec.structs.replace(decided, warnings=list(command.warnings))
        return decided

    def _arrival(self, command: NormalizedCommand, principal: Principal
                 ) -> tuple[StopMark | None, Callable[[], None] | None]:
        """Motion is on its way from the moment it arrives (`_on_its_way`): its stop mark,
        and what ends its being decided (`VelocityStreams.arrived`, `decided`)."""
        on_its_way = self._on_its_way(command, principal)  # in this step: no stop between
        arrived = self.streams.arrived(principal.name) if on_its_way else None
        done = functools.partial(self.streams.decided, principal.name) if arrived else None
        return arrived, done

    async def _admitted(self, command: NormalizedCommand, principal: Principal,
                        arrived: StopMark | None, done: Callable[[], None] | None
                        ) -> Decision:
        """A command that waits its turn (`MAX_IN_FLIGHT`), on its way since it arrived
        (`_arrival`): a stop of it that comes while it waits (a `stop`, its connection
        closing) wins over it as over motion further on (`VelocityStreams.arrived`)."""
        try:
            await self._admission.acquire()
        except BaseException:  # its caller left before it was decided: nothing on its way
            if done is not None:
                done()
            raise
        try:  # from here its decision's task holds it on its way, until it is settled
            return await self._detached(self._decide(command, principal, arrived), then=done)
        finally:
            self._admission.release()

    def _on_its_way(self, command: NormalizedCommand, principal: Principal) -> bool:
        """Whether `command`, as it arrives, is motion on its way (`_admitted`).

        Not if its sender's role may not issue it at all (a GUEST's move): `_precheck` refuses
        it first thing, by the same policy (fixed at start), so none of it can run. Counted,
        it was another principal's motion on its way for every session loss while it waited
        (`VelocityStreams.driven_by_other_than`) and narrowed the loss's halt of the whole
        robot to a stop of the lost principal's own motion (`safe_stop`): a GUEST sending
        refused moves without end kept any session loss from halting the robot.

        Anything else counts, whatever its other checks will say (its sender may move, and
        could hold the same with moves that run), and so does an action the policy does not
        know: when unsure, count. Counting motion that is then refused only narrows a halt to
        the lost principal's own motion, which still all stops; not counting motion that then
        runs would let a halt, or any stop that comes while it waits, miss it (its mark would
        be taken only once it is decided, after that stop: `_execute`)."""
        return command.spec.motion and not self._roles.refuses(principal.role, command.action)

    @property
    def thoughts(self) -> ThoughtLog:
        """What each AI thought led to (§16.5). Made, and its module imported, by the first
        AI command or read: most runs have none (issue 27: idle memory)."""
        if self._thoughts is None:
            from .thoughts import ThoughtLog

            self._thoughts = ThoughtLog()
        return self._thoughts

    def _remember_thought(self, command: NormalizedCommand, principal: Principal,
                          decided: Decision) -> None:
        facts = ai_facts(command) or {}
        self.thoughts.remember(
            command, principal, now_ms(self._clock), outcome=decided.outcome.value,
            audit_id=decided.audit_id, reason=decided.reason,
            error_code=decided.error_code.value if decided.error_code else None,
            reasoning_sha256=facts.get("reasoning_sha256"))

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
                             message_id: str | None = None,
                             rcan: dict[str, Any] | None = None) -> Decision:
        """A request refused before it became a command (schema, size, credentials).

        Unauthenticated requests are not audited: anyone could fill the disk with them.
        """
        if principal is None:
            return decision(rejection, message_id=message_id)
        entry = AuditRecord(
            event=AuditEvent.COMMAND_REJECTED, principal=principal.name, role=principal.role.name,
            message_id=message_id, outcome=rejection.outcome.value,
            deny_reason=rejection.deny_reason, rcan=rcan,
        )
        return decision(rejection, await self.audit.append(entry), message_id=message_id)

    async def _decide(self, command: NormalizedCommand, principal: Principal,
                      arrived: StopMark | None = None) -> Decision:
        """`arrived`: motion's mark, taken as it arrived (`_admitted`)."""
        refused = self._precheck(command, principal)
        if refused is not None:
            return await self._steps.refuse(command, principal, refused)
        if command.spec.effect is Effect.HALT or not command.client_message_id:
            return await self._govern(command, principal, arrived)  # never swallowed or retried
        key = (principal.name, command.message_id)
        earlier = self._idem.claim(key, _fingerprint(command))
        if isinstance(earlier, Conflict):
            return await self._steps.refuse(command, principal, outcomes.MESSAGE_ID_CONFLICT)
        if isinstance(earlier, DecidedBefore):
            return await self._steps.refuse(command, principal, outcomes.DECIDED_BEFORE_RESTART)
        if earlier is not None:  # a retry: the first outcome, nothing executed twice
            return await earlier
        try:
            decision = await self._govern(command, principal, arrived)
        except BaseException as exc:
            self._idem.abandon(key, exc)
            raise
        self._idem.resolve(key, decision)
        return decision

    def _precheck(self, command: NormalizedCommand, principal: Principal) -> Rejection | None:
        if _claims_more(command.claimed_role, principal.role):
            return outcomes.privileges(f"the message claims a role above {principal.role.name}, "
                                       "the credential's")
        if not self._roles.allows(principal.role, command.action):
            return outcomes.privileges(f"{command.action} needs "
                                       f"{self._roles.required(command.action).name} or higher")
        elsewhere = self.not_this_robot(command.ruri)
        if elsewhere is not None:
            return elsewhere
        if not command.spec.stopping:  # a stop's AI problems are warnings (`_forgiven`)
            refused = self._ai.check(command, principal)
            if refused is not None:
                return refused
        if command.spec.effect is not Effect.HALT and not self._limiter.allow(principal):
            return outcomes.RATE_LIMITED  # a stop is never rate-limited
        if not command.spec.stopping and not self.audit.logs_whole(command.requested):
            return outcomes.PARAMS_TOO_LARGE_TO_LOG  # never run with its params left out
        return None

    def not_this_robot(self, ruri: str | None) -> Rejection | None:
        """The refusal of a message addressed to another robot (or to an unreadable RURI)."""
        if ruri is None or self._robot is None:
            return None
        try:
            if parse_ruri(ruri).robot != self._robot:
                return outcomes.NOT_THIS_ROBOT
        except InvalidRuriError as exc:
            return outcomes.invalid_ruri(exc.rule)
        return None

    async def _govern(self, command: NormalizedCommand, principal: Principal,
                      arrived: StopMark | None) -> Decision:
        try:
            applied = self._safety(command, command.params)
        except Violation as violation:
            return await self._steps.refuse(command, principal, violation.rejection)
        gate = self._hitl.gate(command)
        if isinstance(gate, Rejection):
            return await self._steps.refuse(command, principal, gate)
        if isinstance(gate, Escalate):
            return await self._held(command, principal, gate.approver_role, arrived)
        # A command still being carried out (waiting for a subscriber, say) is not silence.
        with self._sessions.in_flight(principal):
            decision = await self._execute(command, principal, applied,
                                           AuditEvent.COMMAND_DISPATCHED, arrived=arrived)
        self._opened(principal, command, decision)
        self._sessions.heartbeat(principal)
        return decision

    async def _held(self, command: NormalizedCommand, principal: Principal,
                    approver_role: Role, arrived: StopMark | None) -> Decision:
        """A command a human must authorize, held (PENDING_AUTH) — unless it is motion that
        a stop of its sender's motion came for since it arrived (`arrived`: its client
        cancelled a motion call, its connection closed, a `stop`): that motion must never
        start, and a human approving it later would start it. Refused `stopped` as motion
        not held is; a stop that comes while its PENDING_AUTH entry is written withdraws it
        as soon as it is held (`command_cancelled` withdraws only what is held already).
        What it is held with (`PendingCommand.stops`) makes a stop of the robot that comes
        while it waits a stop for it too (`_run_approved`)."""
        if arrived is not None and self.streams.stopped_since(arrived):
            return await self._steps.refuse(command, principal, outcomes.STOPPED)
        clear = command.spec.effect is Effect.CLEAR_ESTOP
        held = await self._desk.hold(command, principal, approver_role,
                                     self.streams.stops if command.spec.motion else None,
                                     self.latch.arrived if clear else None)
        # In the step it was put in the store: no review of it can come first.
        if arrived is None or held.pending_id is None or not self.streams.stopped_since(arrived):
            return held
        return await self._desk.resolve(held.pending_id, principal, "withdraw",
                                        STOPPED_WHILE_HELD)

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

    async def _execute(self, command: NormalizedCommand, principal: Principal,
                       params: ActionParams, event: AuditEvent,
                       pending_id: str | None = None, issuer: Principal | None = None,
                       arrived: StopMark | None = None) -> Decision:
        """`issuer`: whose command it is, when `principal` approved it (HiTL); `arrived`:
        motion's mark, on its way since it arrived (`_admitted`)."""
        applied = msgspec.structs.asdict(params)
        spec = command.spec
        if spec.effect is Effect.CLEAR_ESTOP:
            return await self.latch.clear(
                lambda: self._estops.clear(command, principal, event, pending_id))
        if spec.effect in (Effect.LOCK, Effect.UNLOCK):
            return await self._base.lock(command, principal, params, event, pending_id)
        if spec.effect is Effect.HALT:  # zero at once, before the stop is even audited
            self.streams.halt(principal.name)
            self._robot_stopped(f"a stop by '{principal.name}'")
            return await self._halt(command, principal, params, event)
        owner = issuer or principal  # a stream is its issuer's, at the issuer's priority
        if not spec.motion:
            return await self._carry_out(command, principal, owner, params, applied, event,
                                         pending_id, self.streams.mark(owner.name))
        if arrived is not None:  # on its way since it arrived, held so by its task
            return await self._carry_out(command, principal, owner, params, applied, event,
                                         pending_id, arrived)
        # Decided: from now on it drives the base for a session loss of someone else's, and
        # a stop of it (everyone's, or its owner's alone) wins over it: decided before the
        # stop, it must not reach the robot after it (`VelocityStreams.stopped_since`).
        with self.streams.deciding(owner.name) as stops:
            return await self._carry_out(command, principal, owner, params, applied, event,
                                         pending_id, stops)

    async def _carry_out(self, command: NormalizedCommand, principal: Principal,
                         owner: Principal, params: ActionParams, applied: dict[str, Any],
                         event: AuditEvent, pending_id: str | None, stops: StopMark
                         ) -> Decision:
        """`_execute` of what is neither a stop, a clear nor a lock: checked, written ahead,
        sent; motion only if no stop came since it was decided (`stops`)."""
        spec = command.spec
        motion = spec.motion
        if motion and self.latch.latched:
            return await self._steps.refuse(command, principal, outcomes.ESTOP_ACTIVE, event=event,
                                      pending_id=pending_id)
        priority = self._base.priorities.of(owner)
        # Streams and goals both drive the base: the same priorities and locks hold.
        refused = self._base.admits(priority) if spec.streamed or spec.starts_goal else None
        if refused is not None:
            return await self._steps.refuse(command, principal, refused, event=refused_event(event),
                                      pending_id=pending_id)
        why = await self._steps.ready(command)
        if why is not None:
            return await self._steps.refuse(command, principal, outcomes.robot_unavailable(why),
                                      event=event, pending_id=pending_id)
        # An e-stop that latched while this command waited wins.
        if motion and self.latch.latched:
            return await self._steps.refuse(command, principal, outcomes.ESTOP_ACTIVE, event=event,
                                      pending_id=pending_id)
        if spec.streamed:
            return await self._base.stream(command, principal, owner, params, applied, event,
                                      pending_id, priority, stops)
        if self._names_others_arm(command, owner):
            return await self._steps.refuse(command, principal, outcomes.ID_OF_ANOTHER_S_ARM,
                                            event=event, pending_id=pending_id)
        if spec.starts_goal:  # its id chosen now: its entry names it (a crash's restart cancels)
            command = msgspec.structs.replace(command, goal_id=str(uuid.uuid4()))
        entry = record(event, command, principal, Outcome.EXECUTED, applied=applied,
                       pending_id=pending_id, ros2_topic=self._steps.route(command),
                       boot=self._clock.boot() if _is_trajectory(command) else None)
        receipt = await self._steps.write_ahead(entry)
        if receipt is None:
            return decision(outcomes.AUDIT_UNAVAILABLE, message_id=command.message_id)
        # Checked again after the write, with no await between this check and the publish.
        halted = self.streams.halted_since(stops) if motion else None
        if halted is None and self._names_others_arm(command, owner):  # came meanwhile
            halted = outcomes.ID_OF_ANOTHER_S_ARM
        if halted is not None:
            return await self._steps.failed(command, principal, halted)
        if motion:
            self._sending(owner, command)
        result, failure = await self._steps.dispatch(command, params)
        if failure is not None:
            # A goal the bridge refused because a stop came while it was on its way (it
            # cancels it: `GoalTracker`) is answered as one this governor cancels: `stopped`.
            halted = self.streams.halted_since(stops) if spec.starts_goal else None
            return await self._steps.failed(command, principal, halted or failure,
                                            goal_id=result.goal_id)
        if spec.starts_goal:  # a stop or e-stop since it was decided: cancelled by id
            refused = self._base.hold_goal(result.goal_id, owner, priority, command.message_id,
                                           stops)
            if refused is not None:  # (running until its cancel ends it: named, as it may run)
                return await self._steps.failed(command, principal, refused,
                                                goal_id=result.goal_id)
        if result.runs_for_s is not None and result.ros2_topic:
            self._ran_on(result.ros2_topic, owner.name, command.message_id)
        return executed(command, applied, receipt, result)

    def _names_others_arm(self, command: NormalizedCommand, owner: Principal) -> bool:
        """Whether `command` would send an arm's trajectory under the message id of another
        principal's trajectory still running. An arm is held by that id (a stop of one
        principal's motion, an INVOKE's cancel or its client gone), and clients choose ids,
        unique per principal only: the other's arm would be held with this one's."""
        return (_is_trajectory(command)
                and command.message_id in self._trajectories(owner.name, others=True))

    def _ran_on(self, topic: str, owner: str, message_id: str) -> None:
        running = self._steps.running_trajectories()
        sent = {m: who for m, who in self._runs_on.get(topic, {}).items()
                if running is None or m in running}
        sent[message_id] = owner
        self._runs_on[topic] = dict(list(sent.items())[-RUNS_ON_KEPT:])
        # Another principal's trajectory of this id (ids are unique per principal only) has
        # ended, or this one would have been refused (`_names_others_arm`): forgotten, so
        # that a stop of that principal's motion does not hold this one by its id.
        for elsewhere in self._runs_on.values():
            if elsewhere.get(message_id, owner) != owner:
                del elsewhere[message_id]

    def _trajectories(self, owner: str, *, others: bool = False) -> list[str]:
        """The message ids of `owner`'s (or, `others`, everyone else's) commands whose motion
        may still run on (`_runs_on`); when that cannot be read, all of them."""
        running = self._steps.running_trajectories()
        return [message_id for sent in self._runs_on.values() for message_id, who in sent.items()
                if (who != owner) == others and (running is None or message_id in running)]

    async def _halt(self, command: NormalizedCommand, principal: Principal,
                    params: ActionParams, event: AuditEvent) -> Decision:
        """A stop: zero velocity and goal cancels go out first, its entry is sealed in this
        step (after the halt, before any await) and made durable beside them (never before:
        stopping does not wait for the disk), then the reply."""
        applied: dict[str, Any] = {}  # nothing of the body reaches the robot (a reason is kept)
        entry = record(event, command, principal, Outcome.EXECUTED, applied=applied,
                         ros2_topic=self._steps.route(command), sent_first=True)
        self.streams.take_goals()  # the halt cancels every goal
        # Sealed in this step, with the halt: the log lists it where the robot got it.
        (dispatched,), receipt = await self._steps.stop(entry,
                                                       self._steps.dispatch(command, params))
        result, failure = sent(dispatched)
        if receipt is None:
            return decision(outcomes.AUDIT_UNAVAILABLE, message_id=command.message_id)
        if failure is not None:
            return await self._steps.failed(command, principal, failure)
        return executed(command, applied, receipt, result)

    def end_streams(self) -> None:
        """The bridge is stopping: zero now, before the robot is halted and the log closed;
        no motion starts from now on, whenever decided (the robot's halt is the last thing
        this bridge tells it)."""
        self.streams.close(EndReason.BRIDGE_STOPPED)

    # -- goals the robot carries out -------------------------------------------------------

    def goal_finished(self, goal_id: str, outcome: str, *, server: str,
                      message_id: str | None, detail: str | None = None) -> None:
        """A goal the bridge sent ended (succeeded, aborted, canceled, …): audited.

        `message_id` links it to the COMMAND_DISPATCHED entry that sent it."""
        detail = self._base.goal_ended(goal_id) or detail  # the base is free of it
        if self._stopped:  # BRIDGE_STOPPED is the last entry
            log.info("goal %s %s after the bridge stopped: not audited", goal_id, outcome)
            return
        entry = AuditRecord(event=AuditEvent.GOAL_FINISHED, message_id=message_id,
                            params={"goal_id": goal_id}, outcome=outcome,
                            deny_reason=detail, ros2_topic=server)
        self._steps.spawn(self._steps.record_event(entry))

    def foreign_publisher(self, facts: dict[str, Any], *, gone: bool = False) -> None:
        """Another participant began (or, `gone`, stopped) publishing on a topic the bridge
        commands the robot on: audited (FOREIGN_PUBLISHER, FOREIGN_PUBLISHER_GONE). `facts`:
        its topic, type, participant, node and writers."""
        event = AuditEvent.FOREIGN_PUBLISHER_GONE if gone else AuditEvent.FOREIGN_PUBLISHER
        if self._stopped:  # BRIDGE_STOPPED is the last entry
            log.info("%s on %s after the bridge stopped: not audited", event.value,
                     facts.get("topic"))
            return
        entry = AuditRecord(event=event, params=facts, ros2_topic=facts.get("topic"))
        self._steps.spawn(self._steps.record_event(entry))

    async def invoke_result(self, principal: Principal, *, invoke_id: str, status: str,
                            outcome: str | None, facts: dict[str, Any],
                            detail: str | None = None) -> None:
        """An RCAN INVOKE's result (§19.3), decided: audited (INVOKE_RESULT) before it is
        answered, so that each INVOKE's lifecycle (its decision entries and this one, all
        with `message_id` = its msg_id) can be read back from the log. `outcome`: the
        governor's decision on the skill's command (`denied` for an INVOKE refused before it
        became one); `facts`: the skill, duration, goal and error."""
        if self._stopped:  # BRIDGE_STOPPED is the last entry
            log.info("INVOKE %s %s after the bridge stopped: not audited", invoke_id, status)
            return
        entry = AuditRecord(event=AuditEvent.INVOKE_RESULT, principal=principal.name,
                            role=principal.role.name, message_id=invoke_id, invoke_id=invoke_id,
                            status=status, outcome=outcome, params=facts, deny_reason=detail)
        # Its own task: stop() waits for it, and the caller's cancellation does not undo it.
        await asyncio.shield(self._steps.spawn(self._steps.record_event(entry)))

    # -- HiTL (the desk holds and reviews; an approved command comes back here) -------------

    async def authorize(self, pending_id: str, approver: Principal,
                        reason: str | None = None, *, said_by: ReviewMessage = NO_MESSAGE
                        ) -> Decision:
        """One approval; the command runs once it has as many distinct ones as it needs.
        `said_by`: the AUTHORIZE message (§16.4) that said it, recorded with the review (a
        signed one is checked against the held command it names: `review`)."""
        return await self._detached(self._desk.resolve(pending_id, approver, "approve", reason,
                                                       said_by))

    async def deny(self, pending_id: str, approver: Principal,
                   reason: str | None = None, *, said_by: ReviewMessage = NO_MESSAGE
                   ) -> Decision:
        """Any approver's denial ends it, whatever approvals it had."""
        return await self._detached(self._desk.resolve(pending_id, approver, "deny", reason,
                                                       said_by))

    async def withdraw(self, pending_id: str, principal: Principal,
                       reason: str | None = None, *, said_by: ReviewMessage = NO_MESSAGE
                       ) -> Decision:
        """Its issuer takes a pending command back (an approver may too): never executed."""
        return await self._detached(self._desk.resolve(pending_id, principal, "withdraw",
                                                       reason, said_by))

    async def refuse_review(self, pending_id: str, reviewer: Principal, verdict: Verdict,
                            rejection: Rejection, said_by: ReviewMessage = NO_MESSAGE
                            ) -> Decision:
        """A review the transport refused before the desk saw it (an approval its
        principal's policy wants signed): audited as the desk's refusals are."""
        return await self._detached(self._desk.refuse(verdict, reviewer, rejection, pending_id,
                                                      said_by))

    def pending(self) -> list[PendingAuth]:
        return self._desk.pending()

    def pending_record(self, pending_id: str) -> PendingRecord | None:
        """One held command, waiting or what came of it (see `review`), or None if unknown."""
        return self._desk.record(pending_id)

    def held_ended(self, pending_id: str) -> asyncio.Future[Ended] | None:
        """What ends a held command (`HitlDesk.ended`): a held INVOKE is answered then."""
        return self._desk.ended(pending_id)

    def role_for(self, action: str) -> Role:
        """The role `action` needs here (the profile's table, with the config's overrides)."""
        return self._roles.required(action)

    def pending_for_thought(self, thought_id: str) -> str | None:
        """The held command whose AI `thought_id` this is (AUTHORIZE names it so), or None."""
        return self._desk.for_thought(thought_id)

    async def cancel_goal(self, goal_id: str, principal: Principal, *, message_id: str | None,
                          why: str) -> Decision:
        """Cancel one goal of `principal`'s at its request (INVOKE_CANCEL, an INVOKE's
        timeout: §19), audited before the cancel goes out."""
        return await self._detached(self._base.cancel_requested(
            goal_id, principal, message_id=message_id, why=why))

    async def hold_trajectory(self, sent_by: str, principal: Principal, *,
                              message_id: str | None, why: str) -> Decision:
        """Hold the arm still running the trajectory the command `sent_by` sent, at its
        sender's request (an INVOKE_CANCEL of the INVOKE that sent it, its timeout: §19).
        Held first, as any stop (it never waits for the disk), then audited: a
        COMMAND_DISPATCHED `hold_trajectory` entry, or COMMAND_FAILED naming why the arm could
        not be held. The caller has checked the command is `principal`'s."""
        # Arms are held by id, unique per principal only: another's trajectory of this id
        # running means this one's ended (else the other's was refused: `_names_others_arm`),
        # and that one is not this principal's to hold.
        theirs = sent_by in self._trajectories(principal.name, others=True)
        arms = self._steps.hold_trajectories([] if theirs else [sent_by])
        facts = {"sent_by": sent_by, "why": why, **_arms_applied(arms)}
        failed = outcomes.robot_unavailable("; ".join(arms.not_held)) if arms.not_held else None
        entry = AuditRecord(
            event=AuditEvent.COMMAND_FAILED if failed else AuditEvent.COMMAND_DISPATCHED,
            principal=principal.name, role=principal.role.name, message_id=message_id,
            action_type="hold_trajectory", params=facts,
            outcome=(failed.outcome if failed else Outcome.EXECUTED).value,
            deny_reason=failed.deny_reason if failed else None, sent_first=True)
        # Detached: the INVOKE_CANCEL's task may be cancelled; the entry must not be.
        return await self._detached(self._hold_recorded(entry, failed))

    async def _hold_recorded(self, entry: AuditRecord, failed: Rejection | None) -> Decision:
        receipt = await self._steps.write_ahead(entry, urgent=True)
        if receipt is None:
            return decision(outcomes.AUDIT_UNAVAILABLE, message_id=entry.message_id)
        if failed is not None:
            return decision(failed, receipt, message_id=entry.message_id)
        return Decision(outcome=Outcome.EXECUTED, http_status=200, audit_id=receipt.audit_id,
                        message_id=entry.message_id, applied=entry.params)

    def end_stream(self, sent_by: str, principal: Principal, *, why: str) -> bool:
        """End the velocity stream `principal`'s command `sent_by` started, if it still runs,
        at its sender's request (an INVOKE_CANCEL of the INVOKE that started it, its timeout:
        §19): zero at once, as any stop (no await); its STREAM_ENDED says `cancelled`, by
        whom and `why`. Only that stream: a later move that replaced it, or anyone else's,
        runs on. Whether it ended."""
        return self.streams.end_command(principal.name, sent_by, EndReason.CANCELLED, why=why)

    def stream_running(self, sent_by: str, principal: Principal) -> bool:
        """Whether the velocity stream `principal`'s command `sent_by` started still runs."""
        active = self.streams.active
        return active is not None and (active.owner, active.message_id) == (principal.name,
                                                                            sent_by)

    def goal_held(self, goal_id: str) -> bool:
        """Whether the goal `goal_id` still holds the base: sent, not ended, and not taken by
        a stop (which cancels it itself)."""
        return goal_id in self.streams.goals

    def trajectory_running(self, sent_by: str, principal: Principal) -> bool:
        """Whether the trajectory `principal`'s command `sent_by` sent may still be running
        (not held by a stop, its time not up); when that cannot be read, it may."""
        # Ids are unique per principal only: another's trajectory of this id sent means this
        # one's ended (`_ran_on`), and its running is not this one's (an INVOKE's success).
        if sent_by in self._trajectories(principal.name, others=True):
            return False
        running = self._steps.running_trajectories()
        return running is None or sent_by in running

    async def expire_pending(self) -> list[Decision]:
        """Discard and audit (HITL_EXPIRED) every pending command past its TTL."""
        return await self._desk.expire()

    async def _run_approved(self, command: NormalizedCommand, approver: Principal,
                            pending: PendingCommand) -> Decision:
        """The last approval released it: the state *now* decides, not the state when the
        command arrived; it runs as its issuer's, audited as HITL_AUTHORIZED. Motion that a
        stop of the robot (a `stop`, an e-stop, a session loss's halt) came after it was held
        is refused `stopped`: that stop was for all motion decided before it, and a human
        approving it later — from a list read before the stop, say — must not start it. The
        stop withdraws such motion itself (`_robot_stopped`), in its step; this is the
        backstop, should a withdrawal miss one (motion being decided once approved is
        stopped as any other: `_carry_out`)."""
        if pending.estops is not None and self.latch.arrived != pending.estops:
            # A clear held before an e-stop was not asked for that e-stop: approved, it would
            # release the robot from an e-stop acknowledged after the clear was asked for (the
            # e-stop withdraws it, `_estop_withdraws_clears`: this is the backstop).
            return await self._steps.refuse(command, approver, outcomes.ESTOP_ACTIVE,
                                            event=AuditEvent.HITL_AUTHORIZED,
                                            pending_id=pending.pending_id)
        stopped = pending.stops is not None and self.streams.stops != pending.stops
        if stopped and not self.latch.latched:  # (latched: refused `estop_active`, below)
            return await self._steps.refuse(command, approver, outcomes.STOPPED,
                                            event=AuditEvent.HITL_AUTHORIZED,
                                            pending_id=pending.pending_id)
        try:
            applied = self._safety(command, command.params)
        except Violation as violation:
            return await self._steps.refuse(command, approver, violation.rejection,
                                            event=AuditEvent.HITL_AUTHORIZED,
                                            pending_id=pending.pending_id)
        outcome = await self._execute(command, approver, applied, AuditEvent.HITL_AUTHORIZED,
                                      pending.pending_id, issuer=pending.issuer)
        self._opened(pending.issuer, command, outcome)
        return outcome

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
        if (self.streams.driven_by_other_than(principal.name)
                or self._trajectories(principal.name, others=True)):
            return await self._own_stop(principal, why, own)
        log.warning("control session of '%s' lost (%s): halting the robot (safe stop)",
                    principal.name, why)
        # A halt of the whole robot: a stop for all motion decided before it (only the
        # principal's own: nobody else's is on its way, `driven_by_other_than`).
        self.streams.halt(principal.name, EndReason.SESSION_LOST)
        self._robot_stopped(f"a halt for the lost control session of '{principal.name}'")
        self.streams.take_goals()  # the halt cancels every goal
        self.events.session_lost.emit(principal)  # e.g. log the goals being cancelled
        stop = bridge_command(Effect.HALT)
        entry = record(AuditEvent.NETWORK_LOSS_SAFE_STOP, stop, principal, Outcome.EXECUTED,
                         applied={}, ros2_topic=self._steps.route(stop), sent_first=True)
        # Halted first, and even if the audit cannot be written: stopping is never held back.
        (dispatched,), receipt = await self._steps.stop(entry, self._steps.dispatch(stop))
        result, failure = sent(dispatched)
        self.events.safe_stop.emit(principal)  # e.g. STATUS shows `safe_stop`
        if receipt is None:
            return decision(outcomes.AUDIT_UNAVAILABLE, message_id=stop.message_id)
        if failure is not None:
            return await self._steps.failed(stop, principal, failure)
        return executed(stop, {}, receipt, result)

    async def _own_stop(self, principal: Principal, why: str,
                        goals: list[HeldGoal]) -> Decision:
        log.warning("control session of '%s' lost (%s): its goals cancelled; the base stays "
                    "with who holds it", principal.name, why)
        # Its motion still on its way (a goal being sent, a move waiting for its entry) is
        # stopped too, as it comes: refused, or cancelled once its server accepted it; and
        # its motion held for a human is withdrawn (nobody else's).
        self.streams.own_stop(principal.name)
        self._withdraw_held(principal, SESSION_LOST.format(why))
        arms = self._hold_own(principal)
        self._base.cancel_goals(goals, principal, why="session lost")
        applied = {"scope": "own", "goals_cancelled": [g.goal_id for g in goals],
                   **_arms_applied(arms)}
        return await self._own_stop_recorded(principal, applied)

    def _hold_own(self, principal: Principal) -> ArmsHeld:
        """Holds the arms still running a trajectory of `principal`'s (no await)."""
        arms = self._steps.hold_trajectories(self._trajectories(principal.name))
        for why in arms.not_held:
            log.warning("stopping the motion of '%s': %s", principal.name, why,
                        extra={"principal": principal.name})
        return arms

    async def _own_stop_recorded(self, principal: Principal, applied: dict[str, Any]
                                 ) -> Decision:
        """The entry of a stop of `principal`'s motion alone: nothing was sent to the robot."""
        stop = bridge_command(Effect.HALT)
        entry = record(AuditEvent.NETWORK_LOSS_SAFE_STOP, stop, principal, Outcome.EXECUTED,
                         applied=applied, sent_first=True)
        _, receipt = await self._steps.stop(entry)  # sealed with the cancels, not after
        if receipt is None:
            return decision(outcomes.AUDIT_UNAVAILABLE, message_id=stop.message_id)
        return executed(stop, applied, receipt, DispatchResult(ok=True))

    def connection_closed(self, principal: Principal) -> bool:
        """The principal's connection closed: its motion that arrived before now and has not
        started (waiting its turn, for the robot or for its entry: it opened no session yet;
        a goal being sent) never starts, or is cancelled once its server accepted it; nobody
        else's is touched. Whether any was on its way. `end_session` does this first; a
        connection that awaits its command in flight before that calls it before. Its motion
        held for a human is withdrawn (`CONNECTION_CLOSED`): an approval must not start motion
        for a client that is gone."""
        self._withdraw_held(principal, CONNECTION_CLOSED)
        return self.streams.own_stop(principal.name)

    async def end_session(self, principal: Principal, *, on_its_way: bool = False
                          ) -> Decision | None:
        """The principal's connection closed: if it held a control session, safe stop now;
        motion of its that arrived before this and has not started never starts, in any case
        (`connection_closed`; `on_its_way`: what it said, when called earlier).

        Returns the safe stop's decision, or None when there was nothing to stop.
        """
        # Now, before any await: its motion on its way must not start after its connection
        # is gone (before, with no session yet, nothing stopped it: it ran until it timed out).
        on_its_way = self.connection_closed(principal) or on_its_way
        # Detached: the closing connection's handler may be cancelled; the stop must not be.
        if self._sessions.end(principal):
            return await self._detached(self.safe_stop(principal, "its connection closed"))
        if not on_its_way:
            return None
        # Nothing of its reached the robot (that opens a session): a stop of its motion
        # alone, whoever else drives; a halt would stop theirs, or the robot for nothing.
        log.warning("connection of '%s' closed while motion of its was on its way: that "
                    "motion is stopped; nothing else", principal.name)
        applied = {"scope": "own", "goals_cancelled": [], "before_session": True}
        return await self._detached(self._own_stop_recorded(principal, applied))

    def command_cancelled(self, principal: Principal) -> Awaitable[Decision | None]:
        """`motion_cancelled`'s stop alone (its `stopping`)."""
        return self.motion_cancelled(principal).stopping

    def motion_cancelled(self, principal: Principal) -> ClientCancel:
        """A motion command of the principal's was cancelled by its client before its answer
        came (the transport, which knows which of its calls are motion, says so). Its
        decision goes on, detached, and is audited as ever; but its motion must not start,
        or run on, for a caller that no longer wants it — and the governor cannot tell which
        of the principal's motion it was: all of it stops, and nobody else's. Now, before
        any await: its motion on its way never starts (as
        `connection_closed`: refused `stopped`, or its goal cancelled once accepted; held for
        a human once decided, it is refused or withdrawn instead: `_held`), its stream ends
        with zero, its goals are cancelled, its control session ends (nothing of its is left
        to guard), and its motion held for a human is withdrawn (`_withdraw_held`).

        Returns the held commands withdrawn (their pending ids) and what to await: the entry
        of that stop of its own motion (NETWORK_LOSS_SAFE_STOP, `applied.cancelled_by_client`),
        written even if nobody awaits it, or None when nothing of its was on its way or
        running; done once its withdrawals are on record."""
        if self._stopped:  # BRIDGE_STOPPED is the last entry: it halted everything before it
            return ClientCancel((), _resolved(None))
        withdrawing = self._withdraw_held(principal, CANCELLED_BY_CLIENT)
        ids, withdrawn = tuple(withdrawing), list(withdrawing.values())
        on_its_way = self.connection_closed(principal)
        stream = self.streams.active
        ended = self.streams.end_of(principal.name, EndReason.CANCELLED)
        goals = self.streams.take_goals(owner=principal.name)
        arms = self._hold_own(principal)
        if not (on_its_way or ended or goals or arms.held or arms.not_held):
            return ClientCancel(ids, self._after(withdrawn, _resolved(None)))
        self._sessions.end(principal)
        log.warning("a motion command of '%s' was cancelled by its client: its own motion "
                    "is stopped (on its way: %s, stream ended: %s, goals cancelled: %d, arms "
                    "held: %d); nobody else's", principal.name, on_its_way, ended, len(goals),
                    len(arms.held),
                    extra={"principal": principal.name})
        self._base.cancel_goals(goals, principal, why="cancelled by its client")
        applied = {"scope": "own", "cancelled_by_client": True, "on_its_way": on_its_way,
                   "stream_ended": stream.message_id if ended and stream else None,
                   "goals_cancelled": [g.goal_id for g in goals], **_arms_applied(arms)}
        # Detached: the cancelled caller's task may be cancelled again; the entry must not be.
        return ClientCancel(ids, self._after(
            withdrawn, self._detached(self._own_stop_recorded(principal, applied))))

    def _after(self, withdrawn: list[asyncio.Future[Decision]],
               stopped: asyncio.Future[Decision | None] | asyncio.Future[Decision]
               ) -> Awaitable[Decision | None]:
        """`stopped`, done once the withdrawals are on record too."""
        if not withdrawn:
            return stopped
        return self._steps.spawn(_gathered_then(withdrawn, stopped))

    async def withdraw_all_held(self) -> None:
        """The bridge is stopping: every command held for a human — motion or not, anyone's
        — is withdrawn (HITL_WITHDRAWN by its issuer, `BRIDGE_STOPPING`), its entry awaited.
        Held commands live in memory alone: left for the process to end with, each would
        stay a PENDING_AUTH with no end in the log, and nobody would tell its issuer. The
        run's stop path calls this before the API closes, while issuers may still be told
        (a held INVOKE's INVOKE_RESULT, the approvals frames, their pending records); `stop`
        again before BRIDGE_STOPPED, for any held since. One past its TTL that no sweep has
        expired yet is expired first (HITL_EXPIRED): `withdrawing` leaves it to the sweeper,
        which `stop` ends."""
        if not self._stopped:  # BRIDGE_STOPPED is the last entry
            await self._desk.expire()
        withdrawing = self._withdraw_held(None, BRIDGE_STOPPING, which=_any,
                                          what="every command")
        await asyncio.gather(*withdrawing.values(), return_exceptions=True)

    def _withdraw_held(self, issuer: Principal | None, reason: str, *,
                       which: Callable[[NormalizedCommand], bool] = _is_motion,
                       what: str = "motion") -> dict[str, asyncio.Future[Decision]]:
        """Withdraws the motion held for a human of `issuer` (None: of everyone) that a stop
        of it came for (`which` picks other commands: all it held, the bridge stopping; the
        clears an e-stop came after), in this step:
        each as its issuer would withdraw it (HITL_WITHDRAWN,
        `reason` saying the stop; its issuer reads that in its pending record, approvers see
        it leave the list). From this step on no approval of it counts
        (`HitlDesk.withdrawing`); its entry follows once the desk has it. Held commands that
        are not motion, and others' when `issuer` is named, stay. By pending id, what to
        await for each entry.

        Why: such a stop is one for all motion of `issuer`'s (or all motion) decided before it,
        held motion included; approved later it would start motion for a client that cancelled
        it or is gone, or restart what a stop of the robot was for (`_run_approved` still
        refuses held motion approved after a stop of the robot, should a withdrawal miss it:
        the backstop)."""
        if self._stopped:  # BRIDGE_STOPPED is the last entry
            return {}
        picked = self._desk.withdrawing(issuer.name if issuer else None, which)
        return self._withdrawing(picked, reason, what, issuer)

    def _withdrawing(self, picked: list[PendingCommand], reason: str, what: str,
                     issuer: Principal | None = None) -> dict[str, asyncio.Future[Decision]]:
        """Each of `picked` (marked `withdrawing` by the desk) withdrawn as its issuer would,
        with `reason`; by pending id, what to await for each entry."""
        if picked:
            log.warning("%s held for approval is withdrawn (%s): %s", what, reason,
                        ", ".join(f"{p.pending_id} of '{p.issuer.name}'" for p in picked),
                        extra={"principal": issuer.name} if issuer else None)
        return {p.pending_id: self._detached(self._desk.resolve(p.pending_id, p.issuer,
                                                                "withdraw", reason))
                for p in picked}

    async def withdraw_for_ended_credentials(self) -> None:
        """Every held command whose issuer's credential (the one it was held with: a JWT's
        `exp` plus the leeway, a client certificate's notAfter) has run out is withdrawn
        (HITL_WITHDRAWN by its issuer, `CREDENTIAL_EXPIRED`), its entry awaited. Over a
        WebSocket its connection closes then and withdraws its motion; over REST nothing else
        would end it, and approved it would run for a principal that no longer holds any
        credential the bridge accepts (red team 30). An approval that comes before this does
        the same and is refused (`HitlDesk`)."""
        if self._stopped:  # BRIDGE_STOPPED is the last entry
            return
        withdrawing = self._withdrawing(self._desk.credentials_ended(), CREDENTIAL_EXPIRED,
                                        "a command")
        for done in await asyncio.gather(*withdrawing.values(), return_exceptions=True):
            if isinstance(done, Exception):  # (the rest of the sweep goes on)
                log.error("a held command whose issuer's credential expired was not "
                          "withdrawn: %s", done)

    def _robot_stopped(self, cause: str) -> None:
        """A stop of the robot in this step (`VelocityStreams.halt`: a `stop`, an e-stop
        latching, a session loss's halt): every held motion command is withdrawn
        (`ROBOT_STOPPED`), nobody's motion held after it is touched."""
        self._withdraw_held(None, ROBOT_STOPPED.format(cause))

    async def sweep(self) -> None:
        """One round of housekeeping: expire HiTL requests, stop for lost sessions, record
        e-stop repeats that waited long enough, withdraw held commands whose issuer's
        credential ran out. And read the wall clock into its latest time: what expired before
        a step back stays expired (JWTs, the replay window, held commands' credentials), even
        when nothing was checked between its expiry and the step."""
        latest_wall(self._clock).time()
        await self.expire_pending()
        if self._estops.repeats_due():  # in order with the latch's transitions
            await self.latch.then(self._estops.record_repeats)
        lost = self._sessions.take_lost()
        # Concurrently: one slow halt (say, a goal server that never answers) must not
        # delay the next principal's, nor the next sweep.
        await asyncio.gather(*(
            self._steps.spawn(self.safe_stop(p, f"no command or heartbeat for {allowed:g} s"))
            for p, allowed in lost))
        # Last: no stop waits for it (an approval meanwhile is refused by the desk itself).
        await self.withdraw_for_ended_credentials()

    async def _sweep_forever(self) -> None:
        while True:
            await asyncio.sleep(SWEEP_INTERVAL_S)
            try:
                await self.sweep()
            except Exception:
                log.exception("governance sweep failed")

    def _detached(self, decision: Coroutine[Any, Any, Decision], *,
                  then: Callable[[], object] | None = None) -> asyncio.Future[Decision]:
        """`decision` in a task of its own, and a future of its outcome to await: a caller that
        is cancelled cancels only that future, never the decision (like `shield(task)`, but the
        task resolves the future itself: no shield callbacks, two loop turns fewer a command).
        `then` is called once the task is done, even if it never ran."""
        outcome: asyncio.Future[Decision] = asyncio.get_running_loop().create_future()
        task = asyncio.ensure_future(_resolve_into(decision, outcome))
        self._tasks.add(task)
        task.add_done_callback(functools.partial(_settled, self._tasks, decision, outcome,
                                                 then))
        return outcome


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
             outcome: asyncio.Future[Decision], then: Callable[[], object] | None,
             task: asyncio.Task[None]) -> None:
    running.discard(task)
    if then is not None:
        then()
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


def _resolved(value: Decision | None) -> asyncio.Future[Decision | None]:
    """A future already done, of `value`."""
    done: asyncio.Future[Decision | None] = asyncio.get_running_loop().create_future()
    done.set_result(value)
    return done


async def _awaited(future: asyncio.Future[Any]) -> Any:
    return await future


async def _gathered_then(first: list[asyncio.Future[Decision]],
                         then: Awaitable[Decision | None]) -> Decision | None:
    """`then`'s outcome, once `first` are done too (their outcomes are on record)."""
    await asyncio.gather(*first, return_exceptions=True)
    return await then


def _fingerprint(command: NormalizedCommand) -> bytes:
    """What makes a retry the same command: action, parameters and target robot."""
    return msgspec.json.encode({"action": command.action, "params": command.requested,
                                "ruri": command.ruri}, order="sorted")


def _arms_applied(arms: ArmsHeld) -> dict[str, list[str]]:
    """What an own stop's entry says of the arms (nothing when none was running)."""
    facts = {"arms_held": list(arms.held)} if arms.held else {}
    if arms.at_desired:  # held where their trajectories had them: joint_states late
        facts["arms_held_at_desired"] = list(arms.at_desired)
    if arms.not_held:
        facts["arms_not_held"] = list(arms.not_held)
    return facts


def _write_start_point(path: Path, pubkey: Ed25519PublicKey, sign: Callable[[bytes], bytes],
                       cp: Checkpoint) -> None:
    """The replay's state at an audit checkpoint, for the next start to replay from
    (`governance.resume`): imported here, on the log's checkpoint-hook thread, as the start
    let go of it (`rcan_rtps._modules.START_ONLY`)."""
    from .resume import write_point

    try:
        write_point(path, cp, pubkey, sign)
    except (OSError, ValueError) as exc:  # (a full disk; a log cut or altered by another)
        # One line, no traceback: the next start replays from the previous point or the
        # boundary (the same result, only slower), and this is said at each checkpoint.
        log.error("audit start point not written (%s): the next start replays further back",
                  exc)


def _is_trajectory(command: NormalizedCommand) -> bool:
    """Whether `command` sends an arm's trajectory (it runs on in its controller: its entry
    is stamped with the boot clock, for a restart after a crash to take it back)."""
    ros = command.spec.ros
    return isinstance(ros, Publish) and ros.hold is not None
