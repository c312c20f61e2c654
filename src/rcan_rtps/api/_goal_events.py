"""Goal events for the WebSocket: every change of a goal (feedback, state, end).

A subscriber that falls behind keeps only the newest view of each goal, so memory stays
bounded by the goals the bridge tracks and the last thing sent about a goal is its latest
state (a terminal one is never replaced by older feedback).
"""

from __future__ import annotations

import asyncio

from .ports import GoalView

MAX_PENDING_GOALS = 256  # beyond this many goals untaken, the oldest is dropped


class GoalSubscription:
    def __init__(self, events: GoalEvents) -> None:
        self._events = events
        self._pending: dict[str, GoalView] = {}  # insertion order: oldest change first
        self._ready = asyncio.Event()

    def offer(self, view: GoalView) -> None:
        self._pending.pop(view.goal_id, None)
        self._pending[view.goal_id] = view
        if len(self._pending) > MAX_PENDING_GOALS:
            del self._pending[next(iter(self._pending))]
        self._ready.set()

    async def next(self) -> GoalView:
        while not self._pending:
            self._ready.clear()
            await self._ready.wait()
        goal_id = next(iter(self._pending))
        return self._pending.pop(goal_id)

    def close(self) -> None:
        self._events.unsubscribe(self)


class GoalEvents:
    """Fans goal views out to subscribers; `offer` is called on the event loop."""

    def __init__(self) -> None:
        self._subscribers: set[GoalSubscription] = set()

    def offer(self, view: GoalView) -> None:
        for subscription in list(self._subscribers):
            subscription.offer(view)

    def subscribe(self) -> GoalSubscription:
        subscription = GoalSubscription(self)
        self._subscribers.add(subscription)
        return subscription

    def unsubscribe(self, subscription: GoalSubscription) -> None:
        self._subscribers.discard(subscription)

    @property
    def subscribers(self) -> int:
        return len(self._subscribers)
