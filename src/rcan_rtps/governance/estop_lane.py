"""The e-stop lane: what an e-stop, a repeated e-stop and a clear do, one transition at a time.

`EstopMachine` (estop.py) owns the latch and the order of transitions; this module is the work
each transition does. An e-stop reaches the robot first and is made durable beside it (latch
file and audit entry, both before the reply); a clear is written ahead like any command and
unlatches only once it is durable. Repeats while latched are answered at once and recorded
together (ESTOP_REPEATED), so a flood of e-stops cannot grow the log one entry each.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable
from typing import Any

import msgspec

from rcan_rtps.rcan import Effect, NormalizedCommand, Outcome
from rcan_rtps.rcan.actions import with_effect

from . import outcomes
from .audit import AuditEvent, AuditReceipt, AuditRecord
from .clock import Clock, now_ms
from .errors import EstopStateError
from .estop import EstopMachine, EstopRepeats
from .rbac import Principal
from .steps import (
    Decision,
    DispatchResult,
    Steps,
    bridge_command,
    decision,
    executed,
    record,
    sent,
)
from .streams import VelocityStreams

log = logging.getLogger("rcan_rtps.governance.governor")
# Who the latch file names when a clear that came as the bridge stopped is undone.
STOPPING_RELATCHED = "rcan-rtps (a clear_estop refused: the bridge was stopping)"


class EstopLane:
    def __init__(self, steps: Steps, latch: EstopMachine, streams: VelocityStreams,
                 clock: Clock) -> None:
        self._steps = steps
        self._latch = latch
        self._streams = streams
        self._clock = clock
        self._repeats = EstopRepeats()
        # The ESTOP entry holding the latch, while no clear was audited after it.
        self._latched_by: AuditReceipt | None = None

    def estop(self, command: NormalizedCommand, principal: Principal) -> Awaitable[Decision]:
        """Latched already; tell the robot, with latch file and audit entry made durable
        beside it. An e-stop always reaches the robot: if the latch file or the audit log
        cannot be written, it is still published, and the failure is logged and answered.

        Begun in the step the latch flipped when no transition was under way (`engage`), so
        its entry is sealed where the e-stop took effect: a command refused for the latch is
        listed after it."""
        if self._latched_by is not None:
            return self._again(command, principal)
        steps = self._steps
        entry = record(AuditEvent.ESTOP, command, principal, Outcome.EXECUTED, applied={},
                       ros2_topic=steps.route(command), sent_first=True)
        self._streams.take_goals()  # the e-stop cancels every goal
        # The robot is told first (the dispatch's first step publishes, before any await);
        # latch file and audit entry are made durable beside it, both before the reply.
        stopping = steps.stop(entry, steps.dispatch(command, command.params),
                              self._latch.file.write(True, principal.name, now_ms(self._clock)))
        return self._estopped(command, principal, stopping)

    async def _estopped(self, command: NormalizedCommand, principal: Principal,
                        stopping: Awaitable[tuple[list[Any], AuditReceipt | None]]
                        ) -> Decision:
        (dispatched, persisted), receipt = await stopping
        if isinstance(persisted, BaseException):
            log.error("e-stop latched in memory only: %s", persisted,
                      extra={"principal": principal.name})
        result, failure = sent(dispatched)
        if receipt is None:
            return decision(outcomes.AUDIT_UNAVAILABLE, message_id=command.message_id)
        self._latched_by = receipt
        if failure is not None:
            return await self._steps.failed(command, principal, failure)
        return executed(command, {}, receipt, result)

    async def _again(self, command: NormalizedCommand, principal: Principal) -> Decision:
        """An e-stop while an audited one holds the latch: the robot is told again, and the
        caller answered with the entry that latched it; the repeats are recorded together."""
        assert self._latched_by is not None
        result, failure = await self._steps.dispatch(command, command.params)
        self._repeats.add(principal.name, now_ms(self._clock), failed=failure is not None,
                          warnings=command.warnings, at_mono=self._clock.monotonic())
        if failure is not None:
            return decision(failure, message_id=command.message_id)
        return Decision(outcome=Outcome.EXECUTED, http_status=200, applied={},
                        audit_id=self._latched_by.audit_id, message_id=command.message_id,
                        reason="already_latched", ros2_topic=result.ros2_topic)

    def repeats_due(self) -> bool:
        return self._repeats.due(self._clock.monotonic())

    async def record_repeats(self) -> None:
        """One ESTOP_REPEATED entry per principal for the repeats counted so far: its
        `params` the bridge's count (`Tally`), its `warnings` what was wrong with the repeated
        requests — request content, held to the log's bound on it (`entry_bound`) as any
        request's warnings are; in `params` they were not (red team 30: a GUEST's duplicated
        30 KB keys made one entry 2.5x that bound)."""
        estop = with_effect(Effect.ESTOP).name
        for name, tally in self._repeats.take().items():
            params = msgspec.structs.asdict(tally)
            warnings = params.pop("warnings") or None
            await self._steps.record_event(AuditRecord(
                event=AuditEvent.ESTOP_REPEATED, principal=name, action_type=estop,
                params=params, outcome=Outcome.EXECUTED.value, warnings=warnings))

    async def clear(self, command: NormalizedCommand, principal: Principal,
                    event: AuditEvent, pending_id: str | None) -> Decision:
        """Audited, persisted, unlatched (unless an e-stop came after it), published.

        Decided when its entry is sealed. An e-stop that arrived before that (while it
        waited for the robot, or for its turn) wins: the clear is refused (`estop_active`).
        One that arrives after it wins too, and this clear neither writes the latch file nor
        unlatches nor publishes. Either way the e-stop did not wait for this clear: its entry
        was sealed as it arrived (`EstopMachine.engage`). The bridge stopping wins as well
        (`VelocityStreams.closed`): the robot's halt is the last thing the bridge tells it,
        never its e-stop released after it, and the next start stays latched (red team 28)."""
        steps = self._steps
        if self._stopping():
            return await steps.refuse(command, principal, outcomes.STOPPED,
                                      pending_id=pending_id)
        why = await steps.ready(command)
        if why is not None:
            return await steps.refuse(command, principal, outcomes.robot_unavailable(why),
                                      pending_id=pending_id)
        await self.record_repeats()  # the e-stops it clears come first in the log
        if self._latch.overtaken():  # an e-stop came while it waited: nothing is cleared
            return await steps.refuse(command, principal, outcomes.ESTOP_ACTIVE,
                                      pending_id=pending_id)
        entry = record(AuditEvent.ESTOP_CLEARED, command, principal, Outcome.EXECUTED,
                       applied={}, pending_id=pending_id, ros2_topic=steps.route(command))
        # Decided: its entry is sealed as the write begins, in this step. An e-stop from now
        # on is a new one, audited in full, sealed at once after this entry.
        latched_by, self._latched_by = self._latched_by, None
        receipt = await steps.write_ahead(entry)
        if receipt is None:
            if self._latched_by is None:
                self._latched_by = latched_by
            return decision(outcomes.AUDIT_UNAVAILABLE, message_id=command.message_id)
        if self._latch.overtaken():  # an e-stop since it was decided: its latch file holds
            return executed(command, {}, receipt, DispatchResult(ok=True))
        if self._stopping():  # the bridge began stopping while it waited
            self._latched_by = latched_by
            return await steps.failed(command, principal, outcomes.STOPPED)
        try:
            await self._latch.file.write(False, principal.name, now_ms(self._clock))
        except EstopStateError:
            log.exception("e-stop clear not persisted: staying latched",
                          extra={"principal": principal.name, "audit_id": receipt.audit_id})
            return await steps.failed(command, principal, outcomes.ESTOP_STATE_UNWRITABLE)
        if self._stopping():  # the bridge began stopping while the file was written
            return await self._latched_again(command, principal, latched_by)
        if not self._latch.unlatch():  # an e-stop is next in line: the robot stays stopped
            return executed(command, {}, receipt, DispatchResult(ok=True))
        result, failure = await steps.dispatch(command, command.params)
        if failure is not None:
            return await steps.failed(command, principal, failure)
        return executed(command, {}, receipt, result)

    async def _latched_again(self, command: NormalizedCommand, principal: Principal,
                             latched_by: AuditReceipt | None) -> Decision:
        """A clear whose `false` reached the latch file as the bridge began stopping: never
        unlatched nor published, and the file latched again, so the next start is too. An
        e-stop since the clear was decided latched it already (its `true` is queued after
        the `false`): the file names who e-stopped, and that e-stop holds the latch."""
        if self._latch.overtaken():
            return await self._steps.failed(command, principal, outcomes.STOPPED)
        self._latched_by = latched_by
        try:
            await self._latch.file.write(True, STOPPING_RELATCHED, now_ms(self._clock))
        except EstopStateError:  # the file says clear; the log's COMMAND_FAILED latches
            log.exception("e-stop clear refused as the bridge stopped, but its latch file "
                          "could not be latched again: it says clear (the next start is "
                          "latched by the audit log's failed clear)",
                          extra={"principal": principal.name})
        return await self._steps.failed(command, principal, outcomes.STOPPED)

    def _stopping(self) -> bool:
        """The bridge began stopping (`Governor.end_streams`): nothing more reaches the robot
        but stops."""
        return self._streams.closed

    async def republish(self) -> None:
        """Latched at start: the robot is told again."""
        _, failure = await self._steps.dispatch(bridge_command(Effect.ESTOP))
        if failure is not None:
            log.error("latched at start, but the robot could not be told (%s)", failure.reason)
