"""A stop and a motion command a moment apart: the audit log lists them in the order the robot
got them.

The robot side is the recording dispatcher: its `calls` are in the order the bridge would put
them on the wire (a dispatch publishes before its first await). The motion command is decided
from 3 ms before to 3 ms after the stop — often in the same loop turn, its decision starting
just after the stop's zero went out — and whenever its motion reached the robot, its audit
entry must sit on the same side of the stop's entry as its motion sits of the stop's zero.
"""

from __future__ import annotations

import asyncio
import random
from collections import Counter
from collections.abc import Awaitable, Callable

import pytest
from govhelpers import ADMIN, OPS, PLANNER, Harness, command, principal

from rcan_rtps.governance import audit
from rcan_rtps.governance.governor import Decision, Governor
from rcan_rtps.governance.rbac import Principal
from rcan_rtps.rcan import NormalizedCommand, Outcome, Role

TRIALS = 200  # at least; more, up to MAX_TRIALS, until each order was seen NEEDED times
MAX_TRIALS = 2000  # (a busy machine shifts the timing: one order may come rarely)
NEEDED = TRIALS // 20 + 1
MOTIONS = {"move": {"linear_x": 0.2}, "navigate": {"x": 1.0, "y": 2.0, "yaw": 0.0}}
Stop = Callable[[Governor], Awaitable[Decision]]


async def _stop(gov: Governor) -> Decision:
    return await gov.decide(command("stop"), ADMIN)


async def _session_lost(gov: Governor) -> Decision:
    """PLANNER's control session is lost; nobody else holds the base: a full safe stop, in
    a task of its own as the sweep makes it."""
    return await asyncio.ensure_future(gov.safe_stop(PLANNER, "no command or heartbeat for 2 s"))


STOPS: dict[str, Stop] = {"stop": _stop, "session_lost": _session_lost}


async def _after(delay: float, coro: Awaitable[Decision]) -> Decision:
    if delay > 0:
        await asyncio.sleep(delay)
    return await coro


async def _race(gov: Governor, rng: random.Random, stop: Stop, motion: NormalizedCommand,
                mover: Principal) -> tuple[Decision, Decision, bool]:
    """The stop and `motion`, the one started from 0 to 3 ms after the other (half the time
    in the same loop turn). Returns both decisions and whether the motion was started first."""
    delay = rng.choice([0.0, rng.uniform(0, 0.003)])
    motion_first = rng.random() < 0.3
    moving = gov.decide(motion, mover)
    stopping = stop(gov)
    if motion_first:
        moved, stopped = await asyncio.gather(moving, _after(delay, stopping))
    else:
        stopped, moved = await asyncio.gather(stopping, _after(delay, moving))
    return moved, stopped, motion_first


def _seqs(harness: Harness) -> dict[str, int]:
    return {e["audit_id"]: e["seq"] for e in harness.entries}


@pytest.mark.parametrize("disk", ["fast", "slow"])
@pytest.mark.parametrize("stop_kind", sorted(STOPS))
@pytest.mark.parametrize("action", sorted(MOTIONS))
async def test_the_log_lists_a_stop_and_a_motion_in_the_order_the_robot_got_them(
        harness: Harness, monkeypatch: pytest.MonkeyPatch, action: str, stop_kind: str,
        disk: str) -> None:
    if disk == "slow":  # as on an SD card: every write on the log's thread, none on the loop
        monkeypatch.setattr(audit, "INLINE_FSYNC_S", 0.0)
    gov = await harness.governor()
    stop = STOPS[stop_kind]
    # OPS moves (an OWNER: 1000 commands a minute, not rate-limited here); when PLANNER's
    # session is lost nobody else holds the base as the trial starts (the previous trial's
    # stop ended everything), so PLANNER's silence halts the robot.
    mover = OPS
    rng = random.Random(20261127)
    trials: list[tuple[int, Decision, Decision, bool]] = []
    robot_order: dict[bool, int] = {True: 0, False: 0}
    # Both sides exercised: motion the robot got after the stop, and before it (not after a
    # session loss: motion of OPS's decided before it makes it stop PLANNER's only).
    sides = (False,) if stop_kind == "session_lost" else (False, True)
    for trial in range(MAX_TRIALS):
        if trial >= TRIALS and all(robot_order[side] >= NEEDED for side in sides):
            break
        calls_before = len(harness.dispatcher.calls)
        moved, stopped, _ = await _race(gov, rng, stop, command(action, MOTIONS[action]), mover)
        assert stopped.outcome is Outcome.EXECUTED, (trial, stopped)
        calls = [a for a, _ in harness.dispatcher.calls[calls_before:]]
        # Its motion and the stop's zero both reached the robot (a session loss while
        # another principal's motion runs or is on its way stops only the lost principal's:
        # nothing is sent to the robot).
        if moved.outcome is Outcome.EXECUTED and action in calls and "stop" in calls:
            motion_first_on_robot = calls.index(action) < calls.index("stop")
            robot_order[motion_first_on_robot] += 1
            trials.append((trial, moved, stopped, motion_first_on_robot))
        await gov.decide(command("stop"), ADMIN)  # the next trial starts still
        await asyncio.sleep(0.001)  # its cancels and STREAM_ENDED entries are written
    await gov.stop()
    seqs = _seqs(harness)
    disagree = []
    for trial, moved, stopped, motion_first_on_robot in trials:
        assert moved.audit_id is not None and stopped.audit_id is not None, trial
        if (seqs[moved.audit_id] < seqs[stopped.audit_id]) != motion_first_on_robot:
            disagree.append(trial)
    assert disagree == [], (f"{len(disagree)} of {len(trials)} trials: the log's order of the "
                            f"stop and the {action} is not the robot's: {disagree}")
    assert all(robot_order[side] >= NEEDED for side in sides), robot_order



@pytest.mark.parametrize("disk", ["fast", "slow"])
async def test_the_log_lists_an_estop_where_it_latched(
        harness: Harness, monkeypatch: pytest.MonkeyPatch, disk: str) -> None:
    """A move and an e-stop a moment apart: a move the robot got before the latch is listed
    before the ESTOP entry, and a move refused because of the latch after it."""
    if disk == "slow":
        monkeypatch.setattr(audit, "INLINE_FSYNC_S", 0.0)
    gov = await harness.governor()
    rng = random.Random(20261129)

    async def estop(gov: Governor) -> Decision:
        return await gov.decide(command("estop"), ADMIN)

    before, refused = [], []
    for trial in range(MAX_TRIALS):
        if trial >= TRIALS and min(len(before), len(refused)) >= NEEDED:
            break
        calls_before, signals_before = len(harness.dispatcher.calls), len(
            harness.dispatcher.signals)
        moved, stopped, _ = await _race(gov, rng, estop, command("move", MOTIONS["move"]), OPS)
        assert stopped.outcome is Outcome.EXECUTED and stopped.reason is None, (trial, stopped)
        calls = [a for a, _ in harness.dispatcher.calls]
        latched_at = harness.dispatcher.signals[signals_before]  # dispatches before the latch
        if moved.outcome is Outcome.EXECUTED and "move" in calls[calls_before:]:
            assert calls.index("move", calls_before) < latched_at, trial  # the latch stops it
            before.append((trial, moved, stopped))
        elif moved.reason == "estop_active":
            refused.append((trial, moved, stopped))
        await gov.decide(command("clear_estop"), OPS)
        await gov.decide(command("stop"), ADMIN)
        await asyncio.sleep(0.001)
    await gov.stop()
    seqs = _seqs(harness)
    out_of_order = [t for t, moved, stopped in before
                    if seqs[moved.audit_id] > seqs[stopped.audit_id]]
    out_of_order += [t for t, moved, stopped in refused
                     if seqs[moved.audit_id] < seqs[stopped.audit_id]]
    assert out_of_order == [], (f"{len(out_of_order)} of {len(before) + len(refused)} trials: "
                                f"a move listed on the wrong side of the e-stop: {out_of_order}")
    assert min(len(before), len(refused)) >= NEEDED, (len(before), len(refused))


DRIVER = principal("driver", Role.OWNER)  # 1000 commands a minute: not rate-limited here


async def _estop(gov: Governor) -> Decision:
    return await gov.decide(command("estop"), ADMIN)


async def _driver_lost(gov: Governor) -> Decision:
    return await asyncio.ensure_future(gov.safe_stop(DRIVER, "its connection closed"))


STREAM_STOPS: dict[str, Stop] = {"stop": _stop, "estop": _estop, "session_lost": _driver_lost}


@pytest.mark.parametrize("disk", ["fast", "slow"])
@pytest.mark.parametrize("stop_kind", sorted(STREAM_STOPS))
async def test_a_stream_a_stop_ends_is_listed_where_its_zero_went(
        harness: Harness, monkeypatch: pytest.MonkeyPatch, stop_kind: str, disk: str) -> None:
    """A stop ends a running stream: the stream's zero is the first thing its halt sends, so
    its STREAM_ENDED comes right before the stop's own entry, ahead of anything decided after
    the stop (here OPS's move, 0-3 ms later). It was written by a task of its own, sealed a
    loop step later: after the stop's entry, and after whatever was sealed meanwhile."""
    if disk == "slow":
        monkeypatch.setattr(audit, "INLINE_FSYNC_S", 0.0)
    gov = await harness.governor()
    stop, rng = STREAM_STOPS[stop_kind], random.Random(20261130)
    misplaced, after_stop, tried = [], 0, 0
    for trial in range(MAX_TRIALS // 4):  # (at least TRIALS // 2; more while moves decided
        if trial >= TRIALS // 2 and after_stop >= NEEDED:  # after a stop were few)
            break
        tried += 1
        driving = await gov.decide(command("move", {"linear_x": 0.2}), DRIVER)
        assert driving.outcome is Outcome.EXECUTED and gov.streams.active is not None, trial
        delay = rng.choice([0.0, rng.uniform(0, 0.003)])
        stopped, moved = await asyncio.gather(
            stop(gov), _after(delay, gov.decide(command("move", {"linear_x": 0.1}), OPS)))
        assert stopped.outcome is Outcome.EXECUTED, (trial, stopped)
        await gov.latch.settled()
        if gov.latch.latched:
            await gov.decide(command("clear_estop"), OPS)
        await gov.decide(command("stop"), ADMIN)  # the next trial starts still
        await asyncio.gather(*gov._tasks)  # every end written
        seqs = _seqs(harness)
        [ended] = [e for e in harness.entries if e["event"] == "STREAM_ENDED"
                   and e["message_id"] == driving.message_id]
        stop_seq = seqs[stopped.audit_id]
        if ended["seq"] != stop_seq - 1:
            misplaced.append((trial, ended["params"]["reason"], ended["seq"] - stop_seq))
        after_stop += moved.audit_id is not None and seqs[moved.audit_id] > stop_seq
    await gov.stop()
    places = Counter(after for _, _, after in misplaced)  # entries after the stop's: how many
    assert misplaced == [], (f"{len(misplaced)} of {tried} trials: a stream's end not "
                             f"listed where the stop sent its zero (this many entries after "
                             f"the stop's: trials) {dict(places)}: {misplaced[:10]}")
    assert after_stop >= NEEDED, after_stop  # commands were decided right after the stop
