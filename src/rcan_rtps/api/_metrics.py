"""Prometheus metrics of the bridge, in a registry per app (GET /api/metrics).

Counters come from the audit log itself (every durable entry, by event and outcome), so
what is counted is exactly what is on record; gauges are read from the robot at scrape.

Counting is plain Python (a dict increment per entry, a bucket search per command): a command
takes no metric locks. `prometheus_client` (its registry and exposition) is imported at the
first scrape: a bridge nobody scrapes never loads it.
"""

from __future__ import annotations

from bisect import bisect_left
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from rcan_rtps.governance import AuditReceipt, AuditRecord, Governor
from rcan_rtps.rcan.actions import specs

from ._status import StatusHub

if TYPE_CHECKING:
    from prometheus_client import CollectorRegistry

_STATES = ("idle", "moving", "executing", "estop", "fault", "safe_stop", "offline")
BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.5, 1.0, 5.0)
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"  # prometheus_client's, unimported


class Histogram:
    """Observations by bucket (upper bounds inclusive, as Prometheus's `le`), and their sum."""

    def __init__(self, buckets: tuple[float, ...] = BUCKETS) -> None:
        self.buckets = buckets
        self.counts = [0] * (len(buckets) + 1)  # the last: above every bound (+Inf only)
        self.sum = 0.0

    def observe(self, value: float) -> None:
        self.counts[bisect_left(self.buckets, value)] += 1
        self.sum += value

    def cumulative(self) -> list[int]:
        total, out = 0, []
        for count in self.counts:
            total += count
            out.append(total)
        return out


class Metrics:
    content_type = CONTENT_TYPE

    def __init__(self, governor: Governor, status: StatusHub) -> None:
        self._status = status
        self.audit_entries: dict[tuple[str, str, str], int] = {}  # (event, action, outcome)
        self.command_seconds = Histogram()
        self._actions = [(s.name, s.effect.value, s.default_role.name) for s in specs()]
        self._gauges: dict[str, float] = {"pending": 0.0, "estop": 0.0, "age": float("nan")}
        self._state = ""
        self._registry: CollectorRegistry | None = None
        governor.audit.audited.subscribe(self.on_audit)

    def on_audit(self, record: AuditRecord, receipt: AuditReceipt) -> None:
        key = (record.event.value, record.action_type or "", record.outcome or "")
        self.audit_entries[key] = self.audit_entries.get(key, 0) + 1

    @property
    def registry(self) -> CollectorRegistry:
        if self._registry is None:
            from prometheus_client import CollectorRegistry

            self._registry = CollectorRegistry(auto_describe=False)
            self._registry.register(self)  # a collector: it has `collect`
        return self._registry

    def render(self) -> bytes:
        from prometheus_client import generate_latest

        status = self._status.snapshot()  # the STATUS owner's, as every transport sees it
        age = status.ros.last_telemetry_age_s
        self._gauges = {"pending": float(status.pending_auth),
                        "estop": 1.0 if status.estop else 0.0,
                        "age": float("nan") if age is None else age}
        self._state = status.state
        return bytes(generate_latest(self.registry))

    def collect(self) -> Iterator[Any]:
        """The registry's view (prometheus_client's collector protocol)."""
        from prometheus_client.core import (
            CounterMetricFamily,
            GaugeMetricFamily,
            HistogramMetricFamily,
        )
        entries = CounterMetricFamily(
            "rcan_audit_entries", "Durable audit entries, by event, action and outcome",
            labels=["event", "action", "outcome"])
        for labels, count in self.audit_entries.items():
            entries.add_metric(list(labels), float(count))
        yield entries
        hist = self.command_seconds
        bounds = [repr(b) for b in hist.buckets] + ["+Inf"]  # as Prometheus spells them
        yield HistogramMetricFamily(
            "rcan_command_seconds", "Time to decide a command (including dispatch and fsync)",
            buckets=[(b, float(c)) for b, c in zip(bounds, hist.cumulative(), strict=True)],
            sum_value=hist.sum)
        yield GaugeMetricFamily("rcan_pending_approvals", "Commands waiting for a human",
                                value=self._gauges["pending"])
        yield GaugeMetricFamily("rcan_estop_latched", "1 while the e-stop is latched",
                                value=self._gauges["estop"])
        state = GaugeMetricFamily("rcan_robot_state", "1 for the robot's current STATUS state",
                                  labels=["state"])
        for name in _STATES:
            state.add_metric([name], 1.0 if name == self._state else 0.0)
        yield state
        yield GaugeMetricFamily("rcan_telemetry_age_seconds",
                                "Age of the newest ROS 2 telemetry (NaN: none yet)",
                                value=self._gauges["age"])
        actions = GaugeMetricFamily("rcan_action_info", "1 per action this bridge accepts",
                                    labels=["action", "effect", "default_role"])
        for labels in self._actions:
            actions.add_metric(list(labels), 1.0)
        yield actions
