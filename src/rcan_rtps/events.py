"""Who is told what: one typed object of channels, wired before start and frozen then.

The kernel's own reactions are calls, not events (the latch engaging zeroes the streams and
publishes the e-stop Bool; a stream's end is audited by the arbiter that owns it). Events are
what listens from outside: STATUS, metrics, the diagnostics notifier, telemetry, the
WebSocket's goal events, the audit of a goal's end, an INVOKE waiting for its stream's end.
Each channel's subscribers are fixed when the bridge starts (`freeze`): a subscription after
that is a wiring bug and raises, and an emit — from the event loop or from a DDS thread —
reads a tuple nobody changes any more.

A subscriber that fails is logged and the rest are still told: listeners are informative and
must never break what they listen to.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Generic, ParamSpec

import msgspec

if TYPE_CHECKING:  # types only: governance and api import this module, never the reverse
    from .api.ports import GoalView
    from .bridge.sent_goals import GoalFinished
    from .governance.audit import AuditReceipt, AuditRecord
    from .governance.rbac import Principal
    from .governance.streams import StreamEnded

__all__ = ["Channel", "Events", "EventsFrozenError"]

log = logging.getLogger(__name__)
P = ParamSpec("P")


class EventsFrozenError(RuntimeError):
    """A subscription after start: every listener must be wired before the bridge runs."""


class Channel(Generic[P]):
    __slots__ = ("_frozen", "_subscribers", "name")

    def __init__(self, name: str) -> None:
        self.name = name
        self._subscribers: tuple[Callable[P, None], ...] = ()
        self._frozen = False

    def subscribe(self, listener: Callable[P, None]) -> None:
        if self._frozen:
            raise EventsFrozenError(f"{self.name}: subscribed after start")
        self._subscribers = (*self._subscribers, listener)

    def freeze(self) -> None:
        self._frozen = True

    @property
    def heard(self) -> bool:
        """Anyone subscribed (so an emitter can skip building what nobody reads)."""
        return bool(self._subscribers)

    def emit(self, *args: P.args, **kwargs: P.kwargs) -> None:
        for listener in self._subscribers:
            try:
                listener(*args, **kwargs)
            except Exception:
                log.exception("%s listener failed", self.name)


def _channel(name: str) -> Callable[[], Channel[...]]:
    return lambda: Channel(name)


class Events(msgspec.Struct, frozen=True):
    # What STATUS shows of governance changed: the latch flipped, approvals pending changed.
    governance: Channel[[]] = msgspec.field(default_factory=_channel("governance"))
    # A lost control session is about to halt the robot (its goals are still active).
    session_lost: Channel[[Principal]] = msgspec.field(default_factory=_channel("session lost"))
    # A lost control session halted the robot (STATUS shows `safe_stop`).
    safe_stop: Channel[[Principal]] = msgspec.field(default_factory=_channel("safe stop"))
    # An entry is durable (metrics, the log line per decision).
    audited: Channel[[AuditRecord, AuditReceipt]] = msgspec.field(default_factory=_channel("audit"))
    # A command reached the robot (STATUS leaves `safe_stop`).
    command_sent: Channel[[]] = msgspec.field(default_factory=_channel("command sent"))
    # What STATUS shows of the robot may have changed: telemetry, the active goals. Any thread.
    robot: Channel[[]] = msgspec.field(default_factory=_channel("robot"))
    # A goal changed (feedback, state, its end): a copy of its view, on the event loop.
    goal: Channel[[GoalView]] = msgspec.field(default_factory=_channel("goal"))
    # A goal ended, once per goal (the audit's GOAL_FINISHED).
    goal_finished: Channel[[GoalFinished]] = msgspec.field(
        default_factory=_channel("goal finished"))
    # A velocity stream ended, once audited (an INVOKE of a `move` skill is answered then); on
    # the event loop, in the step that ended it.
    stream_ended: Channel[[StreamEnded]] = msgspec.field(
        default_factory=_channel("stream ended"))

    def freeze(self) -> None:
        """From now on the subscribers are fixed."""
        for name in self.__struct_fields__:
            getattr(self, name).freeze()

    @property
    def frozen(self) -> bool:
        return all(getattr(self, name)._frozen for name in self.__struct_fields__)
