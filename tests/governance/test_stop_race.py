"""A motion command, then a stop a moment later: once both are decided the robot is still.

Whatever the interleaving — the stop arriving while the move or goal waits for its audit
entry, or while the goal is on its way to its server — motion decided before a stop must not
reach the robot after it (a stop's cancel reaches only the goals a server already has, and a
stream that starts after the stop's zero runs on)."""

from __future__ import annotations

import asyncio
import random
from typing import Any

from govhelpers import ADMIN, OPS, PLANNER, Harness, LossTrial, command

from rcan_rtps.governance.governor import MAX_IN_FLIGHT, Decision, Governor
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


async def _goal_on_its_way(gov: Governor, harness: Harness, sender: Any) -> asyncio.Future[Any]:
    """`sender`'s navigate, decided and held in its dispatch: on its way to its server."""
    harness.dispatcher.hold = asyncio.Event()
    harness.dispatcher.entered.clear()
    sending = asyncio.ensure_future(gov.decide(command("navigate", GOAL), sender))
    await asyncio.wait_for(harness.dispatcher.entered.wait(), timeout=10)
    return sending


async def test_a_session_loss_does_not_stop_another_principals_goal_on_its_way(
        harness: Harness) -> None:
    """PLANNER drives and goes silent while OPS's goal is on its way to its server: only
    PLANNER's motion stops. A halt of the whole robot (a server-wide cancel, which the bridge
    also counts against the goal being sent) would cancel OPS's goal for PLANNER's silence."""
    gov = await harness.governor()
    await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)  # PLANNER holds a session
    sending = await _goal_on_its_way(gov, harness, OPS)
    before = len(harness.dispatcher.calls)
    lost = await gov.safe_stop(PLANNER, "no command or heartbeat for 2 s")
    assert lost.outcome is Outcome.EXECUTED
    assert gov.streams.active is None  # PLANNER's stream ended (zero sent)
    assert [a for a, _ in harness.dispatcher.calls[before:]] == []  # no robot-wide halt
    assert harness.dispatcher.hold is not None
    harness.dispatcher.hold.set()
    sent = await sending
    assert sent.outcome is Outcome.EXECUTED and sent.goal_id is not None, sent
    assert sent.goal_id in gov.streams.goals and harness.dispatcher.cancelled == []
    [entry] = [e for e in harness.entries if e["event"] == "NETWORK_LOSS_SAFE_STOP"]
    assert entry["applied"]["scope"] == "own"
    await gov.stop()


async def test_an_estop_cleared_while_a_goal_was_on_its_way_still_cancels_it(
        harness: Harness) -> None:
    """An e-stop wins over every goal decided before it, even once cleared: a goal accepted
    after the clear is cancelled and answered `stopped`, as after a `stop`."""
    gov = await harness.governor()
    sending = await _goal_on_its_way(gov, harness, PLANNER)
    await gov.decide(command("estop"), ADMIN)
    cleared = await gov.decide(command("clear_estop"), ADMIN)
    assert cleared.outcome is Outcome.EXECUTED and not gov.latch.latched
    assert harness.dispatcher.hold is not None
    harness.dispatcher.hold.set()
    sent = await sending
    assert (sent.http_status, sent.reason) == (409, "stopped"), sent
    await asyncio.sleep(0)  # the cancel the arbiter spawned gets its turn
    assert harness.dispatcher.cancelled == [f"goal-{harness.dispatcher._goals}"]
    assert gov.streams.goals == {}
    await gov.stop()


async def test_a_lost_principals_goal_on_its_way_is_cancelled_while_another_drives(
        harness: Harness) -> None:
    """OPS drives (its stream holds the base) and PLANNER's goal is on its way to its server
    when PLANNER's connection closes: the session loss stops PLANNER's motion alone. Its goal,
    accepted after, is cancelled and answered `stopped`; OPS's stream runs on. It used to be
    held once accepted — running after its sender was gone, and replacing OPS's stream."""
    gov = await harness.governor()
    await gov.decide(command("move", {"linear_x": 0.2}), OPS)
    sending = await _goal_on_its_way(gov, harness, PLANNER)
    lost = await gov.end_session(PLANNER)
    assert lost is not None and lost.outcome is Outcome.EXECUTED
    assert harness.dispatcher.hold is not None
    harness.dispatcher.hold.set()
    sent = await sending
    assert (sent.http_status, sent.reason) == (409, "stopped"), sent
    await asyncio.gather(*gov._tasks)  # the cancel the arbiter spawned
    assert harness.dispatcher.cancelled == [f"goal-{harness.dispatcher._goals}"]
    assert gov.streams.goals == {}
    assert gov.streams.active is not None and gov.streams.active.owner == OPS.name
    await gov.stop()


async def test_no_motion_of_a_lost_principal_outlives_its_session_while_another_drives(
        harness: Harness) -> None:
    """PLANNER's move or goal (its server answering within 4 ms), and PLANNER's connection
    closing 0-3 ms later, while OPS's stream holds the base: once all is decided nothing of
    PLANNER's moves the robot (no stream of its, every goal of its cancelled), and motion of
    PLANNER's that had not started when its session ended left OPS's stream running."""
    gov = await harness.governor()
    rng = random.Random(20261130)
    dispatch = harness.dispatcher.dispatch

    async def accepted_a_moment_later(command: Any, applied: Any) -> Any:
        if command.spec.starts_goal:  # a goal server takes its time to answer
            await asyncio.sleep(rng.uniform(0, 0.004))
        return await dispatch(command, applied)

    harness.dispatcher.dispatch = accepted_a_moment_later  # type: ignore[method-assign]
    outliving: list[tuple[int, str]] = []
    ops_stopped: list[int] = []
    seen: dict[str, int] = {}
    for trial in range(TRIALS):
        harness.clock.advance(60)  # a fresh rate budget (no sweeper runs here)
        await gov.decide(command("move", {"linear_x": 0.2}), OPS)
        action = rng.choice(["move", "navigate"])
        params = GOAL if action == "navigate" else {"linear_x": 0.1}
        watched = LossTrial(harness.dispatcher)
        delay = rng.uniform(0, 0.003)
        moved, lost = await asyncio.gather(gov.decide(command(action, params), PLANNER),
                                           _after(delay, gov.end_session(PLANNER)))
        await asyncio.gather(*gov._tasks)  # cancels, STREAM_ENDED entries
        if lost is None:  # its motion had not reached the robot yet: no session to end
            await gov.end_session(PLANNER)  # (opened meanwhile: closed for the next trial)
        else:
            seen[moved.reason or moved.outcome.value] = seen.get(
                moved.reason or moved.outcome.value, 0) + 1
            active = gov.streams.active
            outliving += [(trial, what) for what in watched.outliving(gov, PLANNER)]
            if moved.reason == "stopped" and (active is None or active.owner != OPS.name):
                ops_stopped.append(trial)
        await gov.decide(command("stop"), ADMIN)  # the next trial starts still
        await asyncio.gather(*gov._tasks)
    assert outliving == [], f"PLANNER's motion outlived its session: {outliving}"
    assert ops_stopped == [], f"OPS's stream ended for PLANNER's loss: {ops_stopped}"
    assert seen.get("stopped", 0) > TRIALS // 20, seen  # motion on its way was exercised
    await gov.stop()


async def test_a_move_waiting_its_turn_is_stopped_by_a_stop_before_its_turn(
        harness: Harness) -> None:
    """A move that arrived while MAX_IN_FLIGHT commands were being decided, and a `stop`
    (never queued) before its turn came: it was received before the stop, so it never starts.
    It used to take its mark only once admitted, after the stop, and drive on."""
    gov = await harness.governor()
    for _ in range(MAX_IN_FLIGHT):  # every place taken
        await gov._admission.acquire()
    moving = asyncio.ensure_future(gov.decide(command("move", {"linear_x": 0.2}), PLANNER))
    await asyncio.sleep(0.01)
    stopped = await gov.decide(command("stop"), ADMIN)
    assert stopped.outcome is Outcome.EXECUTED and not moving.done()
    for _ in range(MAX_IN_FLIGHT):
        gov._admission.release()
    moved = await moving
    assert (moved.http_status, moved.reason) == (409, "stopped"), moved
    assert gov.streams.active is None and harness.dispatcher.samples == []
    await gov.stop()
