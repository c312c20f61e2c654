"""An injectable clock: wall time for timestamps and for what is compared with the timestamps
of messages and tokens; monotonic time for durations (rate limits, TTLs, timeouts).

The wall clock can be stepped under a running bridge, forward or back (a board without an RTC
boots at 1970 and NTP then steps it by decades; an operator runs `date -s`; NTP steps back
a few seconds). `LatestWall` is the wall time for checks that must not be undone by a step
back: what went stale by the latest time this run has read stays stale."""

from __future__ import annotations

import time
import weakref
from typing import Protocol


class Clock(Protocol):
    def time(self) -> float:
        """Seconds since the epoch (wall clock)."""
        ...

    def monotonic(self) -> float:
        """Seconds on a clock that never goes back."""
        ...


class SystemClock:
    def time(self) -> float:
        return time.time()

    def monotonic(self) -> float:
        return time.monotonic()


class ManualClock:
    """A clock that moves only when told to (tests, simulations)."""

    def __init__(self, start: float = 1_800_000_000.0) -> None:
        self._wall = start
        self._mono = 0.0

    def time(self) -> float:
        return self._wall

    def monotonic(self) -> float:
        return self._mono

    def advance(self, seconds: float) -> None:
        self._wall += seconds
        self._mono += seconds

    def step(self, seconds: float) -> None:
        """The wall clock alone is set forward (or back, negative), as NTP or `date -s` do."""
        self._wall += seconds


class LatestWall:
    """The latest wall time read so far through it: a step back of the wall clock does not
    take it back (it waits until the wall clock passes it again); a step forward moves it.
    One per clock (`latest_wall`), read by every check that uses it and by the governor's
    sweep, so that it is as late as the last time anyone looked."""

    def __init__(self, clock: Clock) -> None:
        self._clock = clock
        self._latest = clock.time()

    def time(self) -> float:
        self._latest = max(self._latest, self._clock.time())
        return self._latest


_LATEST: weakref.WeakKeyDictionary[Clock, LatestWall] = weakref.WeakKeyDictionary()
_SYSTEM = SystemClock()


def latest_wall(clock: Clock) -> LatestWall:
    """The `LatestWall` of `clock`: one for every `SystemClock` (they read the same clock)."""
    key = _SYSTEM if isinstance(clock, SystemClock) else clock
    found = _LATEST.get(key)
    if found is None:
        found = _LATEST[key] = LatestWall(key)
    return found


def now_ms(clock: Clock) -> int:
    return int(clock.time() * 1000)
