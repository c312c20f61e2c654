"""Approvals for the WebSocket: the held commands, pushed to approvers at each change.

An approver's socket gets `{"type": "approvals", "body": {"pending": [PENDING_AUTH, ...]}}`
(the body of `GET /api/hitl/pending`) when it opens and whenever the list changes: a command
held, an approval counted (n-of-m), one approved, denied, withdrawn or expired. The HiTL desk
says so through the governance channel (which also fires for the e-stop latch: a socket is
never sent the list it was sent last). A subscriber that falls behind only ever gets the
newest list. Each gets the held commands it may read (`readable`): those it could approve,
and its own — not every one, because it may list some.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

import msgspec

from rcan_rtps.governance import Principal
from rcan_rtps.governance.review import may_read
from rcan_rtps.rcan import PendingAuth, Role

from ._bodies import PendingList
from ._wakeup import Wakeup


def readable(reader: Principal, pending: list[PendingAuth]) -> list[PendingAuth]:
    """The held commands `reader` may read, as `GET /api/hitl/pending/{id}` lets it: those it
    could approve, and its own. Whoever may list held commands (`hitl_list_role`, the lowest
    role any gate names) used to be shown every one — what it was told was not found by id."""
    return [p for p in pending
            if may_read(reader, p.issued_by, Role[p.requires_auth_from_role])]


class ApprovalsSubscription:
    def __init__(self, feed: ApprovalsFeed, reader: Principal) -> None:
        self._feed = feed
        self._reader = reader
        self._latest: PendingList | None = None
        self._offered: bytes | None = None  # the encoding of the last list offered
        self._ready = asyncio.Event()

    def offer(self, pending: list[PendingAuth]) -> None:
        mine = PendingList(pending=readable(self._reader, pending))
        encoded = msgspec.json.encode(mine)
        if encoded == self._offered:  # e.g. the latch flipped: the list is what it was
            return
        self._offered = encoded
        self._latest = mine
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

    def subscribe(self, reader: Principal) -> ApprovalsSubscription:
        """The list as it is now first, then each change: what `reader` may read of it."""
        subscription = ApprovalsSubscription(self, reader)
        self._subscribers.add(subscription)
        subscription.offer(self._pending())
        return subscription

    def unsubscribe(self, subscription: ApprovalsSubscription) -> None:
        self._subscribers.discard(subscription)

    @property
    def subscribers(self) -> int:
        return len(self._subscribers)

    def _refresh(self) -> None:
        current = self._pending()
        for subscription in list(self._subscribers):
            subscription.offer(current)
