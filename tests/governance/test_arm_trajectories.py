"""An arm's trajectory runs on after it is sent (`DispatchResult.runs_for_s`): a stop of its
sender's motion alone holds it (`Dispatcher.hold_trajectories`), nobody else's; and while it
runs its sender drives the robot, so another principal's session loss does not halt it.
(A stop of the whole robot holds every arm in the bridge: tests/interop/test_arms.py.)"""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from govhelpers import OPS, PLANNER, Harness, command

from rcan_rtps.governance.governor import Governor
from rcan_rtps.rcan import Outcome

ARM = {"joints": ["elbow"], "positions": [0.8], "duration_s": 30.0}
OTHER_ARM = {**ARM, "joints": ["wrist"]}  # another arm: the double gives it its own topic
SHARED_ID = "7f0c1a52-9b9e-4d8e-8a52-2f6f3a0e9c11"  # two principals may each choose it


async def _governor(harness: Harness) -> Governor:
    return await harness.governor(gates="[]")  # no arm command waits for a human here


async def _arm_moved(gov: Governor, who: Any, arm: dict[str, Any] = ARM) -> str:
    moved = await gov.decide(command("arm_joint", arm), who)
    assert moved.outcome is Outcome.EXECUTED, moved
    await asyncio.gather(*gov._tasks)  # its decision settled: no longer on its way
    assert moved.message_id is not None
    return moved.message_id


def _own_stops(harness: Harness) -> list[dict[str, Any]]:
    return [e for e in harness.entries if e["event"] == "NETWORK_LOSS_SAFE_STOP"]


async def test_a_cancelled_call_holds_its_principal_s_arm_only(harness: Harness) -> None:
    gov = await _governor(harness)
    mine = await _arm_moved(gov, PLANNER)
    theirs = await _arm_moved(gov, OPS, OTHER_ARM)
    stopped = await gov.command_cancelled(PLANNER)
    assert stopped is not None and stopped.outcome is Outcome.EXECUTED, stopped
    assert harness.dispatcher.holds == [[mine]]
    assert harness.dispatcher.running == [theirs]  # OPS's arm runs on
    [entry] = _own_stops(harness)
    assert entry["applied"]["arms_held"] == [f"held {mine}"]
    assert "stop" not in [a for a, _ in harness.dispatcher.calls]  # no halt of the robot
    await gov.stop()


async def test_a_cancel_with_only_an_arm_running_still_stops_it(harness: Harness) -> None:
    """Nothing else of the principal's moves (no stream, goal or motion on its way): before,
    the cancel found nothing to stop, and the arm ran its whole trajectory."""
    gov = await _governor(harness)
    mine = await _arm_moved(gov, PLANNER)
    assert await gov.command_cancelled(PLANNER) is not None
    assert harness.dispatcher.holds == [[mine]] and harness.dispatcher.running == []
    await gov.stop()


async def test_a_session_loss_leaves_another_principal_s_arm_running(harness: Harness
                                                                      ) -> None:
    """PLANNER's session lapses while OPS's arm moves: only PLANNER's motion stops (its own
    arm held); a halt of the robot would have held OPS's arm for PLANNER's silence."""
    gov = await _governor(harness)
    mine = await _arm_moved(gov, PLANNER)
    theirs = await _arm_moved(gov, OPS, OTHER_ARM)
    await gov.safe_stop(PLANNER, "silent")
    assert harness.dispatcher.holds == [[mine]]
    assert harness.dispatcher.running == [theirs]
    assert "stop" not in [a for a, _ in harness.dispatcher.calls]
    [entry] = _own_stops(harness)
    assert entry["applied"]["scope"] == "own"
    assert entry["applied"]["arms_held"] == [f"held {mine}"]
    await gov.stop()


async def test_a_session_loss_with_nobody_else_moving_halts_the_robot(harness: Harness
                                                                       ) -> None:
    gov = await _governor(harness)
    await _arm_moved(gov, PLANNER)
    await gov.safe_stop(PLANNER, "silent")
    assert [a for a, _ in harness.dispatcher.calls][-1] == "stop"  # the whole robot
    assert harness.dispatcher.running == []
    await gov.stop()


async def test_an_ended_trajectory_does_not_keep_its_sender_driving(harness: Harness
                                                                     ) -> None:
    gov = await _governor(harness)
    await _arm_moved(gov, OPS, OTHER_ARM)
    harness.dispatcher.running.clear()  # its time is up (the bridge says so)
    await gov.safe_stop(PLANNER, "silent")
    assert [a for a, _ in harness.dispatcher.calls][-1] == "stop"
    await gov.stop()


@pytest.mark.logs_traceback  # (a fault injected on purpose)
async def test_unreadable_running_trajectories_count_as_running(harness: Harness) -> None:
    """When the bridge cannot say what runs, another principal's arm counts as running (a
    halt for PLANNER's silence must not stop it), and PLANNER's own is held all the same."""
    gov = await _governor(harness)
    mine = await _arm_moved(gov, PLANNER)
    await _arm_moved(gov, OPS, OTHER_ARM)

    def broken() -> list[str]:
        raise RuntimeError("bridge fault")

    harness.dispatcher.running_trajectories = broken  # type: ignore[method-assign]
    await gov.safe_stop(PLANNER, "silent")
    assert "stop" not in [a for a, _ in harness.dispatcher.calls]
    assert harness.dispatcher.holds == [[mine]]
    await gov.stop()


async def test_a_message_id_of_another_s_running_trajectory_holds_nothing_of_theirs(
        harness: Harness) -> None:
    """Message ids are the client's, unique per principal only (a retry is matched by
    principal and id); an arm is held by the id of the command that sent it. One principal's
    arm command naming the id of another's trajectory still running is refused (409): else
    a stop of its own motion (its call cancelled, its INVOKE's client gone, its session
    lost) would hold the other's arm as well."""
    gov = await _governor(harness)
    theirs = await gov.decide(command("arm_joint", ARM, message_id=SHARED_ID), OPS)
    assert theirs.outcome is Outcome.EXECUTED, theirs
    mine = await gov.decide(command("arm_joint", OTHER_ARM, message_id=SHARED_ID), PLANNER)
    assert (mine.http_status, mine.reason) == (
        409, "message_id_of_another_principal_s_running_arm"), mine
    await gov.command_cancelled(PLANNER)
    assert harness.dispatcher.running == [SHARED_ID]  # OPS's arm runs on
    await gov.stop()


async def test_the_id_of_another_s_trajectory_sent_while_this_one_was_written_ahead(
        harness: Harness) -> None:
    """The same, when the other's came while this one's entry was being written: checked
    again after the write, with no await before the publish."""
    gov = await _governor(harness)
    release, entered = asyncio.Event(), asyncio.Event()
    write_ahead = gov._steps.write_ahead

    async def held_write(entry: Any, *, urgent: bool = False) -> Any:
        if entry.principal == PLANNER.name and entry.action_type == "arm_joint":
            entered.set()
            await release.wait()
        return await write_ahead(entry, urgent=urgent)

    gov._steps.write_ahead = held_write  # type: ignore[method-assign]
    mine = asyncio.ensure_future(
        gov.decide(command("arm_joint", OTHER_ARM, message_id=SHARED_ID), PLANNER))
    await asyncio.wait_for(entered.wait(), timeout=10)
    theirs = await gov.decide(command("arm_joint", ARM, message_id=SHARED_ID), OPS)
    assert theirs.outcome is Outcome.EXECUTED, theirs
    release.set()
    refused = await mine
    assert (refused.http_status, refused.outcome) == (409, Outcome.DENIED), refused
    assert harness.entries[-1]["event"] == "COMMAND_FAILED"
    await gov.command_cancelled(PLANNER)
    assert harness.dispatcher.running == [SHARED_ID]  # OPS's arm runs on
    await gov.stop()


async def test_a_hold_of_one_s_own_ended_trajectory_leaves_another_s_of_the_same_id(
        harness: Harness) -> None:
    """Once one's trajectory ended (a stop held it), another principal may use its id; an
    INVOKE of the first still waiting on it (its timeout, its client gone) then holds by that
    id — and must not hold the other's arm, which it never sent."""
    gov = await _governor(harness)
    mine = await gov.decide(command("arm_joint", OTHER_ARM, message_id=SHARED_ID), PLANNER)
    assert mine.outcome is Outcome.EXECUTED, mine
    assert (await gov.decide(command("stop"), OPS)).outcome is Outcome.EXECUTED
    theirs = await gov.decide(command("arm_joint", ARM, message_id=SHARED_ID), OPS)
    assert theirs.outcome is Outcome.EXECUTED, theirs
    await gov.hold_trajectory(SHARED_ID, PLANNER, message_id=SHARED_ID, why="INVOKE timeout")
    assert harness.dispatcher.running == [SHARED_ID]  # OPS's arm runs on
    await gov.command_cancelled(PLANNER)  # nor a stop of the first's own motion
    assert harness.dispatcher.running == [SHARED_ID]
    await gov.stop()
