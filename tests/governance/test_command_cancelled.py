"""A client cancels a motion command of its principal's before its answer came
(`Governor.command_cancelled`: an MCP client's `notifications/cancelled` of a `move` or
`navigate` call). The command's decision goes on, detached, and is audited; but the
principal's motion must not start, or run on, for a caller that no longer wants it: its
motion on its way is refused `stopped` (or its goal cancelled once accepted), its stream is
zeroed, its goals are cancelled — a stop of its own motion alone, audited, nobody else's."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from govhelpers import (
    OPS,
    PLANNER,
    Harness,
    command,
    held_motion_stopped,
    motion_held_at,
    principal,
)

from rcan_rtps.governance.audit import AuditEvent, AuditRecord
from rcan_rtps.governance.governor import (
    CANCELLED_BY_CLIENT,
    MAX_IN_FLIGHT,
    STOPPED_WHILE_HELD,
    Governor,
)
from rcan_rtps.governance.rbac import Principal
from rcan_rtps.rcan import MoveParams, Outcome, Role

GOAL = {"x": 1.0, "y": 2.0, "yaw": 0.0}
MOTION = {"move": {"linear_x": 0.2}, "navigate": GOAL}
ZERO = MoveParams(linear_x=0.0, linear_y=0.0, angular_z=0.0)


def _own_stops(harness: Harness) -> list[dict[str, Any]]:
    return [e for e in harness.entries if e["event"] == "NETWORK_LOSS_SAFE_STOP"]


@pytest.mark.parametrize("where", ["ready", "write_ahead"])
@pytest.mark.parametrize("action", ["move", "navigate"])
async def test_motion_on_its_way_when_its_command_is_cancelled_never_starts(
        harness: Harness, action: str, where: str) -> None:
    """PLANNER's motion waits (for the robot, or for its entry) when its client cancels it:
    it is refused `stopped`, nothing of it reaches the robot, and the stop of PLANNER's own
    motion is audited as its client's cancel."""
    gov = await harness.governor()
    stopped = await held_motion_stopped(gov, harness, where,
                                        gov.decide(command(action, MOTION[action]), PLANNER),
                                        lambda: gov.command_cancelled(PLANNER))
    assert stopped is not None and stopped.outcome is Outcome.EXECUTED, stopped
    assert gov.streams.active is None and gov.streams.goals == {}
    assert harness.dispatcher.calls == [] and harness.dispatcher.samples == []
    [entry] = _own_stops(harness)
    assert entry["principal"] == PLANNER.name and entry["audit_id"] == stopped.audit_id
    assert entry["applied"] == {"scope": "own", "cancelled_by_client": True,
                                "on_its_way": True, "stream_ended": None,
                                "goals_cancelled": []}
    refused = [e for e in harness.entries if e.get("action_type") == action
               and e.get("deny_reason") == "COMMAND_REJECTED:stopped"]
    assert len(refused) == 1, harness.entries  # the decision is audited all the same
    await gov.stop()


async def test_a_running_stream_is_zeroed_when_a_command_is_cancelled(harness: Harness
                                                                      ) -> None:
    """PLANNER's move runs: the cancel zeroes it in the step it is told, before any await,
    audits its end (STREAM_ENDED `cancelled`) and the stop naming it, and ends PLANNER's
    control session (nothing of its is left to guard)."""
    gov = await harness.governor()
    moved = await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    assert moved.outcome is Outcome.EXECUTED and gov.streams.active is not None
    await asyncio.gather(*gov._tasks)  # its decision's task settled: no longer on its way
    stopping = gov.command_cancelled(PLANNER)
    assert gov.streams.active is None  # zero went out before any await
    assert harness.dispatcher.samples[-1] == ZERO
    stopped = await stopping
    assert stopped is not None and stopped.outcome is Outcome.EXECUTED, stopped
    await asyncio.gather(*gov._tasks)
    [ended] = [e for e in harness.entries if e["event"] == "STREAM_ENDED"]
    assert (ended["params"]["reason"], ended["params"]["ended_by"]) == ("cancelled", "planner")
    [entry] = _own_stops(harness)
    assert entry["applied"]["stream_ended"] == moved.message_id, entry
    assert entry["applied"]["on_its_way"] is False
    assert [a for a, _ in harness.dispatcher.calls] == ["move"]  # no halt of the robot
    assert await gov.end_session(PLANNER) is None  # its session ended with its motion
    await gov.stop()


async def test_a_goal_is_cancelled_when_a_command_is_cancelled(harness: Harness) -> None:
    gov = await harness.governor()
    sent = await gov.decide(command("navigate", GOAL), PLANNER)
    assert sent.outcome is Outcome.EXECUTED and sent.goal_id is not None
    await asyncio.gather(*gov._tasks)
    stopped = await gov.command_cancelled(PLANNER)
    assert stopped is not None and stopped.outcome is Outcome.EXECUTED, stopped
    await asyncio.gather(*gov._tasks)
    assert harness.dispatcher.cancelled == [sent.goal_id] and gov.streams.goals == {}
    [entry] = _own_stops(harness)
    assert entry["applied"]["goals_cancelled"] == [sent.goal_id], entry
    await gov.stop()


@pytest.mark.parametrize(("theirs", "mine"), [("move", "navigate"), ("navigate", "move")])
async def test_only_the_cancelling_principals_motion_stops(harness: Harness, theirs: str,
                                                          mine: str) -> None:
    """OPS drives (a stream, or a goal) while PLANNER's motion waits for the robot when
    PLANNER's client cancels it: PLANNER's never starts; OPS's goes on, nothing halted."""
    gov = await harness.governor()
    driving = await gov.decide(command(theirs, MOTION[theirs]), OPS)
    assert driving.outcome is Outcome.EXECUTED, driving
    release, entered = motion_held_at(gov, harness, "ready")
    moving = asyncio.ensure_future(gov.decide(command(mine, MOTION[mine]), PLANNER))
    await asyncio.wait_for(entered.wait(), timeout=10)
    samples = len(harness.dispatcher.samples)
    assert await gov.command_cancelled(PLANNER) is not None
    release.set()
    moved = await moving
    assert (moved.http_status, moved.reason) == (409, "stopped"), moved
    await asyncio.gather(*gov._tasks)
    assert ZERO not in harness.dispatcher.samples[samples:]  # OPS's stream was not zeroed
    assert harness.dispatcher.cancelled == []
    assert [a for a, _ in harness.dispatcher.calls] == [theirs]
    if theirs == "move":
        assert gov.streams.active is not None and gov.streams.active.owner == OPS.name
    else:
        assert [g.owner for g in gov.streams.goals.values()] == [OPS.name]
    await gov.stop()


async def test_nothing_of_its_on_its_way_or_running_stops_nothing(harness: Harness) -> None:
    """PLANNER's command was refused, and OPS drives: the cancel stops nothing, writes no
    entry and leaves OPS's stream running."""
    gov = await harness.governor()
    await gov.decide(command("move", {"linear_x": 0.2}), OPS)
    refused = await gov.decide(command("move", {"linear_x": 5.0}), PLANNER)
    assert refused.outcome is Outcome.SAFETY_VIOLATION, refused
    await asyncio.gather(*gov._tasks)
    before = len(harness.entries)
    assert await gov.command_cancelled(PLANNER) is None
    active = gov.streams.active
    assert active is not None and active.owner == OPS.name
    assert len(harness.entries) == before
    await gov.stop()



# -- motion held for a human (§9) -------------------------------------------------------------

ARM = {"joints": ["shoulder", "elbow"], "positions": [0.1, -0.2], "duration_s": 2.0}
ARM_AND_LOCK = ("[{action: arm_joint, require_auth: true, authorized_roles: [OWNER]}, "
                "{action: lock, require_auth: true, authorized_roles: [OWNER]}]")
OTHER = principal("other", Role.USER)


def _withdrawals(harness: Harness) -> list[tuple[str, str, list[str | None]]]:
    """(principal, pending_id, the reasons it names) of each HITL_WITHDRAWN entry."""
    return [(e["principal"], e["pending_id"], [r.get("reason") for r in e["approvals"]])
            for e in harness.entries if e["event"] == "HITL_WITHDRAWN"]


async def _held(gov: Governor, action: str, params: dict[str, Any], who: Principal) -> str:
    held = await gov.decide(command(action, params), who)
    assert held.outcome is Outcome.PENDING_AUTH and held.pending_id, held
    return held.pending_id


async def test_held_motion_is_withdrawn_when_a_command_is_cancelled(harness: Harness
                                                                    ) -> None:
    """PLANNER's arm_joint waits for a human (answered `pending_auth`, the cancel crossing
    that answer) when its client cancels a motion call: it is withdrawn, audited as its
    withdrawal by PLANNER saying why, and an OWNER's approval — even one that comes before
    the withdrawal's entry — never runs it. PLANNER's held lock (no motion) and OTHER's held
    arm_joint still wait; OTHER's runs once approved."""
    gov = await harness.governor(gates=ARM_AND_LOCK)
    arm = await _held(gov, "arm_joint", ARM, PLANNER)
    lock = await _held(gov, "lock", {"name": "teleop"}, PLANNER)
    theirs = await _held(gov, "arm_joint", ARM, OTHER)
    # An OWNER's approval under way as the cancel comes: its review runs before the
    # withdrawal's (both wait for the loop), and must not count.
    approving = asyncio.ensure_future(gov.authorize(arm, OPS))
    await asyncio.sleep(0)  # its review's task is made, not yet run
    stopping = gov.command_cancelled(PLANNER)
    late = await approving
    assert (late.http_status, late.reason) == (404, "pending_not_found"), late
    assert await stopping is None  # nothing of PLANNER's was on its way or running
    assert sorted(p.pending_id for p in gov.pending()) == sorted([lock, theirs])
    assert _withdrawals(harness) == [("planner", arm, [CANCELLED_BY_CLIENT])]
    record = gov.pending_record(arm)
    assert record is not None and record.state == "resolved"
    again = await gov.authorize(arm, OPS)
    assert (again.http_status, again.reason) == (404, "pending_not_found"), again
    assert harness.dispatcher.calls == []
    ran = await gov.authorize(theirs, OPS)
    assert ran.outcome is Outcome.EXECUTED, ran
    assert [a for a, _ in harness.dispatcher.calls] == ["arm_joint"]
    await gov.stop()


async def test_motion_cancelled_before_it_is_held_is_refused(harness: Harness) -> None:
    """PLANNER's arm_joint waits its turn (every slot of the admission queue taken) when its
    client cancels it: decided after the cancel, it is refused `stopped`, as motion not held
    is — never held for a human who could approve it later."""
    gov = await harness.governor()
    for _ in range(MAX_IN_FLIGHT):
        await gov._admission.acquire()
    deciding = asyncio.ensure_future(gov.decide(command("arm_joint", ARM), PLANNER))
    await asyncio.sleep(0)  # it arrived (on its way) and waits for a slot
    assert not deciding.done()
    stopped = await gov.command_cancelled(PLANNER)
    assert stopped is not None and stopped.outcome is Outcome.EXECUTED, stopped
    for _ in range(MAX_IN_FLIGHT):
        gov._admission.release()
    decided = await deciding
    assert (decided.http_status, decided.reason) == (409, "stopped"), decided
    assert gov.pending() == []
    assert [e["event"] for e in harness.entries if e.get("action_type") == "arm_joint"] == [
        "COMMAND_REJECTED"]
    assert harness.dispatcher.calls == []
    await gov.stop()


async def test_motion_cancelled_while_its_hold_is_written_is_withdrawn(harness: Harness
                                                                       ) -> None:
    """PLANNER's arm_joint is cancelled while its PENDING_AUTH entry is being written: held
    after the cancel, it is withdrawn in the step it is held, audited so, and no approval
    runs it."""
    gov = await harness.governor()
    release, entered = asyncio.Event(), asyncio.Event()
    append = gov.audit.append

    async def held_append(entry: AuditRecord, **kwargs: Any) -> Any:
        if entry.event is AuditEvent.PENDING_AUTH:
            entered.set()
            await release.wait()
        return await append(entry, **kwargs)

    gov.audit.append = held_append  # type: ignore[method-assign]
    deciding = asyncio.ensure_future(gov.decide(command("arm_joint", ARM), PLANNER))
    await asyncio.wait_for(entered.wait(), timeout=10)
    stopped = await gov.command_cancelled(PLANNER)
    assert stopped is not None and stopped.applied["on_its_way"] is True, stopped
    release.set()
    decided = await deciding
    assert (decided.http_status, decided.reason) == (200, "hitl_withdrawn"), decided
    assert gov.pending() == []
    [(who, pending_id, reasons)] = _withdrawals(harness)
    assert (who, reasons) == ("planner", [STOPPED_WHILE_HELD])
    late = await gov.authorize(pending_id, OPS)
    assert (late.http_status, late.reason) == (404, "pending_not_found"), late
    assert harness.dispatcher.calls == []
    await gov.stop()
