"""What a crashed run left running, as `resume` finds it in the audit log and a start takes
it back (`Governor.start`, the dispatcher's `halt_left`).

The types alone, apart from the replay that finds them (`resume.py`): the replay runs once,
at start, and is then let go of (`rcan_rtps._modules.START_ONLY`: idle memory, issue 27),
while these stay in use by the governor and the dispatcher.
"""

from __future__ import annotations

from typing import Any

import msgspec

from .clock import BootInstant

# A controller may still be settling onto a trajectory's last point just after its time (as
# bridge.arm_holds.SETTLING_S).
SETTLING_S = 1.0


class LeftArm(msgspec.Struct, frozen=True, kw_only=True, omit_defaults=True):
    """An arm's trajectory a crashed run sent that may still run in its controller.

    Dated by the boot clock when its entry was stamped with it and the start is in that
    same boot (exact: the boot clock is never stepped); else by the wall clock of its entry
    (an entry written before the stamp, another boot, a platform without a boot clock)."""

    message_id: str
    action: str
    principal: str | None
    topic: str | None  # where it went (`ros2_topic`)
    params: dict[str, Any]  # as sent (`applied`): routes the hold (its `group`)
    joints: list[str]
    sent_at_ms: int  # the wall time of its entry
    runs_for_s: float
    # The boot clock of its entry (`AuditRecord.boot`), when it was stamped: the boot's id
    # and ms since that boot. (Left out of `facts` when None: as entries were before.)
    sent_boot_id: str | None = None
    sent_boot_ms: int | None = None

    @property
    def due_ms(self) -> int:
        """Wall time after which it has ended, settling included."""
        return self.sent_at_ms + self._lasts_ms

    def left_ms(self, wall_ms: int, boot: BootInstant | None) -> int:
        """How much longer it may run (settling included; <= 0: it has ended) at wall time
        `wall_ms` and `boot` (now on the boot clock): by the boot clock in the boot it was
        sent in, whatever the wall clock did since; else by the wall clock."""
        if (boot is not None and self.sent_boot_ms is not None
                and self.sent_boot_id == boot.boot_id):
            return self.sent_boot_ms + self._lasts_ms - boot.ms
        return self.due_ms - wall_ms

    @property
    def _lasts_ms(self) -> int:
        return round((self.runs_for_s + SETTLING_S) * 1000)


class LeftGoal(msgspec.Struct, frozen=True, kw_only=True):
    """A goal a crashed run sent that no entry shows ended."""

    message_id: str
    action: str
    principal: str | None
    server: str | None
    goal_id: str | None  # None: its entry predates goal ids written ahead (cannot be named)


class LeftStream(msgspec.Struct, frozen=True, kw_only=True):
    """A velocity stream a crashed run was sending that no entry shows ended."""

    message_id: str
    action: str
    principal: str | None
    topic: str | None


class LeftRunning(msgspec.Struct, kw_only=True):
    """The motion the previous run left possibly running (it did not end with BRIDGE_STOPPED)."""

    arms: list[LeftArm] = msgspec.field(default_factory=list)
    goals: list[LeftGoal] = msgspec.field(default_factory=list)
    streams: list[LeftStream] = msgspec.field(default_factory=list)

    def __bool__(self) -> bool:
        return bool(self.arms or self.goals or self.streams)

    def facts(self) -> dict[str, Any]:
        """What an entry records of it (all of it: a later scan takes up what a start could
        not take back from here, `still_left`)."""
        facts: dict[str, Any] = msgspec.to_builtins(self)
        return facts
