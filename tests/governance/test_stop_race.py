"""A motion command, then a stop a moment later: once both are decided the robot is still.

Whatever the interleaving — the stop arriving while the move or goal waits for its audit
entry, or while the goal is on its way to its server — motion decided before a stop must not
reach the robot after it (a stop's cancel reaches only the goals a server already has, and a
stream that starts after the stop's zero runs on)."""

from __future__ import annotations

import asyncio
import random
from typing import Any

import pytest
from govhelpers import ADMIN, OPS, PLANNER, VIEWER, Harness, LossTrial, command

from rcan_rtps.governance.governor import MAX_IN_FLIGHT, Decision, Governor
from rcan_rtps.rcan import ErrorCode, Outcome

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


def _move_held(gov: Governor, harness: Harness, where: str, sender: Any) -> asyncio.Event:
    """`sender`'s move, held `where`: waiting its turn (MAX_IN_FLIGHT commands being decided),
    or its entry being written (its decision's, or its refusal's). Set the event to let it go."""
    release = asyncio.Event()
    if where == "its_turn":
        async def every_place_taken() -> None:
            for _ in range(MAX_IN_FLIGHT):
                await gov._admission.acquire()
            await release.wait()
            for _ in range(MAX_IN_FLIGHT):
                gov._admission.release()

        gov._steps.spawn(every_place_taken())
        return release
    write_ahead = gov._steps.write_ahead

    async def held_write(entry: Any, *, urgent: bool = False) -> Any:
        if entry.action_type == "move" and entry.principal == sender.name:
            await release.wait()
        return await write_ahead(entry, urgent=urgent)

    gov._steps.write_ahead = held_write  # type: ignore[method-assign]
    return release


async def _lost_while_a_move_waits(gov: Governor, harness: Harness, where: str,
                                   sender: Any) -> tuple[Decision, list[str], Decision]:
    """PLANNER drives; `sender`'s move is held `where` when PLANNER's session is lost. The
    loss's decision, what it sent the robot, and the move's decision once let go."""
    await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)  # PLANNER holds a session
    release = _move_held(gov, harness, where, sender)
    await asyncio.sleep(0)  # (every place taken, for `its_turn`)
    waiting = asyncio.ensure_future(gov.decide(command("move", {"linear_x": 0.1}), sender))
    await asyncio.sleep(0.01)
    assert not waiting.done()
    before = len(harness.dispatcher.calls)
    lost = await gov.safe_stop(PLANNER, "no command or heartbeat for 2 s")
    sent = [a for a, _ in harness.dispatcher.calls[before:]]
    release.set()
    return lost, sent, await waiting


@pytest.mark.parametrize("where", ["its_turn", "its_refusal_entry"])
async def test_a_move_its_sender_may_not_send_leaves_a_session_loss_a_halt(
        harness: Harness, where: str) -> None:
    """A GUEST (whose role may not move) keeps a move waiting — its turn, or its refusal's
    entry — while PLANNER's session is lost, with nobody else driving: the loss halts the whole
    robot. The GUEST's move counted as another principal's motion on its way and narrowed the
    halt to PLANNER's own motion (`applied.scope: own`, nothing sent): by sending refused moves
    without end, a GUEST could keep every session loss from halting the robot."""
    gov = await harness.governor()
    lost, sent, moved = await _lost_while_a_move_waits(gov, harness, where, VIEWER)
    assert lost.outcome is Outcome.EXECUTED, lost
    assert sent == ["stop"], sent  # zero published, every goal cancelled
    [entry] = [e for e in harness.entries if e["event"] == "NETWORK_LOSS_SAFE_STOP"]
    assert entry["applied"] == {}, entry  # not a stop of PLANNER's motion alone
    assert (moved.http_status, moved.error_code) == (403, ErrorCode.INSUFFICIENT_PRIVILEGES)
    await asyncio.gather(*gov._tasks)
    assert gov.streams.active is None and gov.streams._deciding == {}
    await gov.stop()


@pytest.mark.parametrize("where", ["its_turn", "its_refusal_entry"])
async def test_a_move_its_sender_may_send_still_narrows_a_session_loss(
        harness: Harness, where: str) -> None:
    """The same with OPS's move waiting: OPS may move, so its move is on its way from its
    arrival and PLANNER's loss stops PLANNER's motion alone; OPS's move then starts."""
    gov = await harness.governor()
    lost, sent, moved = await _lost_while_a_move_waits(gov, harness, where, OPS)
    assert lost.outcome is Outcome.EXECUTED, lost
    assert sent == [], sent  # no halt of the robot
    [entry] = [e for e in harness.entries if e["event"] == "NETWORK_LOSS_SAFE_STOP"]
    assert entry["applied"]["scope"] == "own", entry
    assert moved.outcome is Outcome.EXECUTED, moved
    active = gov.streams.active
    assert active is not None and active.owner == OPS.name and active.target.linear_x == 0.1
    await gov.stop()
