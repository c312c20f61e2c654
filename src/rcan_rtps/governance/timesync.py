"""Whether the wall clock is synchronized, as the kernel says (RCAN §8.4, the P66 clock fields).

On Linux, `adjtimex(2)` with no modes set only reads the kernel's clock discipline: an NTP
daemon (chrony, ntpd, systemd-timesyncd) that has the clock in hand clears STA_UNSYNC, and
`esterror` is its estimate of the clock's error. That is what `clock_status` reports: the
source is named `ntp` when the kernel's NTP discipline is synchronized (NTS or a GPS reference
disciplining through it look the same from here), `none` when it is not; elsewhere, or if the
call fails, nothing is known (`None`).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import sys

import msgspec

_STA_UNSYNC = 0x0040
_TIME_ERROR = 5


class ClockStatus(msgspec.Struct, frozen=True, kw_only=True):
    synchronized: bool | None  # None: unknown on this system
    source: str | None  # "ntp" | "none" | None
    error_ms: float | None  # the kernel's estimated error (esterror), when synchronized


class _Timex(ctypes.Structure):
    # struct timex of <sys/timex.h> (Linux, LP64 and ILP32 alike: longs and ints in order);
    # the trailing padding the kernel reserves is included so it writes only into our memory.
    _fields_ = [("modes", ctypes.c_uint), ("offset", ctypes.c_long), ("freq", ctypes.c_long),
                ("maxerror", ctypes.c_long), ("esterror", ctypes.c_long),
                ("status", ctypes.c_int), ("constant", ctypes.c_long),
                ("precision", ctypes.c_long), ("tolerance", ctypes.c_long),
                ("time_sec", ctypes.c_long), ("time_usec", ctypes.c_long),
                ("tick", ctypes.c_long), ("ppsfreq", ctypes.c_long), ("jitter", ctypes.c_long),
                ("shift", ctypes.c_int), ("stabil", ctypes.c_long), ("jitcnt", ctypes.c_long),
                ("calcnt", ctypes.c_long), ("errcnt", ctypes.c_long), ("stbcnt", ctypes.c_long),
                ("tai", ctypes.c_int), ("_reserved", ctypes.c_int * 11)]


UNKNOWN = ClockStatus(synchronized=None, source=None, error_ms=None)


@functools.cache
def _adjtimex() -> ctypes._CFuncPtr | None:  # type: ignore[name-defined]
    if not sys.platform.startswith("linux"):
        return None
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name, use_errno=True)
    except OSError:
        return None
    call = getattr(libc, "adjtimex", None)
    if call is not None:
        call.argtypes = [ctypes.POINTER(_Timex)]
        call.restype = ctypes.c_int
    return call


def clock_status() -> ClockStatus:
    call = _adjtimex()
    if call is None:
        return UNKNOWN
    timex = _Timex()  # modes 0: read only
    state = call(ctypes.byref(timex))
    if state < 0:
        return UNKNOWN
    synced = state != _TIME_ERROR and not timex.status & _STA_UNSYNC
    return ClockStatus(synchronized=synced, source="ntp" if synced else "none",
                       error_ms=round(timex.esterror / 1000.0, 3) if synced else None)
