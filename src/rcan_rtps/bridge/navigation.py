"""Goals on one action server (nav2 NavigateToPose, DockRobot, ...), tracked for
GET /api/goals/{goal_id}; `bridge.goals` holds one tracker per goal route.

A tracker made at start lists its goals and cancels every goal of its server (a stop), its
cancel client kept ready (`keep_cancel_ready`). Sending goals and following them to their
end (`sent_goals.SentGoals`) is loaded with its first goal: a bridge never asked to
`navigate` or `dock` does not hold that code, and no stop runs it (issue 27: idle memory).
"""

from __future__ import annotations

import asyncio
import logging
import time
import uuid
from typing import TYPE_CHECKING, Any

from ..api.ports import GoalView
from ..events import Events
from ..ros.actions import ActionClient
from ..ros.errors import ActionError, WireError
from ..ros.participant import RosNode
from ..ros.services import RequestMapping

if TYPE_CHECKING:
    from .sent_goals import SentGoals

log = logging.getLogger(__name__)
NAVIGATE_TO_POSE = "nav2_msgs/action/NavigateToPose"
TERMINAL = {"succeeded", "canceled", "aborted", "rejected", "lost"}
CANCEL_READY_PERIOD_S = 1.0  # s: how often a tracker looks whether a server (re)appeared


def now_ms() -> int:
    return int(time.time() * 1000)


class GoalTracker:
    """Sends goals to one action server (of one type) and follows them (`SentGoals`, made
    by the first goal); cancels every goal of that server."""

    def __init__(self, node: RosNode, action: str, type_name: str = NAVIGATE_TO_POSE, *,
                 keep: int = 200, mapping: RequestMapping = RequestMapping.AUTO,
                 events: Events | None = None) -> None:
        self.node = node
        self.client = ActionClient(node, action, type_name, mapping=mapping, governed=True)
        self._views: dict[str, GoalView] = {}
        self._keep = keep
        self._sent: SentGoals | None = None  # made by the first goal
        # Told when the active goals change (`robot`), of any change (`goal`, a copy) and of
        # each goal's end, once (`goal_finished`).
        self.events = events or Events()
        self._cancel_ready_for = 0  # the server match the cancel client was prepared for
        self._preparing: asyncio.Task[None] | None = None
        # Stops so far (`cancel_all`): a goal that was being sent across one is cancelled.
        # Every server-wide cancel is a stop the governor counts too (`stop`, e-stop, a
        # session loss that halts the whole robot, shutdown), and it answers the failed send
        # `stopped`; a session loss while another principal's goal is being sent halts
        # nothing robot-wide, so it never reaches here.
        self._stops = 0

    @property
    def action_name(self) -> str:
        return self.client.name

    @property
    def type_name(self) -> str:
        return self.client.type_name

    async def send(self, goal: dict[str, Any], timeout: float, *,
                   message_id: str | None = None, command: str | None = None,
                   goal_id: str | None = None) -> str:
        """Sends a goal (for the command `message_id` of action `command`, with the id
        `goal_id` if given); its id once accepted. Raises on rejection, or when no server
        answers within `timeout`."""
        stops = self._stops
        if self._sent is None:
            from .sent_goals import SentGoals  # a goal is a move, never a stop

            self._sent = SentGoals(self.client, self._views, self.events, self._keep)
        goal_id = await self._sent.send(goal, timeout, message_id=message_id, command=command,
                                        goal_id=goal_id)
        if self._stops != stops:
            await self._stopped_while_sent(goal_id)
        return goal_id

    async def _stopped_while_sent(self, goal_id: str) -> None:
        """A stop came while the goal was on its way: its server-wide cancel may have reached
        the server first (a server cancels only the goals it has), so this one is cancelled
        now and the command refused (fails closed: the stop wins)."""
        assert self._sent is not None
        log.warning("a stop came while goal %s was being sent to %s: cancelling it", goal_id,
                    self.client.name)
        if not await self._sent.cancel(goal_id):
            await self.cancel_all()  # not confirmed: every goal of the server, again
        raise ActionError(f"a stop came while the goal was being sent to {self.client.name}: "
                          f"goal {goal_id} cancelled")

    async def cancel_all(self) -> int:
        """Cancels every goal on the server, whoever sent it: `stop` means stop."""
        self._stops += 1  # before any await: a goal being sent now is cancelled once accepted
        if not self.client.server_present():
            return 0  # nothing to cancel, and no reason to wait for a server to appear
        try:
            return await self.client.cancel_all(timeout=2.0, server_wide=True)
        except WireError:
            log.info("no action server on %s: no goals to cancel", self.client.name)
            return 0

    async def cancel(self, goal_id: str) -> bool:
        """Cancels one goal this bridge sent; True if the server is canceling it."""
        return self._sent is not None and await self._sent.cancel(goal_id)

    def unsettled(self) -> list[tuple[str, str | None, str | None]]:
        """(goal id, command, action) of each goal whose send gave up that the server may
        still accept or run (`SentGoals.unsettled`)."""
        return [] if self._sent is None else self._sent.unsettled()

    def not_seen_ended(self) -> list[tuple[str, str | None, str | None]]:
        """(goal id, command, action) of each goal of this run that the server may still run
        though a stop's cancel may not have reached it (`SentGoals.not_seen_ended`)."""
        if self._sent is None:
            return []
        return self._sent.not_seen_ended(self.client.server_present())

    def may_run(self, goal_id: str) -> bool:
        """Whether the server may run `goal_id` though its send failed: the send gave up
        after its request went out (the server may accept it late: watched for), or it was
        accepted and is being cancelled (a stop came while it was on its way) — not when
        the server refused it."""
        return self.client.watching_late(uuid.UUID(goal_id).bytes) or goal_id in self.active()

    async def cancel_left(self, goal_id: str | None, timeout: float) -> bool:
        """Cancels a goal a crashed run of the bridge left, by its id (any client may), or
        with no id known every goal of the server (as a stop does); waits up to `timeout`
        for the server. True if the server is canceling it (them)."""
        if goal_id is None:
            await self.client.prepare_cancel(timeout)
            return await self.client.cancel_all(timeout, server_wide=True) > 0
        return await self.client.cancel_goal_id(uuid.UUID(goal_id).bytes, timeout)

    def watch_left(self, goal_id: str, timeout: float, *, message_id: str | None,
                   command: str | None) -> None:
        """Watches for the server accepting late a goal a crashed run left that it is not
        running now: its send may have given up on a server still holding the request. It
        is cancelled as soon as it is listed running, and audited, as a goal whose send gave
        up in this run (`SentGoals.watch_left`)."""
        if self._sent is None:
            from .sent_goals import SentGoals  # (a goal was sent: by the crashed run)

            self._sent = SentGoals(self.client, self._views, self.events, self._keep)
        self._sent.watch_left(goal_id, timeout, message_id=message_id, command=command)

    def warn_cancelling(self, why: str) -> None:
        """Logs each active goal about to be cancelled, and why."""
        for goal_id in self.active():
            feedback = self._views[goal_id].feedback or {}
            left = feedback.get("distance_remaining")
            where = f", {left:.2f} m from its target" if isinstance(left, float) else ""
            log.warning("cancelling %s goal %s on %s%s: %s", self.type_name.rsplit("/", 1)[-1],
                        goal_id, self.client.name, where, why)

    def active(self) -> list[str]:
        return [g for g, v in self._views.items() if v.state not in TERMINAL]

    def goal(self, goal_id: str) -> GoalView | None:
        return self._views.get(goal_id)

    def goals(self) -> list[GoalView]:
        return sorted(self._views.values(), key=lambda v: v.created_ms)

    def keep_cancel_ready(self, period: float = CANCEL_READY_PERIOD_S) -> None:
        """From now on, whenever a server appears (or comes back), makes its cancel client
        ready, so that a stop's server-wide cancel makes no endpoints and waits for no
        discovery: goals sent by others (RViz, a script) are cancelled by a stop, and the
        first stop after a server appeared must not be its cancel client's first use."""
        if self._preparing is None:
            self._preparing = asyncio.get_running_loop().create_task(
                self._keep_cancel_ready(period))

    async def _keep_cancel_ready(self, period: float) -> None:
        while True:
            matches = self.client.status_matches()  # one C call: cheap at idle
            if matches != self._cancel_ready_for and self.client.server_present():
                try:
                    await self.client.prepare_cancel()
                    self._cancel_ready_for = matches
                except WireError as exc:  # not answered in time: tried again next period
                    log.debug("%s: cancel client not ready yet: %s", self.client.name, exc)
            await asyncio.sleep(period)

    @property
    def cancel_ready(self) -> bool:
        """Whether the cancel client was made ready for the server now on the graph."""
        return self._cancel_ready_for == self.client.status_matches() != 0

    async def close(self) -> None:
        """Stops following goals (they go on on the server) and leaves; idempotent."""
        if self._preparing is not None:
            self._preparing.cancel()
            await asyncio.gather(self._preparing, return_exceptions=True)
        if self._sent is not None:
            await self._sent.close()
        self.client.close()
