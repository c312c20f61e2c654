"""The one recording `Dispatcher` of the tests: what governance hands the bridge, no DDS.

Records each dispatch as (action, applied parameters as a dict). It can report the robot
unreachable (`available = False`), raise (`raises`), or hold motion until released: in its
dispatch (`hold`, then `entered`) or in its readiness check (`hold_ready`, then `ready_entered`).
"""

from __future__ import annotations

import asyncio
from collections.abc import Collection
from typing import Any

import msgspec

from rcan_rtps.governance import ArmsHeld, DispatchResult
from rcan_rtps.governance.left import LeftGoal, LeftRunning
from rcan_rtps.governance.steps import LeftHalted
from rcan_rtps.rcan import ActionParams, MoveParams, NormalizedCommand

UNAVAILABLE = "no subscriber on /robot1/cmd_vel"


class RecordingDispatcher:
    def __init__(self) -> None:
        self.calls: list[tuple[str, dict[str, Any]]] = []
        self.available = True
        self.raises: Exception | None = None
        self.hold: asyncio.Event | None = None  # when set: motion waits for it
        self.entered = asyncio.Event()  # a held dispatch has started
        self.hold_ready: asyncio.Event | None = None  # when set: motion's `ready` waits for it
        self.ready_entered = asyncio.Event()  # a held readiness check has started
        self.samples: list[MoveParams] = []  # velocity-stream samples after each first one
        self.cancelled: list[str] = []  # goals cancelled one by one (the arbiter's)
        self.signals: list[int] = []  # e-stop signals published as the latch engaged
        self._goals = 0
        self.running: list[str] = []  # message ids of arm trajectories still running
        self._arm_topics: dict[str, str] = {}  # an arm trajectory's message id → its topic
        self.holds: list[list[str]] = []  # `hold_trajectories` calls: the ids it held
        self.unheard_arms = False  # when set: no arm can be held (no joint_states heard)
        self.left: list[LeftRunning] = []  # `halt_left` calls: what a crashed run left
        self.halt_hold: asyncio.Event | None = None  # when set: `halt_left` waits for it
        # A goal's send: "rejected" by its server, or "gave up" (no reply in time: its
        # server may accept it late); None: accepted.
        self.goal_send: str | None = None
        self.watched: list[LeftGoal] = []  # goals whose send gave up, not yet settled

    def route(self, command: NormalizedCommand) -> str | None:
        return f"/robot1/{command.action}"

    async def ready(self, command: NormalizedCommand) -> str | None:
        if self.hold_ready is not None and command.spec.motion:
            self.ready_entered.set()
            await self.hold_ready.wait()
        return None if self.available else UNAVAILABLE

    async def dispatch(self, command: NormalizedCommand,
                       applied: ActionParams) -> DispatchResult:
        assert isinstance(applied, command.spec.params), "the typed path must stay typed"
        if self.raises is not None:
            raise self.raises
        if self.hold is not None and command.spec.motion:
            self.entered.set()
            await self.hold.wait()
        if not self.available:
            return DispatchResult(ok=False, detail=UNAVAILABLE)
        self.calls.append((command.action, msgspec.to_builtins(applied)))
        if command.spec.stopping:  # a halt of the robot holds every arm
            self.running.clear()
        goal_id = None
        if command.spec.starts_goal and self.goal_send is not None:
            may_run = command.goal_id if self.goal_send == "gave up" else None
            return DispatchResult(ok=False, detail=f"the goal's send: {self.goal_send}",
                                  goal_id=may_run)
        if command.spec.starts_goal:
            self._goals += 1
            goal_id = f"goal-{self._goals}"
        publishes = command.spec.ros.publishes() if command.spec.motion else ()
        hold = publishes[0].hold if publishes else None
        runs_for_s = hold.runs_for_s(applied) if hold is not None else None
        topic = f"/robot1/{command.action}"
        if runs_for_s is not None:  # an arm's trajectory: a topic per set of joints (per arm)
            topic += "/" + "-".join(getattr(applied, "joints", ()))
            # The arm's controller replaces the trajectory it ran with this one.
            self.running = [m for m in self.running if self._arm_topics.get(m) != topic]
            self._arm_topics[command.message_id] = topic
            self.running.append(command.message_id)
        return DispatchResult(ok=True, ros2_topic=topic, goal_id=goal_id,
                              runs_for_s=runs_for_s)

    def hold_trajectories(self, message_ids: Collection[str]) -> ArmsHeld:
        if self.unheard_arms:
            return ArmsHeld(not_held=tuple(f"{m} not held: no joint_states heard"
                                           for m in self.running if m in message_ids))
        held = [m for m in self.running if m in message_ids]
        self.running = [m for m in self.running if m not in message_ids]
        self.holds.append(held)
        return ArmsHeld(held=tuple(f"held {m}" for m in held))

    def running_trajectories(self) -> list[str]:
        return list(self.running)

    def goals_watched(self) -> list[LeftGoal]:
        return list(self.watched)

    async def halt_left(self, left: LeftRunning) -> LeftHalted:
        """A crashed run's motion taken back: recorded (`left`); each arm held unless
        `unheard_arms`, each goal with an id cancelled."""
        self.left.append(left)
        if self.halt_hold is not None:
            await self.halt_hold.wait()
        topics = tuple(a.topic or "" for a in left.arms)
        arms = (ArmsHeld(not_held=tuple(f"{t}: no joint_states heard" for t in topics))
                if self.unheard_arms else ArmsHeld(held=topics))
        return LeftHalted(zero_reached=True, arms=arms,
                          goals_cancelled=tuple(g.goal_id for g in left.goals if g.goal_id),
                          goals_not_cancelled=tuple(f"{g.message_id}: no id" for g in left.goals
                                                    if not g.goal_id),
                          still_left=tuple(a.message_id for a in left.arms
                                           if self.unheard_arms))

    async def cancel_goal(self, goal_id: str) -> bool:
        self.cancelled.append(goal_id)
        return True

    def signal_estop(self) -> None:
        self.signals.append(len(self.calls))  # how many dispatches came before it

    def send_velocity(self, velocity: MoveParams) -> str | None:
        if self.raises is not None:
            raise self.raises
        if not self.available and (velocity.linear_x or velocity.linear_y or velocity.angular_z):
            return UNAVAILABLE
        self.samples.append(velocity)
        return None
