"""The steps every part of the kernel takes the same way: write ahead, send, refuse.

The governor is the pipeline (decide → write ahead → execute); the e-stop lane, the base arbiter
and the HiTL desk are modules of their own. They all audit, reach the robot and answer through
one `Steps`, so an entry, a send and a refusal mean the same thing wherever they happen.
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import uuid
from collections.abc import Awaitable, Collection, Coroutine, Sequence
from typing import Any, NamedTuple, Protocol

import msgspec

from rcan_rtps.rcan import ActionParams, DecisionBody, Effect, ErrorCode, NormalizedCommand, Outcome
from rcan_rtps.rcan.actions import MoveParams, with_effect

from .audit import AuditEvent, AuditLog, AuditReceipt, AuditRecord
from .clock import BootInstant
from .errors import AuditError
from .left import LeftGoal, LeftRunning
from .outcomes import (
    AUDIT_UNAVAILABLE,
    DISPATCH_ERROR,
    Rejection,
    robot_unavailable,
)
from .rbac import Principal

log = logging.getLogger("rcan_rtps.governance.governor")  # one logger for the kernel's steps


class DispatchResult(msgspec.Struct, frozen=True, kw_only=True):
    """What the bridge reports after handing a command to ROS 2."""

    ok: bool
    ros2_topic: str | None = None
    # The goal started; on a failure, one its server may run all the same (its send gave up
    # after the request went out, or it was accepted and is being cancelled): the command's
    # COMMAND_FAILED names it, for a crash's restart to cancel (`resume`).
    goal_id: str | None = None
    detail: str | None = None
    # What was sent runs on after this, for up to so many seconds (an arm's trajectory): a
    # stop of its sender's motion alone holds it (`Dispatcher.hold_trajectories`), and while
    # it runs its sender drives.
    runs_for_s: float | None = None


class ArmsHeld(NamedTuple):
    """What a stop did to the arms: the topics held, the arms that could not be (why), and of
    the topics held those held where their trajectory had the arm rather than where it was
    measured (its joint_states late)."""

    held: tuple[str, ...] = ()
    not_held: tuple[str, ...] = ()
    at_desired: tuple[str, ...] = ()


class LeftHalted(NamedTuple):
    """What a start did to the motion a crashed run left (`Dispatcher.halt_left`)."""

    zero_reached: bool  # the zero velocity reached a reader of the velocity topic
    goals_cancelled: tuple[str, ...] = ()  # their ids (a goal with none: its server, all)
    goals_not_cancelled: tuple[str, ...] = ()  # why, for each
    arms: ArmsHeld = ArmsHeld()
    # The message ids of what may still run: arms not held, goals no server answered for.
    still_left: tuple[str, ...] = ()


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

    def hold_trajectories(self, message_ids: Collection[str]) -> ArmsHeld:
        """Hold what the commands `message_ids` sent that still runs on (`runs_for_s`), now
        (no await); a stop of the whole robot holds every one itself."""
        ...

    def running_trajectories(self) -> Collection[str]:
        """The message ids of the commands whose motion may still run on (`runs_for_s`)."""
        ...

    def goals_watched(self) -> list[LeftGoal]:
        """The goals whose send gave up that their server may still accept or run (watched
        for their late acceptance, not seen ended or canceling): BRIDGE_STOPPED names them,
        for the next start to cancel."""
        ...

    async def halt_left(self, left: LeftRunning) -> LeftHalted:
        """Takes back the motion a crashed run left (a start's first act): zero velocity, each
        goal cancelled by its id (one with no id known: every goal of its server), each arm
        still due held where joint_states says it is (never at a guess: an arm whose
        joints are not heard within the start-up wait is reported, not held)."""
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
    runs_for_s: float | None = None  # what it sent runs on so long (`DispatchResult`)

    def body(self) -> DecisionBody:
        return DecisionBody(
            outcome=self.outcome.value,
            audit_id=self.audit_id, message_id=self.message_id,
            error_code=self.error_code.value if self.error_code else None, reason=self.reason,
            applied=self.applied, pending_id=self.pending_id, expires_at_ms=self.expires_at_ms,
            goal_id=self.goal_id, ros2_topic=self.ros2_topic, warnings=self.warnings,
        )


Sent = tuple[DispatchResult, Rejection | None]


class Steps:
    """Audit, robot and background tasks, as every part of the kernel uses them."""

    def __init__(self, audit: AuditLog, dispatcher: Dispatcher) -> None:
        self.audit = audit
        self.dispatcher = dispatcher
        self.tasks: set[asyncio.Task[Any]] = set()

    async def write_ahead(self, record: AuditRecord, *, urgent: bool = False
                          ) -> AuditReceipt | None:
        """The decision entry, durable; None if it cannot be written (then nothing is sent).
        `urgent`: a stop's, whose group commit waits for no more entries."""
        try:
            return await self.audit.append(record, urgent=urgent)
        except AuditError:
            log.exception("audit write failed: %s not sent", record.action_type,
                          extra={"principal": record.principal})
            return None

    def stop(self, entry: AuditRecord, *signals: Coroutine[Any, Any, Any]
             ) -> Coroutine[Any, Any, tuple[list[Any], AuditReceipt | None]]:
        """A stop's signals and its entry (a stop, an e-stop, a safe stop), both under way
        when this returns — called in the same step as the halt or the latch, no await
        between them:

        - each of `signals` (the robot told, a latch file written) gets its task first, so
          its first step (the publish) runs before anything this stop writes to disk;
        - then `entry` is sealed: its place in the chain is where the stop took effect, so
          no entry sealed after the halt (a move decided just after it) comes before it;
        - it is made durable beside the signals, never before them: stopping does not wait
          for the disk, and is never held back by it (unwritable: logged, receipt None).

        Awaiting the result gives what each signal returned or raised, and the receipt."""
        started = [asyncio.ensure_future(signal) for signal in signals]
        try:
            durable: Awaitable[AuditReceipt] = self.audit.seal(entry, urgent=True)
        except AuditError as exc:
            durable = _failed(exc)
        return _stopped(entry, started, durable)

    async def record_event(self, record: AuditRecord) -> None:
        """An entry about something that already happened (nothing waits on it)."""
        await _recorded(record, self.audit.append(record))

    def record_now(self, record: AuditRecord) -> None:
        """An entry about something that happened in this step (a stream's zero went out),
        sealed now — its place in the chain is this step: a stop's halt lists the stream it
        ended before the stop's own entry, where the robot got its zero — and made durable in
        a task of its own (the bridge's stop waits for it; nobody else does)."""
        try:
            durable = self.audit.seal(record)
        except AuditError:
            log.exception("audit write failed: %s not recorded", record.event.value)
            return
        self.spawn(_recorded(record, durable))

    def route(self, command: NormalizedCommand) -> str | None:
        try:
            return self.dispatcher.route(command)
        except Exception:  # only the audit entry's ros2_topic is missing then
            log.exception("no route for %s", command.action)
            return None

    async def ready(self, command: NormalizedCommand) -> str | None:
        try:
            return await self.dispatcher.ready(command)
        except Exception as exc:  # a broken readiness check counts as "not ready"
            log.exception("readiness check for %s failed", command.action)
            return f"readiness check failed: {exc!r}"

    def hold_trajectories(self, message_ids: Collection[str]) -> ArmsHeld:
        if not message_ids:
            return ArmsHeld()
        try:
            return self.dispatcher.hold_trajectories(message_ids)
        except Exception as exc:  # reported with the stop, never raised into it
            log.exception("holding the arms failed")
            return ArmsHeld(not_held=(f"holding the arms failed: {exc!r}",))

    def goals_watched(self) -> list[LeftGoal]:
        try:
            return self.dispatcher.goals_watched()
        except Exception:  # the stop is recorded all the same
            log.exception("reading the goals watched for late acceptance failed")
            return []

    def running_trajectories(self) -> Collection[str] | None:
        """None: not known (count every one as running: fail closed)."""
        try:
            return self.dispatcher.running_trajectories()
        except Exception:
            log.exception("reading the running trajectories failed")
            return None

    async def dispatch(self, command: NormalizedCommand, applied: ActionParams | None = None
                       ) -> Sent:
        try:
            result = await self.dispatcher.dispatch(
                command, command.params if applied is None else applied)
        except Exception as exc:  # a bridge fault is an outcome (failed), never a crash
            log.exception("dispatch of %s failed", command.action)
            return DispatchResult(ok=False, detail=repr(exc)), DISPATCH_ERROR
        if result.ok:
            return result, None
        return result, robot_unavailable(result.detail)

    async def failed(self, command: NormalizedCommand, principal: Principal,
                     rejection: Rejection, *, goal_id: str | None = None) -> Decision:
        """After a write-ahead entry: the send did not happen or failed (COMMAND_FAILED);
        `goal_id`: a goal of it that may run all the same (`DispatchResult.goal_id`)."""
        return await self.refuse(command, principal, rejection, event=AuditEvent.COMMAND_FAILED,
                                 goal_id=goal_id)

    async def refuse(self, command: NormalizedCommand, principal: Principal,
                     rejection: Rejection, *, event: AuditEvent = AuditEvent.COMMAND_REJECTED,
                     pending_id: str | None = None, goal_id: str | None = None,
                     ) -> Decision:
        entry = record(event, command, principal, rejection.outcome, rejection=rejection,
                       pending_id=pending_id, goal_id=goal_id)
        receipt = await self.write_ahead(entry)
        if receipt is None:
            return decision(AUDIT_UNAVAILABLE, message_id=command.message_id)
        return decision(rejection, receipt, message_id=command.message_id)

    def spawn(self, coro: Coroutine[Any, Any, Any]) -> asyncio.Task[Any]:
        """A task the governor waits for before BRIDGE_STOPPED."""
        task = asyncio.ensure_future(coro)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)
        return task


async def _failed(exc: AuditError) -> AuditReceipt:
    """A stop's entry that could not even be sealed (the log is unwritable): its failure,
    beside the signals that go out anyway."""
    raise exc


async def _recorded(record: AuditRecord, durable: Awaitable[AuditReceipt]) -> None:
    """`durable` awaited; a failure logged (nobody waits on the entry)."""
    try:
        await durable
    except AuditError:
        log.exception("audit write failed: %s not recorded", record.event.value)


async def _stopped(entry: AuditRecord, signals: Sequence[asyncio.Future[Any]],
                   durable: Awaitable[AuditReceipt]) -> tuple[list[Any], AuditReceipt | None]:
    """`Steps.stop`'s signals and entry, done: what each signal returned or raised, and the
    entry's receipt (None: it could not be written; the signals went anyway)."""
    *sent, receipt = await asyncio.gather(*signals, durable, return_exceptions=True)
    if isinstance(receipt, AuditError):
        log.error("audit write failed: the %s went out unaudited (%s)", entry.action_type,
                  receipt, extra={"principal": entry.principal})
        return sent, None
    if isinstance(receipt, BaseException):
        raise receipt
    return sent, receipt


def record(event: AuditEvent, command: NormalizedCommand, principal: Principal,
           outcome: Outcome, *, applied: dict[str, Any] | None = None,
           rejection: Rejection | None = None, ros2_topic: str | None = None,
           pending_id: str | None = None, sent_first: bool | None = None,
           goal_id: str | None = None, boot: BootInstant | None = None) -> AuditRecord:
    """The audit entry of `command`'s decision (its goal's id, when one was chosen for it;
    a failure's names `goal_id`, a goal that may run all the same; `boot`: an arm
    trajectory's, the boot clock as it is written)."""
    return AuditRecord(
        event=event, principal=principal.name, role=principal.role.name,
        message_id=command.message_id, action_type=command.action, params=command.requested,
        applied=applied, outcome=outcome.value,
        deny_reason=rejection.deny_reason if rejection else None, ai=ai_facts(command),
        ros2_topic=ros2_topic, pending_id=pending_id,
        warnings=list(command.warnings) or None, sent_first=sent_first,
        # A held command's reviews (who approved, denied or withdrew it, and why).
        approvals=[msgspec.to_builtins(a) for a in command.approvals] or None,
        rcan=command.envelope.audit_facts() if command.envelope is not None else None,
        goal_id=command.goal_id if outcome is Outcome.EXECUTED else goal_id,
        boot=None if boot is None else {"boot_id": boot.boot_id, "ms": boot.ms},
    )


def ai_facts(command: NormalizedCommand) -> dict[str, Any] | None:
    """A command's AI fields as its entry records them: the reasoning by its digest only (the
    audit is readable below the config scope the reasoning itself needs, §16.5)."""
    if command.ai is None:
        return None
    facts = msgspec.structs.asdict(command.ai)
    if facts["client"] is None:  # recorded where there is one: older entries stay as they were
        del facts["client"]
    reasoning = facts.pop("reasoning")
    if reasoning is not None:
        facts["reasoning_sha256"] = hashlib.sha256(reasoning.encode()).hexdigest()
    return facts


def sent(outcome: Sent | BaseException) -> Sent:
    """A dispatch's result out of `gather(..., return_exceptions=True)`."""
    if isinstance(outcome, BaseException):  # `dispatch` catches Exception: this is worse
        raise outcome
    return outcome


def bridge_command(effect: Effect) -> NormalizedCommand:
    """A command the bridge issues itself (a safe stop, an e-stop re-published at start)."""
    spec = with_effect(effect)
    return NormalizedCommand(action=spec.name, params=spec.params(), requested={},
                             message_id=str(uuid.uuid4()))


def executed(command: NormalizedCommand, applied: dict[str, Any], receipt: AuditReceipt,
             result: DispatchResult) -> Decision:
    return Decision(outcome=Outcome.EXECUTED, http_status=200, applied=applied,
                    audit_id=receipt.audit_id, message_id=command.message_id,
                    ros2_topic=result.ros2_topic, goal_id=result.goal_id,
                    runs_for_s=result.runs_for_s)


def decision(rejection: Rejection, receipt: AuditReceipt | None = None, *,
             message_id: str | None = None) -> Decision:
    return Decision(outcome=rejection.outcome, http_status=rejection.http_status,
                    error_code=rejection.error_code, reason=rejection.reason,
                    audit_id=receipt.audit_id if receipt else None, message_id=message_id)


def refused_event(event: AuditEvent) -> AuditEvent:
    """The event of a refusal: an approval's own (HITL_AUTHORIZED), else COMMAND_REJECTED."""
    return AuditEvent.COMMAND_REJECTED if event is AuditEvent.COMMAND_DISPATCHED else event
