"""How much the bridge tells the audit (and the log) of what other DDS participants do.

Any participant on the domain may appear and leave as often as it likes, unauthenticated; each
appearance told is a signed, durable audit entry. `ReportBudget` holds one token bucket per
participant and one for all of them: an event is told while both have a token, and counted
otherwise (bridge/commanders.py sums the counted ones up, once per interval). A participant's
bucket is dropped once full again (a full bucket is a new one), so churning participants cost
no memory beyond what the shared bucket let through.
"""

from __future__ import annotations

from collections.abc import Hashable
from typing import Generic, TypeVar

K = TypeVar("K", bound=Hashable)


class Bucket:
    """`burst` tokens, one more each `refill_s` seconds (continuously), up to `burst`."""

    __slots__ = ("_at", "_tokens", "burst", "refill_s")

    def __init__(self, burst: float, refill_s: float, now: float) -> None:
        self.burst, self.refill_s = burst, refill_s
        self._tokens, self._at = burst, now

    def level(self, now: float) -> float:
        return min(self.burst, self._tokens + max(0.0, now - self._at) / self.refill_s)

    def spend(self, now: float) -> None:
        self._tokens, self._at = self.level(now) - 1.0, max(now, self._at)


class ReportBudget(Generic[K]):
    """A bucket per key and one shared: `take(key, now)` spends a token of each, or none."""

    def __init__(self, *, key_burst: float, key_refill_s: float, all_burst: float,
                 all_refill_s: float, now: float) -> None:
        self._key_burst, self._key_refill_s = key_burst, key_refill_s
        self._all = Bucket(all_burst, all_refill_s, now)
        self._keys: dict[K, Bucket] = {}

    def take(self, key: K, now: float) -> bool:
        bucket = self._keys.get(key) or Bucket(self._key_burst, self._key_refill_s, now)
        if bucket.level(now) < 1.0 or self._all.level(now) < 1.0:
            return False
        bucket.spend(now)
        self._all.spend(now)
        self._keys[key] = bucket
        return True

    def prune(self, now: float) -> None:
        """Forgets the keys whose bucket is full again."""
        self._keys = {k: b for k, b in self._keys.items() if b.level(now) < b.burst}

    def __len__(self) -> int:
        return len(self._keys)
