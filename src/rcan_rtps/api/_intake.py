"""One COMMAND body in, one decision out: the part every transport shares, and the e-stop lane.

A transport (REST, the WebSocket, a future MCP server or web console) does three things:

    item = intake(raw, limit)          # validate now: cheap (msgspec, no I/O), never raises
    if item.stopping:                  # a valid `stop` / `estop`
        await lane.submit(item)        # decided at once, beside whatever the transport queues
    else:
        ... its own queue or flow ... reply = await decide(governor, principal, item)

Validating first is what lets a stop skip the queue honestly: only a body that *is* a valid
`stop`/`estop` gets the lane, so a flood of junk that merely mentions "estop" still waits its
turn (and meets the transport's bound). The lane never refuses: when `width` stops of one
connection are already being decided, `submit` waits for one to finish — backpressure on that
connection's reader, not a 429. An e-stop latches synchronously inside the governor, so a
second one behind the first loses nothing.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from contextlib import AbstractContextManager
from typing import Any, NamedTuple

import msgspec

from rcan_rtps.governance import Governor, Principal, Rejection, outcomes
from rcan_rtps.governance.clock import SystemClock, now_ms
from rcan_rtps.governance.replay import ReplayWindow
from rcan_rtps.governance.signatures import Signatures
from rcan_rtps.rcan import (
    STATUS_OF,
    Authorization,
    DecisionBody,
    Envelope,
    ErrorCode,
    Heartbeat,
    InvalidRuriError,
    Invoke,
    InvokeCancel,
    NormalizedCommand,
    Outcome,
    SchemaValidationError,
    VersionIncompatibleError,
    reply_id,
    validate_message,
)

from ._bodies import HeartbeatReply, error_body, failure_reply
from ._skills import NO_SKILLS, Skills

log = logging.getLogger(__name__)

Reply = tuple[int, Any]
Deliver = Callable[[Reply], Awaitable[None]]
Observe = Callable[[float], None]
# Calls its argument, within the block, if the request's client hangs up
# (`ConnectionDeadlines.hung_up`, bound to a request).
HangUp = Callable[[Callable[[], None]], AbstractContextManager[None]]
CLIENT_CLOSED = 499  # the status of a request whose client hung up before its answer (nginx's)

TOO_DEEP = "JSON is nested too deeply"
# How many times `max_body_bytes` a transport holds of a body: a larger one is read only to
# find a stop in it (a stop always stops), the rest get 413. REST and `/mcp` read one larger
# still on to its end through its skeleton (`_skim`, held to this room); the WebSocket, whose
# frames aiohttp assembles whole, refuses a frame larger than this.
STOP_ROOM = 4
# A bug in validation must not take a transport down: it is answered (and audited) like this.
_INTERNAL = Rejection(503, Outcome.FAILED, ErrorCode.ROBOT_UNAVAILABLE, "internal_error")
_WALL = SystemClock()


class Checks(msgspec.Struct, frozen=True):
    """What every transport checks of a message beyond its schema: signatures (per principal)
    and the §8.3 replay window."""

    replay: ReplayWindow | None = None
    signatures: Signatures | None = None


NO_CHECKS = Checks()


class Intake(msgspec.Struct, frozen=True):
    """A validated command, HEARTBEAT, INVOKE, INVOKE_CANCEL or AUTHORIZE, or the pre-command
    refusal its body earned (with schema detail, and the message's id where an RCAN 3.x reply
    needs it)."""

    command: NormalizedCommand | None = None
    heartbeat: Heartbeat | None = None
    message3: Invoke | InvokeCancel | Authorization | None = None
    refusal: Rejection | None = None
    detail: str | None = None
    msg_id: str | None = None
    rcan: dict[str, Any] | None = None  # a refused RCAN 3.x message's envelope facts (audit)
    refused_id: str | None = None  # a refused 1.2 form's own message_id (audit only)

    @property
    def stopping(self) -> bool:
        """A valid `stop` or `estop`: the kind no queue may hold back."""
        return self.command is not None and self.command.spec.stopping

    @property
    def message_id(self) -> str | None:
        return None if self.command is None else self.command.message_id


def intake(raw: bytes, limit: int, checks: Checks = NO_CHECKS,
           principal: str | None = None, *, skimmed: Skimmed | None = None) -> Intake:
    """Size check, `validate_message`, then the sender's signature policy and the replay
    window; every failure becomes a refusal, never a raise. A stop that fails the last two is
    still that stop, with a warning for each failure. `skimmed`: `raw` is the skeleton of a
    larger body (`_commands.read_command`), taken only if it says stop."""
    if skimmed is not None or len(raw) > limit:
        return _oversize(raw, limit, checks, principal, skimmed)
    try:
        message = validate_message(raw)
    except RecursionError:  # msgspec gives up on deep nesting with this, not a DecodeError
        return Intake(refusal=outcomes.schema_failed("$"), detail=TOO_DEEP)
    except SchemaValidationError as exc:
        return Intake(refusal=outcomes.schema_failed(exc.path), detail=exc.detail,
                      msg_id=reply_id(raw))
    except InvalidRuriError as exc:
        return Intake(refusal=outcomes.invalid_ruri(exc.rule), msg_id=reply_id(raw))
    except VersionIncompatibleError as exc:
        return Intake(refusal=outcomes.version_incompatible(exc.rule), msg_id=exc.msg_id)
    except Exception:
        log.exception("validating a command body failed unexpectedly")
        return Intake(refusal=_INTERNAL)
    if isinstance(message, Heartbeat):  # not a command: no signature policy
        refusal = _replay_refusal(message, checks.replay, principal)
        if refusal is None:
            return Intake(heartbeat=message)
        assert message.envelope is not None  # only envelopes are checked
        return Intake(refusal=refusal, msg_id=message.envelope.msg_id)
    if not isinstance(message, NormalizedCommand):
        return _checked_message3(message, checks, principal)
    return _checked(message, checks, principal)


def _oversize(raw: bytes, limit: int, checks: Checks, principal: str | None,
              skimmed: Skimmed | None) -> Intake:
    """A body over the size limit: refused 413, unless it says stop — a stop always stops,
    its size a warning. Read first without the checks: an oversize message that is no stop
    does not use up its msg_id."""
    if not intake(raw, len(raw)).stopping:
        return Intake(refusal=outcomes.PAYLOAD_TOO_LARGE)
    return with_warnings(intake(raw, len(raw), checks, principal),
                         (oversize_warning(raw, limit, skimmed),))


class Skimmed(NamedTuple):
    """What a skeleton stands for (`_commands.read_command`)."""

    size: int  # the body's, as sent
    shortened: int  # strings cut


def oversize_warning(raw: bytes, limit: int, skimmed: Skimmed | None = None) -> str:
    """What a stop over the size limit carries: it stopped all the same. `skimmed`: `raw` is
    the skeleton of a body that size."""
    size, shortened = (len(raw), 0) if skimmed is None else skimmed
    cut = f" ({shortened} of its strings kept only in part)" if shortened else ""
    return f"$: {size} bytes, over the {limit} taken{cut}: stopped all the same"


def _checked_message3(message: Invoke | InvokeCancel | Authorization, checks: Checks,
                      principal: str | None) -> Intake:
    """INVOKE, INVOKE_CANCEL, AUTHORIZE: the sender's signature policy, then the replay
    window. INVOKE and INVOKE_CANCEL cannot be signed: under `required` they are refused, so
    no command escapes the policy through a skill. An AUTHORIZE can (the SDK's envelope):
    under `required` an approval must be, a denial need not (`Signatures.check_review`)."""
    refusal = None
    if checks.signatures is not None and principal is not None:
        if isinstance(message, Authorization):
            refusal, envelope = checks.signatures.check_review(
                principal, message.verdict == "approve", message.envelope)
            if envelope is not None and envelope is not message.envelope:
                message = msgspec.structs.replace(message, envelope=envelope)
        else:
            refusal, _ = checks.signatures.check(principal, message.envelope)
    if refusal is None:
        refusal = _replay_refusal(message, checks.replay, principal)
    if refusal is None:
        return Intake(message3=message)
    envelope = message.envelope
    return Intake(refusal=refusal, msg_id=envelope.msg_id, rcan=envelope.audit_facts())


def _checked(command: NormalizedCommand, checks: Checks, principal: str | None) -> Intake:
    refusals: list[Rejection] = []
    if checks.signatures is not None and principal is not None:
        refusal, envelope = checks.signatures.check(principal, command.envelope)
        if envelope is not command.envelope:
            command = msgspec.structs.replace(command, envelope=envelope)
        if refusal is not None:
            refusals.append(refusal)
    # A message refused for its signature does not use up its msg_id (a stop goes on anyway).
    if not refusals or command.spec.stopping:
        refusal = _replay_refusal(command, checks.replay, principal)
        if refusal is not None:
            refusals.append(refusal)
    if not refusals:
        return Intake(command=command)
    if command.spec.stopping:
        warnings = [f"{r.deny_reason}: stopped all the same (a stop always stops)"
                    for r in refusals]
        return Intake(command=msgspec.structs.replace(
            command, warnings=(*command.warnings, *warnings)))
    envelope = command.envelope
    if envelope is None:  # a 1.2 form refused by a `required` policy
        own_id = command.message_id if command.client_message_id else None
        return Intake(refusal=refusals[0], refused_id=own_id)
    return Intake(refusal=refusals[0], msg_id=envelope.msg_id, rcan=envelope.audit_facts())


def with_warnings(item: Intake, warnings: tuple[str, ...]) -> Intake:
    """A stop's intake with what its transport found wrong before the body (a JSON-RPC
    envelope read leniently, say) as its first warnings; any other intake as it is."""
    if not warnings or item.command is None or not item.command.spec.stopping:
        return item
    return Intake(command=msgspec.structs.replace(
        item.command, warnings=(*warnings, *item.command.warnings)))


def _replay_refusal(message: NormalizedCommand | Heartbeat | Invoke | InvokeCancel
                    | Authorization, window: ReplayWindow | None,
                    principal: str | None) -> Rejection | None:
    envelope = message.envelope
    if window is None or envelope is None or not envelope.replay_checked:
        return None
    return window.check(envelope.msg_id, envelope.sent_at_s, safety=envelope.safety,
                        sender=principal or "")


def give_back_id(item: Intake, checks: Checks, principal: str) -> None:
    """The replay window forgets the id of a message refused before anything was done with
    it (a full queue's 429): the client's retry of it is the same message, not a replay."""
    message = item.command or item.heartbeat or item.message3
    envelope = None if message is None else message.envelope
    if checks.replay is not None and envelope is not None and envelope.replay_checked:
        checks.replay.release(envelope.msg_id, principal)


async def decide(governor: Governor, principal: Principal, item: Intake,
                 observe: Observe | None = None,
                 invocations: Skills | None = None, hung_up: HangUp | None = None) -> Reply:
    """The decision for one intake; pre-command refusals are audited for the principal. An
    INVOKE of a goal is answered when the goal ends (`_invoke`); with `hung_up`, an INVOKE
    whose client hangs up before that is answered to nobody (`CLIENT_CLOSED`) and its
    motion stopped (`_invoke`: nobody is left to answer for it)."""
    started = time.perf_counter()
    try:
        if item.heartbeat is not None:
            return 200, heartbeat(governor, principal, item.heartbeat)
        if item.message3 is not None:
            return await _message3(governor, principal, item.message3,
                                   invocations or NO_SKILLS, hung_up)
        if item.command is not None:
            decision = await governor.decide(item.command, principal)
            return decision.http_status, replied(decision.body(), item.command.envelope)
        assert item.refusal is not None
        decision = await governor.reject_request(principal, item.refusal, rcan=item.rcan,
                                                 message_id=item.msg_id or item.refused_id)
        if item.refusal.error_code is not ErrorCode.SCHEMA_VALIDATION_FAILED:
            refused = decision.body()
            if item.msg_id is not None:
                refused.msg_id, refused.status = item.msg_id, STATUS_OF[refused.outcome]
            return decision.http_status, refused
        # Schema failures also say what was wrong where (the reason is the field path).
        body = error_body(ErrorCode.SCHEMA_VALIDATION_FAILED, reason=item.detail,
                          path=item.refusal.reason, audit_id=decision.audit_id)
        if item.msg_id is not None:
            body.msg_id, body.status = item.msg_id, STATUS_OF[body.outcome]
        return decision.http_status, body
    finally:
        if observe is not None:
            observe(time.perf_counter() - started)


async def _message3(governor: Governor, principal: Principal,
                    message: Invoke | InvokeCancel | Authorization,
                    skills: Skills, hung_up: HangUp | None) -> Reply:
    if isinstance(message, Authorization):
        from ._invoke import authorize  # with the INVOKEs: see `_skills`

        return await authorize(governor, principal, message)
    if isinstance(message, InvokeCancel):
        return await skills.invocations().cancel(governor, principal, message)
    started = await skills.invocations().start(governor, principal, message)
    if started.reply is not None:
        if started.finish is not None:  # held: answered as its hold ends, in the log alone
            started.finish().add_done_callback(_answered_unheard)
        return started.reply
    assert started.finish is not None
    if hung_up is None:
        return await started.finish()
    return await _unless_hung_up(started.finish(), hung_up)


async def _unless_hung_up(finish: Awaitable[Reply], hung_up: HangUp) -> Reply:
    """An INVOKE's answer, given up if its client hangs up first (a server that lets its
    handler run on after that tells no one): its wait is cancelled, which stops its motion."""
    answering = asyncio.ensure_future(finish)
    left = False

    def leave() -> None:
        nonlocal left
        left = True
        answering.cancel()

    with hung_up(leave):
        try:
            return await answering
        except asyncio.CancelledError:
            if not left:  # this handler itself was cancelled: so is `answering`
                raise
    return CLIENT_CLOSED, error_body("CLIENT_CLOSED", reason="client_hung_up", outcome="failed")


def _answered_unheard(answer: asyncio.Future[Reply]) -> None:
    """A held INVOKE's answer, which its REST client (answered 202) does not wait for: a
    failure to make it is logged, as nobody else would see it."""
    if not answer.cancelled() and (error := answer.exception()) is not None:
        log.error("answering a held INVOKE failed", exc_info=error)


def replied(body: DecisionBody, envelope: Envelope | None) -> DecisionBody:
    """A decision's body; for a message of the RCAN 3.x generation also its id and status."""
    if envelope is not None:
        body.msg_id = envelope.msg_id or body.message_id
        body.status = STATUS_OF[body.outcome]
    return body


def heartbeat(governor: Governor, principal: Principal, beat: Heartbeat) -> HeartbeatReply:
    """A HEARTBEAT keeps its sender's control session alive; it is not audited."""
    governor.heartbeat(principal)
    return HeartbeatReply(ok=True, principal=principal.name, timestamp_ms=now_ms(_WALL),
                          msg_id=beat.message_id, status="ok")


async def decide_safely(governor: Governor, principal: Principal, item: Intake,
                        observe: Observe | None = None,
                        invocations: Skills | None = None) -> Reply:
    """`decide` for transports without a last-resort middleware: an exception is an answer
    (503, as REST gives), never the end of the connection's command handling."""
    try:
        return await decide(governor, principal, item, observe, invocations)
    except Exception as exc:
        log.exception("deciding a command of %s failed", principal.name,
                      extra={"principal": principal.name})
        return failure_reply(exc)


class StopLane:
    """`stop`/`estop` of one connection (and, on the WebSocket, INVOKE_CANCEL: the stop of one
    skill's motion), decided the moment they arrive, concurrently with (and never behind) the
    connection's other commands. Their replies may overtake earlier commands' replies; each
    carries its `message_id` (an INVOKE_CANCEL's INVOKE_RESULT, its `reply_to`)."""

    def __init__(self, governor: Governor, principal: Principal, deliver: Deliver, *,
                 observe: Observe | None = None, width: int = 4,
                 invocations: Skills | None = None) -> None:
        self._governor = governor
        self._principal = principal
        self._deliver = deliver
        self._observe = observe
        self._invocations = invocations  # an INVOKE_CANCEL's INVOKEs
        self._room = asyncio.Semaphore(width)
        self._running: set[asyncio.Task[None]] = set()

    async def submit(self, item: Intake) -> None:
        """Start deciding `item`; waits only while `width` stops are already being decided."""
        await self._room.acquire()
        self._start(item)

    async def try_submit(self, item: Intake) -> bool:
        """Start deciding `item` if there is room now (never waits); False, not taken, if
        `width` are already being decided. For what may be refused: a stop never is."""
        if self._room.locked():
            return False
        await self._room.acquire()  # not locked: taken at once, no suspension
        self._start(item)
        return True

    def _start(self, item: Intake) -> None:
        task = asyncio.create_task(self._run(item))
        self._running.add(task)
        task.add_done_callback(self._running.discard)

    async def _run(self, item: Intake) -> None:
        try:
            reply = await decide_safely(self._governor, self._principal, item, self._observe,
                                        self._invocations)
            await self._deliver(reply)
        except Exception:  # a failed delivery must not go unnoticed, nor kill the lane
            log.exception("delivering a stop outcome to %s failed", self._principal.name,
                          extra={"principal": self._principal.name})
        finally:
            self._room.release()

    async def drain(self) -> None:
        """Wait until every submitted stop is decided (and its reply delivered or dropped)."""
        while self._running:
            await asyncio.gather(*self._running, return_exceptions=True)
