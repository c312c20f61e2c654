"""PENDING_AUTH notifications: a WARN diagnostic on the robot's graph (spec §4) plus the
configured webhook, each isolated so one failing never silences the other."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Sequence

from ..governance import Notifier
from ..rcan import PendingAuth
from ..ros.participant import RosNode
from ..ros.rostime import now_msg

log = logging.getLogger(__name__)
OK, WARN = 0, 1
# A WARN is published again at this period while approvals wait, as ROS diagnostics are
# (diagnostic_updater's default): a monitor that joins late, or missed a sample, still sees it.
REPEAT_S = 1.0


class DiagnosticsNotifier:
    """Publishes `DiagnosticArray` with one WARN status naming the pending command (again
    every `repeat_s` while it is the latest), and an OK for the same status once no approval
    waits any more (monitors then clear it)."""

    def __init__(self, node: RosNode, topic: str, repeat_s: float = REPEAT_S) -> None:
        self.node = node
        self.publisher = node.create_publisher(topic, "diagnostic_msgs/msg/DiagnosticArray")
        self.repeat_s = repeat_s
        self._warn: tuple[str, list[dict[str, str]]] | None = None  # the WARN last published
        self._repeater: asyncio.Task[None] | None = None

    @property
    def warning(self) -> bool:
        """A WARN is the last thing published."""
        return self._warn is not None

    async def notify(self, message: PendingAuth) -> None:
        action = message.original_command.get("action", "?")
        self._publish(WARN, f"command '{action}' awaits human approval", [
            {"key": "pending_id", "value": message.pending_id},
            {"key": "requires_auth_from_role", "value": message.requires_auth_from_role},
            {"key": "expires_at_ms", "value": str(message.expires_at_ms)},
        ])

    def pending_changed(self, waiting: int) -> None:
        """Approvals were resolved or expired: with none left, the WARN gives way to OK."""
        if self.warning and not waiting:
            self._publish(OK, "no command awaits human approval", [])

    def close(self) -> None:
        """Stops repeating (the bridge is stopping); idempotent."""
        if self._repeater is not None:
            self._repeater.cancel()
            self._repeater = None

    async def _repeat(self) -> None:
        while self._warn is not None:
            await asyncio.sleep(self.repeat_s)
            if self._warn is not None:
                try:
                    self._publish(WARN, *self._warn)
                except Exception:  # the node is closing: the next stop step ends this
                    log.exception("repeating the PENDING_AUTH diagnostic failed")
                    return

    def _publish(self, level: int, text: str, values: list[dict[str, str]]) -> None:
        self._warn = (text, values) if level == WARN else None
        if self._warn is not None and (self._repeater is None or self._repeater.done()):
            self._repeater = asyncio.get_running_loop().create_task(self._repeat())
        self.publisher.publish({
            "header": {"stamp": now_msg(), "frame_id": ""},
            "status": [{"level": level, "name": f"{self.node.name}: hitl", "message": text,
                        "hardware_id": self.node.fqn, "values": values}],
        })


class FanOutNotifier:
    def __init__(self, notifiers: Sequence[Notifier]) -> None:
        self.notifiers = list(notifiers)

    async def notify(self, message: PendingAuth) -> None:
        results = await asyncio.gather(*(n.notify(message) for n in self.notifiers),
                                       return_exceptions=True)
        for notifier, result in zip(self.notifiers, results, strict=True):
            if isinstance(result, BaseException):
                log.warning("PENDING_AUTH notification via %s failed: %s",
                            type(notifier).__name__, result)
