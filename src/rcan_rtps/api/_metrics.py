"""Prometheus metrics of the bridge, in a registry per app (GET /api/metrics).

Counters come from the audit log itself (every durable entry, by event and outcome), so
what is counted is exactly what is on record; gauges are read from the robot at scrape.
"""

from __future__ import annotations

from prometheus_client import CONTENT_TYPE_LATEST as CONTENT_TYPE
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest

from rcan_rtps.governance import AuditReceipt, AuditRecord, Governor
from rcan_rtps.rcan.actions import specs

from ._status import StatusHub

_STATES = ("idle", "moving", "executing", "estop", "fault", "safe_stop", "offline")


class Metrics:
    content_type = CONTENT_TYPE

    def __init__(self, governor: Governor, status: StatusHub) -> None:
        self.registry = CollectorRegistry()
        self._status = status
        self.audit_entries = Counter(
            "rcan_audit_entries", "Durable audit entries, by event, action and outcome",
            ["event", "action", "outcome"], registry=self.registry)
        self.command_seconds = Histogram(
            "rcan_command_seconds", "Time to decide a command (including dispatch and fsync)",
            registry=self.registry,
            buckets=(0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.5, 1.0, 5.0))
        self.pending = Gauge("rcan_pending_approvals", "Commands waiting for a human",
                             registry=self.registry)
        self.estop = Gauge("rcan_estop_latched", "1 while the e-stop is latched",
                           registry=self.registry)
        self.state = Gauge("rcan_robot_state", "1 for the robot's current STATUS state",
                           ["state"], registry=self.registry)
        self.telemetry_age = Gauge("rcan_telemetry_age_seconds",
                                   "Age of the newest ROS 2 telemetry (NaN: none yet)",
                                   registry=self.registry)
        self.actions = Gauge("rcan_action_info", "1 per action this bridge accepts",
                             ["action", "effect", "default_role"], registry=self.registry)
        for spec in specs():
            self.actions.labels(spec.name, spec.effect.value, spec.default_role.name).set(1)
        governor.audit.listeners.append(self.on_audit)

    def on_audit(self, record: AuditRecord, receipt: AuditReceipt) -> None:
        self.audit_entries.labels(record.event.value, record.action_type or "",
                                  record.outcome or "").inc()

    def render(self) -> bytes:
        status = self._status.snapshot()  # the STATUS owner's, as every transport sees it
        self.pending.set(status.pending_auth)
        self.estop.set(1 if status.estop else 0)
        for state in _STATES:
            self.state.labels(state).set(1 if status.state == state else 0)
        age = status.ros.last_telemetry_age_s
        self.telemetry_age.set(float("nan") if age is None else age)
        return bytes(generate_latest(self.registry))
