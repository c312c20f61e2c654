"""An arm's trajectory runs on after it is sent (`DispatchResult.runs_for_s`): a stop of its
sender's motion alone holds it (`Dispatcher.hold_trajectories`), nobody else's; and while it
runs its sender drives the robot, so another principal's session loss does not halt it.
(A stop of the whole robot holds every arm in the bridge: tests/interop/test_arms.py.)"""

from __future__ import annotations

import asyncio
from typing import Any

from govhelpers import OPS, PLANNER, Harness, command

from rcan_rtps.governance.governor import Governor
from rcan_rtps.rcan import Outcome

ARM = {"joints": ["elbow"], "positions": [0.8], "duration_s": 30.0}
OTHER_ARM = {**ARM, "joints": ["wrist"]}  # another arm: the double gives it its own topic


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
