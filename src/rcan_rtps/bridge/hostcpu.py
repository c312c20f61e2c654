"""The CPU utilisation of the machine the bridge runs on, for STATUS's §20 `cpu_percent`.

Read from /proc/stat (Linux): the share of non-idle time across all CPUs since the previous
reading, taken at most once per `min_interval_s` (STATUS is computed at the telemetry rate
and on every change; the figure in between is the last one). Elsewhere, or before a second
reading exists, there is no figure (None). It is the bridge's host, which is the robot's
computer only where the bridge runs on the robot.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

_STAT = Path("/proc/stat")


def _read_times(path: Path) -> tuple[int, int] | None:
    """(busy, total) jiffies of all CPUs, or None where /proc/stat is not there."""
    try:
        with path.open("rb") as file:
            first = file.readline().split()
    except OSError:
        return None
    if not first or first[0] != b"cpu":
        return None
    values = [int(v) for v in first[1:]]
    idle = values[3] + (values[4] if len(values) > 4 else 0)  # idle + iowait
    total = sum(values[:8])  # guest time is already inside user and nice
    return total - idle, total


class CpuMeter:
    def __init__(self, *, min_interval_s: float = 1.0, path: Path = _STAT,
                 monotonic: Callable[[], float] = time.monotonic) -> None:
        self._path = path
        self._interval = min_interval_s
        self._monotonic = monotonic
        self._lock = threading.Lock()
        self._last: tuple[int, int] | None = _read_times(path)
        self._at = monotonic()
        self._percent: float | None = None

    def percent(self) -> float | None:
        with self._lock:
            now = self._monotonic()
            if now - self._at >= self._interval:
                self._sample(now)
            return self._percent

    def _sample(self, now: float) -> None:
        times = _read_times(self._path)
        if times is not None and self._last is not None:
            busy, total = times[0] - self._last[0], times[1] - self._last[1]
            if total > 0:
                self._percent = round(max(0.0, min(100.0, 100.0 * busy / total)), 1)
        self._last, self._at = times, now
