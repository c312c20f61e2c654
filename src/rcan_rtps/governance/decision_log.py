"""One log line per durable audit entry: what someone tailing the server needs to see.

Decisions log at INFO; safety events (e-stop, clear, session-loss stop, failed sends, expired
approvals, a recovered log tail) at WARNING, so they show at the default level too. Each line
carries `principal` and `audit_id` as context (fields of their own in JSON logs).
"""

from __future__ import annotations

import logging

from .._printable import shown  # (a deny_reason holds paths through the client's own keys)
from .audit import AuditEvent, AuditReceipt, AuditRecord

log = logging.getLogger("rcan_rtps.decisions")

SAFETY_EVENTS = frozenset({
    AuditEvent.ESTOP, AuditEvent.ESTOP_CLEARED, AuditEvent.NETWORK_LOSS_SAFE_STOP,
    AuditEvent.COMMAND_FAILED, AuditEvent.HITL_EXPIRED, AuditEvent.AUDIT_TAIL_RECOVERED,
})


def describe(record: AuditRecord) -> str:
    """`EVENT by principal action -> outcome (reason) on topic`, leaving out what is absent."""
    parts = [record.event.value]
    if record.principal:
        parts.append(f"by {record.principal}")
    if record.action_type:
        parts.append(record.action_type)
    if record.outcome:
        parts.append(f"-> {record.outcome}")
    if record.deny_reason:
        parts.append(f"({record.deny_reason})")
    if record.event is AuditEvent.STREAM_ENDED and record.params:
        parts.append(f"({record.params.get('reason')})")
    if record.ros2_topic:
        parts.append(f"on {record.ros2_topic}")
    return shown(" ".join(parts))


def log_entry(record: AuditRecord, receipt: AuditReceipt) -> None:
    """An `AuditLog` listener."""
    level = logging.WARNING if record.event in SAFETY_EVENTS else logging.INFO
    if log.isEnabledFor(level):
        log.log(level, "%s [audit #%d]", describe(record), receipt.seq,
                extra={"principal": record.principal, "audit_id": receipt.audit_id})
