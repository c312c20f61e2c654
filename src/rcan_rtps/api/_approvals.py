"""Approvals for the WebSocket: the held commands, pushed to approvers at each change.

An approver's socket gets `{"type": "approvals", "body": {"pending": [PENDING_AUTH, ...]}}`
(the body of `GET /api/hitl/pending`) when it opens and whenever the list changes: a command
held, an approval counted (n-of-m), one approved, denied, withdrawn or expired. The HiTL desk
says so through the governance channel (which also fires for the e-stop latch: a socket is
never sent the list it was sent last). A subscriber that falls behind only ever gets the
newest list.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

import msgspec

from rcan_rtps.rcan import PendingAuth

from ._bodies import PendingList
from ._wakeup import Wakeup


class ApprovalsSubscription:
    def __init__(self, feed: ApprovalsFeed) -> None:
        self._feed = feed
        self._latest: PendingList | None = None
        self._offered: bytes | None = None  # the encoding of the last list offered
        self._ready = asyncio.Event()

    def offer(self, pending: PendingList, encoded: bytes) -> None:
        if encoded == self._offered:  # e.g. the latch flipped: the list is what it was
            return
        self._offered = encoded
        self._latest = pending
        self._ready.set()

    async def next(self) -> PendingList:
        await self._ready.wait()
        self._ready.clear()
        assert self._latest is not None
        return self._latest

    def close(self) -> None:
        self._feed.unsubscribe(self)


class ApprovalsFeed:
    """Fans the pending list out; `changed` is safe from any thread once `start`ed."""

    def __init__(self, pending: Callable[[], list[PendingAuth]]) -> None:
        self._pending = pending
        self._subscribers: set[ApprovalsSubscription] = set()
        self._wakeup = Wakeup(self._refresh)

    def start(self) -> None:
        self._wakeup.start()

    def close(self) -> None:
        self._wakeup.close()

    def changed(self) -> None:
        self._wakeup.changed()

    def subscribe(self) -> ApprovalsSubscription:
        """The list as it is now first, then each change."""
        subscription = ApprovalsSubscription(self)
        self._subscribers.add(subscription)
        subscription.offer(*self._now())
        return subscription

    def unsubscribe(self, subscription: ApprovalsSubscription) -> None:
        self._subscribers.discard(subscription)

    @property
    def subscribers(self) -> int:
        return len(self._subscribers)

    def _refresh(self) -> None:
        current = self._now()
        for subscription in list(self._subscribers):
            subscription.offer(*current)

    def _now(self) -> tuple[PendingList, bytes]:
        current = PendingList(pending=self._pending())
        return current, msgspec.json.encode(current)
