"""An injectable clock: wall time for timestamps and for what is compared with the timestamps
of messages and tokens; monotonic time for durations (rate limits, TTLs, timeouts).

The wall clock can be stepped under a running bridge, forward or back (a board without an RTC
boots at 1970 and NTP then steps it by decades; an operator runs `date -s`; NTP steps back
a few seconds). `LatestWall` is the wall time for checks that must not be undone by a step
back: what went stale by the latest time this run has read stays stale.

`Clock.boot` is where this boot's boot clock stands (Linux: CLOCK_BOOTTIME, counting from boot,
suspend included, never stepped; the boot named by /proc/sys/kernel/random/boot_id): a start
in the same boot as an entry stamped with it knows exactly how long ago that entry was
written, whatever the wall clock did in between. None where there is none (macOS: Python
offers no CLOCK_BOOTTIME there)."""

from __future__ import annotations

import time
import weakref
from typing import NamedTuple, Protocol


class BootInstant(NamedTuple):
    """A time on one boot's boot clock: the boot's id and milliseconds since it booted."""

    boot_id: str
    ms: int


class Clock(Protocol):
    def time(self) -> float:
        """Seconds since the epoch (wall clock)."""
        ...

    def monotonic(self) -> float:
        """Seconds on a clock that never goes back."""
        ...

    def boot(self) -> BootInstant | None:
        """Now on this boot's boot clock; None where the platform has none."""
        ...


class SystemClock:
    def time(self) -> float:
        return time.time()

    def monotonic(self) -> float:
        return time.monotonic()

    def boot(self) -> BootInstant | None:
        return system_boot()


_BOOT_ID_PATH = "/proc/sys/kernel/random/boot_id"
_boot_id: list[str | None] = []  # read once: a process lives in one boot


def system_boot() -> BootInstant | None:
    """Now on this machine's boot clock (CLOCK_BOOTTIME) with its boot id; None without
    either (not Linux, or /proc not mounted)."""
    boottime = getattr(time, "CLOCK_BOOTTIME", None)
    if boottime is None:
        return None
    if not _boot_id:
        _boot_id.append(_read_boot_id())
    boot_id = _boot_id[0]
    if boot_id is None:
        return None
    return BootInstant(boot_id, time.clock_gettime_ns(boottime) // 1_000_000)


def _read_boot_id() -> str | None:
    try:
        with open(_BOOT_ID_PATH, encoding="ascii") as f:
            return f.read().strip() or None
    except (OSError, ValueError):
        return None


class ManualClock:
    """A clock that moves only when told to (tests, simulations)."""

    def __init__(self, start: float = 1_800_000_000.0,
                 boot_id: str | None = "manual-boot-1") -> None:
        self._wall = start
        self._mono = 0.0
        self._boot_id = boot_id  # None: a platform without a boot clock
        self._booted = 0.0  # seconds on the boot clock

    def boot(self) -> BootInstant | None:
        if self._boot_id is None:
            return None
        return BootInstant(self._boot_id, int(self._booted * 1000))

    def time(self) -> float:
        return self._wall

    def monotonic(self) -> float:
        return self._mono

    def advance(self, seconds: float) -> None:
        self._wall += seconds
        self._mono += seconds
        self._booted += seconds

    def reboot(self, boot_id: str) -> None:
        """The machine booted again (as `boot_id`): its boot clock starts over; the wall
        clock is where it was."""
        self._boot_id, self._booted = boot_id, 0.0

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
