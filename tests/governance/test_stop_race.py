"""A motion command, then a stop a moment later: once both are decided the robot is still.

Whatever the interleaving — the stop arriving while the move or goal waits for its audit
entry, or while the goal is on its way to its server — motion decided before a stop must not
reach the robot after it (a stop's cancel reaches only the goals a server already has, and a
stream that starts after the stop's zero runs on)."""

from __future__ import annotations

import asyncio
import random
from typing import Any

from govhelpers import ADMIN, PLANNER, Harness, command

from rcan_rtps.governance.governor import Decision, Governor
from rcan_rtps.rcan import Outcome

TRIALS = 300
GOAL = {"x": 1.0, "y": 2.0, "yaw": 0.0}


async def _after(delay: float, coro: Any) -> Any:
    await asyncio.sleep(delay)
    return await coro


async def _race(gov: Governor, rng: random.Random, motion: Any) -> tuple[Decision, Decision]:
    """`motion` decided first, the stop from 0 to 3 ms later (often in the same loop turn)."""
    delay = rng.choice([0.0, rng.uniform(0, 0.003)])
    moved, stopped = await asyncio.gather(gov.decide(motion, PLANNER),
                                          _after(delay, gov.decide(command("stop"), ADMIN)))
    return moved, stopped


async def test_a_move_decided_before_a_stop_is_not_moving_after_it(harness: Harness) -> None:
    gov = await harness.governor()
    rng = random.Random(20261127)
    moving_after_stop: list[int] = []
    outcomes: dict[str, int] = {}
    for trial in range(TRIALS):
        moved, stopped = await _race(gov, rng, command("move", {"linear_x": 0.2}))
        assert stopped.outcome is Outcome.EXECUTED, trial
        key = moved.reason or moved.outcome.value
        outcomes[key] = outcomes.get(key, 0) + 1
        if gov.streams.active is not None:
            moving_after_stop.append(trial)
        await gov.decide(command("stop"), ADMIN)  # the next trial starts still
    assert moving_after_stop == [], f"moving after the stop in trials {moving_after_stop}"
    # both sides of the race were exercised: moves ended by the stop, and moves it refused
    assert outcomes.get("executed", 0) > TRIALS // 20 and outcomes.get("stopped", 0), outcomes
    await gov.stop()


async def test_a_goal_decided_before_a_stop_is_cancelled_by_it(harness: Harness) -> None:
    gov = await harness.governor()
    rng = random.Random(20261128)
    left_running: list[int] = []
    outcomes: dict[str, int] = {}
    for trial in range(TRIALS):
        n_calls = len(harness.dispatcher.calls)
        sent, stopped = await _race(gov, rng, command("navigate", GOAL))
        assert stopped.outcome is Outcome.EXECUTED, trial
        key = sent.reason or sent.outcome.value
        outcomes[key] = outcomes.get(key, 0) + 1
        await asyncio.sleep(0)  # (a cancel the arbiter spawned gets its turn)
        calls = [a for a, _ in harness.dispatcher.calls[n_calls:]]
        if "navigate" in calls:
            # the goal went out: a halt after it (it cancels every goal), or its own cancel
            last_goal = len(calls) - 1 - calls[::-1].index("navigate")
            halted_after = "stop" in calls[last_goal + 1:]
            cancelled = f"goal-{harness.dispatcher._goals}" in harness.dispatcher.cancelled
            if not halted_after and not cancelled:
                left_running.append(trial)
        await gov.decide(command("stop"), ADMIN)
    assert left_running == [], f"a goal left running after the stop in trials {left_running}"
    assert outcomes.get("executed", 0) > TRIALS // 20 and outcomes.get("stopped", 0), outcomes
    await gov.stop()
