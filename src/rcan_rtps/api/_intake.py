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
from dataclasses import dataclass
from typing import Any

from rcan_rtps.governance import Governor, Principal, Rejection, outcomes
from rcan_rtps.rcan import (
    ErrorCode,
    InvalidRuriError,
    NormalizedCommand,
    Outcome,
    SchemaValidationError,
    validate_command,
)

from ._bodies import error_body, failure_reply

log = logging.getLogger(__name__)

Reply = tuple[int, Any]
Deliver = Callable[[Reply], Awaitable[None]]
Observe = Callable[[float], None]

TOO_DEEP = "JSON is nested too deeply"
# A bug in validation must not take a transport down: it is answered (and audited) like this.
_INTERNAL = Rejection(503, Outcome.FAILED, ErrorCode.ROBOT_UNAVAILABLE, "internal_error")


@dataclass(frozen=True)
class Intake:
    """A validated command, or the pre-command refusal its body earned (with schema detail)."""

    command: NormalizedCommand | None = None
    refusal: Rejection | None = None
    detail: str | None = None

    @property
    def stopping(self) -> bool:
        """A valid `stop` or `estop`: the kind no queue may hold back."""
        return self.command is not None and self.command.spec.stopping

    @property
    def message_id(self) -> str | None:
        return None if self.command is None else self.command.message_id


def intake(raw: bytes, limit: int) -> Intake:
    """Size check, then `validate_command`; every failure becomes a refusal, never a raise."""
    if len(raw) > limit:
        return Intake(refusal=outcomes.PAYLOAD_TOO_LARGE)
    try:
        return Intake(command=validate_command(raw))
    except RecursionError:  # msgspec gives up on deep nesting with this, not a DecodeError
        return Intake(refusal=outcomes.schema_failed("$"), detail=TOO_DEEP)
    except SchemaValidationError as exc:
        return Intake(refusal=outcomes.schema_failed(exc.path), detail=exc.detail)
    except InvalidRuriError as exc:
        return Intake(refusal=outcomes.invalid_ruri(exc.rule))
    except Exception:
        log.exception("validating a command body failed unexpectedly")
        return Intake(refusal=_INTERNAL)


async def decide(governor: Governor, principal: Principal, item: Intake,
                 observe: Observe | None = None) -> Reply:
    """The decision for one intake; pre-command refusals are audited for the principal."""
    started = time.perf_counter()
    try:
        if item.command is not None:
            decision = await governor.decide(item.command, principal)
            return decision.http_status, decision.body()
        assert item.refusal is not None
        decision = await governor.reject_request(principal, item.refusal)
        if item.refusal.error_code is not ErrorCode.SCHEMA_VALIDATION_FAILED:
            return decision.http_status, decision.body()
        # Schema failures also say what was wrong where (the reason is the field path).
        body = error_body(ErrorCode.SCHEMA_VALIDATION_FAILED, reason=item.detail,
                          path=item.refusal.reason, audit_id=decision.audit_id)
        return decision.http_status, body
    finally:
        if observe is not None:
            observe(time.perf_counter() - started)


async def decide_safely(governor: Governor, principal: Principal, item: Intake,
                        observe: Observe | None = None) -> Reply:
    """`decide` for transports without a last-resort middleware: an exception is an answer
    (503, as REST gives), never the end of the connection's command handling."""
    try:
        return await decide(governor, principal, item, observe)
    except Exception as exc:
        log.exception("deciding a command of %s failed", principal.name,
                      extra={"principal": principal.name})
        return failure_reply(exc)


class StopLane:
    """`stop`/`estop` of one connection, decided the moment they arrive, concurrently with (and
    never behind) the connection's other commands. Their replies may overtake earlier
    commands' replies; each carries its `message_id`."""

    def __init__(self, governor: Governor, principal: Principal, deliver: Deliver, *,
                 observe: Observe | None = None, width: int = 4) -> None:
        self._governor = governor
        self._principal = principal
        self._deliver = deliver
        self._observe = observe
        self._room = asyncio.Semaphore(width)
        self._running: set[asyncio.Task[None]] = set()

    async def submit(self, item: Intake) -> None:
        """Start deciding `item`; waits only while `width` stops are already being decided."""
        await self._room.acquire()
        task = asyncio.create_task(self._run(item))
        self._running.add(task)
        task.add_done_callback(self._running.discard)

    async def _run(self, item: Intake) -> None:
        try:
            reply = await decide_safely(self._governor, self._principal, item, self._observe)
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
