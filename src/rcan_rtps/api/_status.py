"""The one owner of STATUS for every transport (REST, WebSocket, metrics, and what comes later).

It holds a read-only snapshot and pushes it to subscribers: at once when something that matters
changes (state, e-stop, faults, pending approvals, goals, connectivity, battery, other
publishers on the command topics), and at the telemetry rate. Nobody polls: a transport
subscribes and sends what it is handed. A subscriber that cannot keep up only ever gets the
newest snapshot, so memory stays bounded.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Callable
from typing import Any

from ..rcan import Status
from ._wakeup import Wakeup

log = logging.getLogger(__name__)


def _what_matters(status: Status) -> tuple[Any, ...]:
    """The parts of STATUS whose change is pushed at once (positions wait for the tick)."""
    return (status.state, status.estop, tuple((f.name, f.level, f.message) for f in status.faults),
            status.pending_auth, tuple(status.active_goals), status.ros.connected,
            status.battery_pct, _navigation_matters(status), status.foreign_publishers_count,
            tuple((f.topic, f.participant, f.node, f.expected)
                  for f in status.foreign_publishers))


def _navigation_matters(status: Status) -> tuple[Any, ...] | None:
    # A recovery or a new state is pushed at once; the distance left waits for the tick.
    nav = status.navigation
    return None if nav is None else (nav.goal_id, nav.state, nav.recoveries)


class StatusSubscription:
    """The newest snapshot for one subscriber; older ones it did not take are dropped."""

    def __init__(self, hub: StatusHub) -> None:
        self._hub = hub
        self._latest: Status | None = None
        self._ready = asyncio.Event()

    def offer(self, status: Status) -> None:
        self._latest = status
        self._ready.set()

    async def next(self) -> Status:
        await self._ready.wait()
        self._ready.clear()
        assert self._latest is not None
        return self._latest

    def close(self) -> None:
        self._hub.unsubscribe(self)

    def __aiter__(self) -> AsyncIterator[Status]:
        return self._iterate()

    async def _iterate(self) -> AsyncIterator[Status]:
        while True:
            yield await self.next()


class StatusHub:
    def __init__(self, compute: Callable[[], Status], period_s: float) -> None:
        self._compute = compute
        self._period = period_s
        self._subscribers: set[StatusSubscription] = set()
        self._latest: Status | None = None
        self._wakeup = Wakeup(self._refresh)
        self._failing = False
        self._ticker: asyncio.Task[None] | None = None

    # -- reading ---------------------------------------------------------------------------
    def snapshot(self) -> Status:
        """STATUS now: computed afresh, so a reply never shows less than its caller caused."""
        status = self._compute()
        self._take(status, tick=False)
        return status

    def subscribe(self) -> StatusSubscription:
        """Snapshots as they come; the current one first."""
        subscription = StatusSubscription(self)
        self._subscribers.add(subscription)
        latest = self._latest if self._latest is not None else self._try_compute()
        if latest is not None:
            subscription.offer(latest)
        return subscription

    def unsubscribe(self, subscription: StatusSubscription) -> None:
        self._subscribers.discard(subscription)

    @property
    def subscribers(self) -> int:
        return len(self._subscribers)

    # -- being told ------------------------------------------------------------------------
    def changed(self) -> None:
        """Something STATUS is made of may have changed; safe from any thread."""
        self._wakeup.changed()

    def _refresh(self) -> None:
        status = self._try_compute()
        if status is not None:
            self._take(status, tick=False)

    # -- the tick --------------------------------------------------------------------------
    async def start(self) -> None:
        self._wakeup.start()
        if self._ticker is None:
            self._ticker = asyncio.create_task(self._tick(), name="status-hub")

    async def close(self) -> None:
        ticker, self._ticker = self._ticker, None
        if ticker is not None:
            ticker.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await ticker
        self._wakeup.close()

    async def _tick(self) -> None:
        while True:
            status = self._try_compute()
            if status is not None:
                self._take(status, tick=True)
            await asyncio.sleep(self._period)

    def _try_compute(self) -> Status | None:
        try:
            status = self._compute()
        except Exception:
            if not self._failing:  # a broken source is logged once, not at every tick
                log.exception("computing STATUS failed")
            self._failing = True
            return None
        self._failing = False
        return status

    def _take(self, status: Status, *, tick: bool) -> None:
        previous, self._latest = self._latest, status
        if tick or previous is None or _what_matters(previous) != _what_matters(status):
            for subscription in list(self._subscribers):
                subscription.offer(status)
