"""Every goal action the registry declares, each on its own action server.

One `GoalTracker` (one action client) per distinct (configured action name, action type) of
the registry's `SendGoal` routes: `navigate` reaches the NavigateToPose server named by
`bridge.ros2.nav_action`, `dock` the DockRobot server named by `dock_action`. The config has
already refused two types on one server (`config._model.goal_routes_problem`). A key set to
null names no server: that route has no tracker (its goals are refused), and with no tracker
at all the action client's modules are never imported.

What concerns goals as a whole spans every tracker: a stop cancels goals on every server, the
API lists every goal, and listeners (STATUS, WebSocket goal events, the audit's GOAL_FINISHED)
hear from all of them. STATUS `navigation` stays NavigateToPose's.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from ..api.ports import GoalView
from ..config import Ros2Config
from ..events import Events
from ..rcan import Navigation
from ..rcan.actions import GoalRoute, goal_routes
from ..rcan.actions.navigate import NAVIGATE_TO_POSE
from ..ros.participant import RosNode

if TYPE_CHECKING:
    from ..ros.services import RequestMapping
    from .navigation import GoalTracker

log = logging.getLogger(__name__)


def route_mapping(ros2: Ros2Config, action_key: str) -> RequestMapping:
    """The configured request-reply mapping of a goal route (its name's override first)."""
    from ..ros.services import RequestMapping

    name = getattr(ros2, action_key)
    return RequestMapping(ros2.request_mappings.get(name, ros2.request_mapping))


SETTLE_POLL_S = 0.05  # s between looks at the watched goals while the bridge leaves
# What a server answers for a goal it does not have running (it ended, or never was).
CANCELING_NOTHING = "its server is canceling nothing (it had ended?)"


class GoalRoutes:
    """The bridge's goals: one tracker per goal route, found by the route's config key."""

    def __init__(self, node: RosNode, ros2: Ros2Config,
                 routes: tuple[GoalRoute, ...] | None = None,
                 events: Events | None = None) -> None:
        # Every tracker tells the same events: whoever listens hears of all goals.
        self.events = events or Events()
        self._by_key: dict[str, GoalTracker] = {}
        trackers: dict[tuple[str, str], GoalTracker] = {}
        named = [r for r in (goal_routes() if routes is None else routes)
                 if getattr(ros2, r.action_key) is not None]  # null: the robot has no such server
        if named:
            # Here, at start: the stop path (`cancel_all`) never waits for an import.
            from .navigation import GoalTracker
        for route in named:
            server = (ros2.resolve(getattr(ros2, route.action_key)), route.type_name)
            tracker = trackers.get(server)
            if tracker is None:
                tracker = trackers[server] = GoalTracker(
                    node, getattr(ros2, route.action_key), route.type_name,
                    mapping=route_mapping(ros2, route.action_key), events=self.events)
            self._by_key[route.action_key] = tracker
        self.trackers: tuple[GoalTracker, ...] = tuple(trackers.values())

    def tracker(self, action_key: str) -> GoalTracker | None:
        """The tracker of the server a route's config key names."""
        return self._by_key.get(action_key)

    def action_name(self, action_key: str) -> str | None:
        tracker = self._by_key.get(action_key)
        return tracker.action_name if tracker is not None else None

    async def send(self, action_key: str, goal: dict[str, Any], timeout: float, *,
                   message_id: str | None = None, command: str | None = None,
                   goal_id: str | None = None) -> str:
        """Sends a goal to its route's own server (with the id `goal_id` if given); its id
        once accepted. Raises on rejection or unavailability, and LookupError for a route
        the registry did not declare."""
        tracker = self._by_key.get(action_key)
        if tracker is None:
            raise LookupError(f"no goal route `{action_key}`")
        return await tracker.send(goal, timeout, message_id=message_id, command=command,
                                  goal_id=goal_id)

    async def cancel_all(self) -> int:
        """Cancels every goal on every goal server, whoever sent it: `stop` means stop. The
        servers are asked at once, so one slow server does not hold the others' cancel."""
        counts = await asyncio.gather(*(t.cancel_all() for t in self.trackers),
                                      return_exceptions=True)
        for tracker, count in zip(self.trackers, counts, strict=True):
            if isinstance(count, BaseException):
                log.error("cancelling goals on %s failed: %s", tracker.action_name, count)
        return sum(c for c in counts if isinstance(c, int))

    async def cancel_left(self, server: str | None, goal_id: str | None,
                          timeout: float, *, message_id: str | None = None,
                          command: str | None = None) -> str | None:
        """Cancels a goal a crashed run left on `server` (`GoalTracker.cancel_left`; on
        every goal server when that one is no longer configured: an id names one goal
        wherever it is). None once a server is canceling it, else why not. One no server
        is canceling is watched for (`GoalTracker.watch_left`): its send may have given up
        on a server that has not accepted it yet (the command `message_id` of `command`)."""
        trackers = [t for t in self.trackers if t.action_name == server] or self.trackers
        if not trackers:
            return "no goal server is configured"
        outcomes = await asyncio.gather(*(t.cancel_left(goal_id, timeout) for t in trackers),
                                        return_exceptions=True)
        if any(o is True for o in outcomes):
            return None
        if goal_id is not None:
            for tracker in trackers:
                tracker.watch_left(goal_id, timeout, message_id=message_id, command=command)
        errors = [f"{type(o).__name__}: {o}" for o in outcomes if isinstance(o, BaseException)]
        return "; ".join(errors) or CANCELING_NOTHING

    def unsettled(self) -> list[tuple[str, str, str | None, str | None]]:
        """(server, goal id, command, action) of each goal whose send gave up that its
        server may still accept or run: watched for, not yet seen ended or canceling."""
        return [(t.action_name, *goal) for t in self.trackers for goal in t.unsettled()]

    def not_seen_ended(self) -> list[tuple[str, str, str | None, str | None]]:
        """(server, goal id, command, action) of each goal of this run whose end was not
        seen that a stop's cancel may not have reached (`GoalTracker.not_seen_ended`)."""
        return [(t.action_name, *goal) for t in self.trackers for goal in t.not_seen_ended()]

    async def settle(self, timeout: float) -> None:
        """Waits up to `timeout` for the goals whose send gave up to settle (each watch
        cancels its goal as soon as the server lists it): the bridge is leaving, and its
        watches end with it."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while self.unsettled() and loop.time() < deadline:
            await asyncio.sleep(SETTLE_POLL_S)

    def may_run(self, goal_id: str) -> bool:
        """Whether a goal whose send failed may run on its server all the same
        (`GoalTracker.may_run`): its command's COMMAND_FAILED names it, for a crash's
        restart to cancel."""
        return any(t.may_run(goal_id) for t in self.trackers)

    async def cancel(self, goal_id: str) -> bool:
        """Cancels one goal this bridge sent, on its own server; True if it is canceling."""
        for tracker in self.trackers:
            if tracker.goal(goal_id) is not None:
                return await tracker.cancel(goal_id)
        return False

    def warn_cancelling(self, why: str) -> None:
        for tracker in self.trackers:
            tracker.warn_cancelling(why)

    def navigation(self) -> Navigation | None:
        """STATUS `navigation`: the newest active NavigateToPose goal and its progress."""
        navigating = self._active_views(lambda t: t.type_name == NAVIGATE_TO_POSE)
        if not navigating:
            return None
        from .sent_goals import navigation_summary  # loaded by the first goal

        return navigation_summary(navigating[-1])

    def active(self) -> list[str]:
        """The goals not yet ended, on every server, oldest first."""
        return [v.goal_id for v in self._active_views(lambda t: True)]

    def _active_views(self, which: Callable[[GoalTracker], bool]) -> list[GoalView]:
        views = [t.goal(g) for t in self.trackers if which(t) for g in t.active()]
        return sorted((v for v in views if v is not None), key=lambda v: v.created_ms)

    def goal(self, goal_id: str) -> GoalView | None:
        for tracker in self.trackers:
            view = tracker.goal(goal_id)
            if view is not None:
                return view
        return None

    def goals(self) -> list[GoalView]:
        """Every goal tracked, on every server, oldest first."""
        return sorted((v for t in self.trackers for v in t.goals()), key=lambda v: v.created_ms)

    def start(self) -> None:
        """Each server's cancel client is made ready as the server appears (the stop path)."""
        for tracker in self.trackers:
            tracker.keep_cancel_ready()

    async def close(self) -> None:
        """Stops following goals (they go on on their servers) and leaves; idempotent."""
        await asyncio.gather(*(t.close() for t in self.trackers))
