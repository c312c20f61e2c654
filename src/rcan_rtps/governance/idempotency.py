"""Retries of client-supplied message ids: the first outcome again, nothing executed twice.

Bounded in time (`ttl_s`) and size (`max_entries`): memory never grows with the number of
commands served. Only ids a client chose are kept (a generated id can never be retried). An id
reused for a different command (another action or other parameters) is a conflict, not a retry.
Outcomes live in memory, so a start remembers the keys the audit log shows an earlier run
decided within the ttl (`remember_decided`): their retry is refused, never run a second time.
"""

from __future__ import annotations

import asyncio
from collections import OrderedDict
from collections.abc import Hashable, Iterable
from typing import Generic, TypeVar

from .clock import Clock

K = TypeVar("K", bound=Hashable)
T = TypeVar("T")


class Conflict:
    """`claim`'s answer when the key was used for a different command."""


CONFLICT = Conflict()


class DecidedBefore:
    """`claim`'s answer for a key an earlier run decided: its outcome is in the audit log, not
    here, and what it decided must not be done twice."""


DECIDED_BEFORE = DecidedBefore()


class Idempotency(Generic[K, T]):
    """First outcome per key; concurrent duplicates wait for the first one."""

    def __init__(self, clock: Clock, ttl_s: float = 600.0, max_entries: int = 10_000) -> None:
        self._clock = clock
        self.ttl_s = ttl_s
        self._max = max_entries
        self._entries: OrderedDict[K, tuple[float, bytes, asyncio.Future[T]]] = OrderedDict()
        self._before: dict[K, float] = {}  # key → when an earlier run decided it (monotonic)

    def __len__(self) -> int:
        return len(self._entries)

    def remember_decided(self, decided: Iterable[tuple[K, float]]) -> int:
        """At start: the keys an earlier run decided, each with its age (s), kept for what is
        left of the ttl (at most `max_entries`). Returns how many.

        A negative age (logged ahead of the clock now: it was stepped back between the runs,
        or this start came before NTP set it) is kept the whole ttl: how long ago it was
        decided is unknown, and its retry must not run a second time."""
        now = self._clock.monotonic()
        for key, age_s in decided:
            if len(self._before) >= self._max:
                break
            if age_s < self.ttl_s:
                self._before.setdefault(key, now - max(0.0, age_s))
        return len(self._before)

    def claim(self, key: K, fingerprint: bytes
              ) -> asyncio.Future[T] | Conflict | DecidedBefore | None:
        """The earlier outcome (a future), CONFLICT, DECIDED_BEFORE (an earlier run's), or None
        after reserving `key`."""
        self._prune()
        before = self._before.get(key)
        if before is not None:
            if self._clock.monotonic() - before < self.ttl_s:
                return DECIDED_BEFORE
            del self._before[key]  # its ttl is over: a new first time
        seen = self._entries.get(key)
        if seen is not None:
            return seen[2] if seen[1] == fingerprint else CONFLICT
        future: asyncio.Future[T] = asyncio.get_running_loop().create_future()
        self._entries[key] = (self._clock.monotonic(), fingerprint, future)
        return None

    def resolve(self, key: K, value: T) -> None:
        seen = self._entries.get(key)
        if seen is not None and not seen[2].done():
            seen[2].set_result(value)

    def abandon(self, key: K, exc: BaseException) -> None:
        """No outcome was reached: waiters get the error, and a retry may run again."""
        seen = self._entries.pop(key, None)
        if seen is not None and not seen[2].done():
            seen[2].set_exception(exc)
            seen[2].exception()  # mark retrieved: nobody may be waiting

    def _prune(self) -> None:
        horizon = self._clock.monotonic() - self.ttl_s
        # Oldest first: expired ones always go; beyond the size bound the oldest decided go
        # too (a retry that late gets a fresh decision rather than unbounded memory).
        while self._entries:
            key, (at, _, future) = next(iter(self._entries.items()))
            if not future.done():
                break
            if at > horizon and len(self._entries) < self._max:
                break
            del self._entries[key]
