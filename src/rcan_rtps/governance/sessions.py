"""Control sessions (§10.8): who holds one, since when nothing was heard from them, and how
much silence their session allows.

A principal holds a session from the moment motion of theirs is sent to the robot (a refused
command opens none) until they stop on purpose or go silent for longer than allowed: then the
governor halts what they drive (`Governor.safe_stop`). A timed move allows
`safety.unattended_move_s` of silence, anything else `safety.session_timeout_s`. A command
still being carried out (waiting for a subscriber, say) is not silence.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

from rcan_rtps.rcan import ActionSpec

from .clock import Clock
from .rbac import Principal


class Sessions:
    """Who holds a control session, since when nothing was heard from them, and how much
    silence their session allows (a timed move's: `unattended_s`)."""

    def __init__(self, clock: Clock, timeout_s: float, unattended_s: float | None = None
                 ) -> None:
        self._clock = clock
        self.timeout_s = timeout_s
        self.unattended_s = unattended_s or timeout_s
        self._last: dict[str, tuple[Principal, float, float]] = {}  # → (p, heard, allowed)
        self._busy: dict[str, int] = {}  # commands being carried out, per principal

    @contextlib.contextmanager
    def in_flight(self, principal: Principal) -> Iterator[None]:
        self._busy[principal.name] = self._busy.get(principal.name, 0) + 1
        try:
            yield
        finally:
            left = self._busy.pop(principal.name) - 1
            if left:
                self._busy[principal.name] = left

    def touch(self, principal: Principal, spec: ActionSpec[Any], *, timed: bool = False
              ) -> None:
        """An executed command: motion opens (or renews) the session, a stop ends it."""
        if spec.motion:
            allowed = self.unattended_s if timed else self.timeout_s
            self._last[principal.name] = (principal, self._clock.monotonic(), allowed)
        elif spec.stopping:
            self._last.pop(principal.name, None)  # stopped on purpose: nothing to guard

    def heartbeat(self, principal: Principal) -> None:
        last = self._last.get(principal.name)
        if last is not None:
            self._last[principal.name] = (principal, self._clock.monotonic(), last[2])

    def end(self, principal: Principal) -> bool:
        """Drop the principal's session; True if it held one."""
        return self._last.pop(principal.name, None) is not None

    def take_lost(self) -> list[tuple[Principal, float]]:
        """Sessions silent for longer than they allow: (principal, the silence allowed)."""
        now = self._clock.monotonic()
        lost = [(p, allowed) for p, at, allowed in self._last.values()
                if now - at > allowed and p.name not in self._busy]
        for p, _ in lost:
            del self._last[p.name]
        return lost
