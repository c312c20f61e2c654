"""A principal's connection closes while its move or goal is decided but not yet sent.

Motion opens its sender's control session only as it is sent (`Governor._sending`): before,
while it waits for the robot or for its write-ahead entry, its sender holds no session, and
`end_session` found nothing to end. The motion then started after its connection was gone and
ran until the session it opened timed out. Motion of a principal decided before its
connection closed must never start (refused 409 `stopped`, or cancelled once its goal is
accepted), and nobody else's motion is touched."""

from __future__ import annotations

import asyncio
import random
from collections.abc import Awaitable, Callable
from typing import Any

import pytest
from govhelpers import (
    ADMIN,
    OPS,
    PLANNER,
    Harness,
    LossTrial,
    command,
    held_motion_stopped,
    motion_held_at,
)

from rcan_rtps.governance.governor import MAX_IN_FLIGHT, Decision, Governor
from rcan_rtps.rcan import Outcome

TRIALS = 300
GOAL = {"x": 1.0, "y": 2.0, "yaw": 0.0}
MOTION = {"move": {"linear_x": 0.2}, "navigate": GOAL}


@pytest.mark.parametrize("where", ["ready", "write_ahead"])
@pytest.mark.parametrize("action", ["move", "navigate"])
async def test_motion_decided_before_its_connection_closed_never_starts(
        harness: Harness, action: str, where: str) -> None:
    """PLANNER alone: its motion waits (for the robot, or for its entry) when its connection
    closes. It is refused `stopped`; nothing of it reaches the robot. The loss is audited, of
    PLANNER's own motion (nothing else drives: nothing else to stop)."""
    gov = await harness.governor()
    lost = await held_motion_stopped(gov, harness, where,
                                     gov.decide(command(action, MOTION[action]), PLANNER),
                                     lambda: gov.end_session(PLANNER))
    assert lost is not None and lost.outcome is Outcome.EXECUTED, lost
    assert gov.streams.active is None and gov.streams.goals == {}
    assert [a for a, _ in harness.dispatcher.calls] == []  # nothing reached the robot
    assert harness.dispatcher.samples == []
    [entry] = [e for e in harness.entries if e["event"] == "NETWORK_LOSS_SAFE_STOP"]
    assert entry["applied"] == {"scope": "own", "goals_cancelled": [], "before_session": True}
    assert await gov.end_session(PLANNER) is None  # no session was opened meanwhile
    await gov.stop()


@pytest.mark.parametrize("action", ["move", "navigate"])
async def test_motion_waiting_its_turn_when_its_connection_closes_never_starts(
        harness: Harness, action: str) -> None:
    """PLANNER's motion arrived but waits to be admitted (MAX_IN_FLIGHT commands are being
    decided) when its connection closes: received before the close, it never starts."""
    gov = await harness.governor()
    for _ in range(MAX_IN_FLIGHT):  # every place taken
        await gov._admission.acquire()
    moving = asyncio.ensure_future(gov.decide(command(action, MOTION[action]), PLANNER))
    await asyncio.sleep(0.01)
    assert not moving.done()
    lost = await gov.end_session(PLANNER)
    assert lost is not None and lost.outcome is Outcome.EXECUTED, lost
    for _ in range(MAX_IN_FLIGHT):
        gov._admission.release()
    moved = await moving
    assert (moved.http_status, moved.reason) == (409, "stopped"), moved
    assert [a for a, _ in harness.dispatcher.calls] == [] and gov.streams.active is None
    await gov.stop()


@pytest.mark.parametrize("action", ["move", "navigate"])
async def test_motion_arriving_in_the_step_its_connection_closes_never_starts(
        harness: Harness, action: str) -> None:
    """The close handled in the same loop step as the motion's arrival, before its decision
    ran at all: it never starts either."""
    gov = await harness.governor()
    moved, lost = await asyncio.gather(gov.decide(command(action, MOTION[action]), PLANNER),
                                       gov.end_session(PLANNER))
    assert lost is not None and lost.outcome is Outcome.EXECUTED, lost
    assert (moved.http_status, moved.reason) == (409, "stopped"), moved
    assert [a for a, _ in harness.dispatcher.calls] == [] and gov.streams.active is None
    await gov.stop()


async def test_only_the_closed_principals_motion_on_its_way_stops(harness: Harness) -> None:
    """OPS drives, and OPS's next move and PLANNER's move both wait for their entries when
    PLANNER's connection closes: PLANNER's is refused, OPS's starts; nothing is halted."""
    gov = await harness.governor()
    await gov.decide(command("move", {"linear_x": 0.2}), OPS)
    release, entered = motion_held_at(gov, harness, "write_ahead")
    theirs = asyncio.ensure_future(gov.decide(command("move", {"linear_x": 0.3}), OPS))
    mine = asyncio.ensure_future(gov.decide(command("move", {"linear_x": 0.1}), PLANNER))
    await asyncio.wait_for(entered.wait(), timeout=10)
    await asyncio.sleep(0.01)  # both are waiting for their entries
    calls = len(harness.dispatcher.calls)
    lost = await gov.end_session(PLANNER)
    assert lost is not None and lost.outcome is Outcome.EXECUTED, lost
    assert len(harness.dispatcher.calls) == calls  # no halt of the robot
    release.set()
    ops, planner = await theirs, await mine
    assert ops.outcome is Outcome.EXECUTED, ops
    assert (planner.http_status, planner.reason) == (409, "stopped"), planner
    active = gov.streams.active
    assert active is not None and active.owner == OPS.name and active.target.linear_x == 0.3
    await gov.stop()


async def _ended_after(delay: float, gov: Governor) -> Decision | None:
    await asyncio.sleep(delay)
    return await gov.end_session(PLANNER)


@pytest.mark.parametrize("others", ["alone", "ops_drives"])
async def test_no_motion_decided_before_a_connection_closed_outlives_it(
        harness: Harness, others: str) -> None:
    """PLANNER's move or goal (the robot ready and its goal server answering within 4 ms,
    its entry written with others), and PLANNER's connection closing 0-3 ms later: once all
    is decided nothing of PLANNER's moves the robot — whether or not its motion had opened a
    session when the connection closed — and OPS's stream, when it drives, is left running
    unless PLANNER's motion had already taken the base from it."""
    gov = await harness.governor()
    rng = random.Random(20261201 + (others == "alone"))
    ready, dispatch = harness.dispatcher.ready, harness.dispatcher.dispatch

    def later(call: Callable[..., Awaitable[Any]], goals_only: bool
              ) -> Callable[..., Awaitable[Any]]:
        async def a_moment_later(cmd: Any, *args: Any) -> Any:
            if cmd.spec.starts_goal or not goals_only:
                await asyncio.sleep(rng.choice([0.0, rng.uniform(0, 0.004)]))
            return await call(cmd, *args)
        return a_moment_later

    harness.dispatcher.ready = later(ready, False)  # type: ignore[method-assign]
    harness.dispatcher.dispatch = later(dispatch, True)  # type: ignore[method-assign]
    outliving: list[tuple[int, str]] = []
    ops_stopped: list[int] = []
    seen: dict[str, int] = {}
    for trial in range(TRIALS):
        harness.clock.advance(60)  # a fresh rate budget (no sweeper runs here)
        if others == "ops_drives":
            await gov.decide(command("move", {"linear_x": 0.2}), OPS)
        action = rng.choice(list(MOTION))
        watched = LossTrial(harness.dispatcher)
        moved, _ = await asyncio.gather(
            gov.decide(command(action, MOTION[action]), PLANNER),
            _ended_after(rng.uniform(0, 0.003), gov))
        await asyncio.gather(*gov._tasks)  # cancels, STREAM_ENDED entries
        key = moved.reason or moved.outcome.value
        seen[key] = seen.get(key, 0) + 1
        active = gov.streams.active
        outliving += [(trial, what) for what in watched.outliving(gov, PLANNER)]
        if others == "ops_drives" and moved.reason == "stopped" and (
                active is None or active.owner != OPS.name):
            ops_stopped.append(trial)
        if await gov.end_session(PLANNER) is not None:  # a session left open after the close
            outliving.append((trial, "session"))
        await gov.decide(command("stop"), ADMIN)  # the next trial starts still
        await asyncio.gather(*gov._tasks)
    assert outliving == [], f"PLANNER's motion outlived its connection: {outliving}"
    assert ops_stopped == [], f"OPS's stream ended for PLANNER's loss: {ops_stopped}"
    # both sides of the race: motion stopped on its way, and motion that had started
    assert seen.get("stopped", 0) > TRIALS // 20 and seen.get("executed", 0), seen
    await gov.stop()
