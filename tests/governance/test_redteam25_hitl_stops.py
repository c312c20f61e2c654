"""Red team 25: motion held for a human and the stops that come while it waits.

A stop of the robot (`stop`, an e-stop, a session loss's halt) is a stop for all motion decided
before it. Motion held for a human was decided before it: approved after the stop (an e-stop
since cleared, a `stop` long done), it used to run — an approver working from a list read
before the stop restarted what the stop was for.

Such a stop now withdraws that held motion itself (test_held_motion_withdrawn_by_stops.py);
these tests take the withdrawal out (`withdrawals_missed`), as a fault would, to show the
approval's own check still refuses it: the backstop."""

from __future__ import annotations

import pytest
from govhelpers import ADMIN, OPS, PLANNER, Harness, command, principal, withdrawals_missed

from rcan_rtps.governance.governor import Decision, Governor
from rcan_rtps.rcan import Outcome, Role

ARM = {"joints": ["shoulder", "elbow"], "positions": [0.1, -0.2], "duration_s": 2.0}
MOVE_GATE = "[{action: move, require_auth: true, authorized_roles: [OWNER]}]"
TWO_OWNERS = "[{action: arm_joint, require_auth: true, approvals: 2, authorized_roles: [OWNER]}]"
OPS2 = principal("ops2", Role.OWNER)


async def held_arm(gov: Governor) -> str:
    held = await gov.decide(command("arm_joint", ARM), PLANNER)
    assert held.outcome is Outcome.PENDING_AUTH and held.pending_id
    return held.pending_id


@pytest.fixture
async def gov(harness: Harness) -> Governor:
    governor = await harness.governor()
    withdrawals_missed(governor)
    return governor


def refused_stopped(harness: Harness, d: Decision, pending_id: str) -> None:
    assert (d.http_status, d.outcome, d.reason) == (409, Outcome.DENIED, "stopped"), d
    assert "arm_joint" not in [c[0] for c in harness.dispatcher.calls]
    last = harness.entries[-1]
    assert (last["event"], last["outcome"], last["pending_id"]) == (
        "HITL_AUTHORIZED", "denied", pending_id)


async def test_held_motion_approved_after_an_estop_and_its_clear_does_not_run(
        harness: Harness, gov: Governor) -> None:
    pending_id = await held_arm(gov)
    await gov.decide(command("estop"), PLANNER)
    cleared = await gov.decide(command("clear_estop"), ADMIN)
    assert cleared.outcome is Outcome.EXECUTED and not gov.latch.latched
    refused_stopped(harness, await gov.authorize(pending_id, OPS), pending_id)
    assert gov.pending() == []  # resolved: it cannot be approved again later


async def test_held_motion_approved_after_a_stop_does_not_run(
        harness: Harness, gov: Governor) -> None:
    pending_id = await held_arm(gov)
    stopped = await gov.decide(command("stop"), OPS2)  # anyone's stop stops all
    assert stopped.outcome is Outcome.EXECUTED
    refused_stopped(harness, await gov.authorize(pending_id, OPS), pending_id)


async def test_a_held_move_does_not_outlive_a_stop(harness: Harness) -> None:
    gov = await harness.governor(gates=MOVE_GATE)
    withdrawals_missed(gov)
    held = await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    assert held.outcome is Outcome.PENDING_AUTH and held.pending_id
    await gov.decide(command("stop"), PLANNER)
    d = await gov.authorize(held.pending_id, OPS)
    assert (d.http_status, d.reason) == (409, "stopped")
    assert gov.streams.active is None
    assert [c[0] for c in harness.dispatcher.calls] == ["stop"]


async def test_the_last_of_several_approvals_after_a_stop_does_not_run_it(
        harness: Harness) -> None:
    gov = await harness.governor(gates=TWO_OWNERS)
    withdrawals_missed(gov)
    pending_id = await held_arm(gov)
    assert (await gov.authorize(pending_id, OPS)).http_status == 202
    await gov.decide(command("stop"), PLANNER)
    refused_stopped(harness, await gov.authorize(pending_id, OPS2), pending_id)


async def test_held_motion_with_no_stop_since_still_runs(harness: Harness,
                                                         gov: Governor) -> None:
    """The mark counts stops, not time: a stop *before* it was held is no stop of it."""
    await gov.decide(command("stop"), PLANNER)
    pending_id = await held_arm(gov)
    d = await gov.authorize(pending_id, OPS)
    assert d.outcome is Outcome.EXECUTED
    assert [c[0] for c in harness.dispatcher.calls] == ["stop", "arm_joint"]
