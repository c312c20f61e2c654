"""POST /api/command/cancel: a client says it cancelled a motion command of its principal's
before its answer came (`rcan-rtps mcp` does, for its MCP client: tests/mcp/
test_mcp_stdio_cancel.py). The principal's motion on its way never starts, what runs stops —
its own alone — audited; with nothing of its to stop, nothing happens. Its motion held for a
human is withdrawn, and the answer lists it (`withdrawn`)."""

from __future__ import annotations

from tests.api.apihelpers import ZERO, Api, own_stops


async def test_with_nothing_of_its_to_stop_nothing_happens(api: Api) -> None:
    status, body = await api.command("ops", {"action": "move", "params": {"linear_x": 0.3}})
    assert (status, body["outcome"]) == (200, "executed"), body
    before = len(api.entries)
    status, body = await api.call("POST", "/api/command/cancel", "planner")
    assert (status, body) == (200, {"principal": "planner", "stopped": False})
    assert len(api.entries) == before
    active = api.gov.streams.active
    assert active is not None and active.owner == "ops"  # OPS's stream runs on


async def test_the_principals_running_move_stops_audited(api: Api) -> None:
    status, moved = await api.command("planner", {"action": "move",
                                                  "params": {"linear_x": 0.3}})
    assert (status, moved["outcome"]) == (200, "executed"), moved
    status, body = await api.call("POST", "/api/command/cancel", "planner")
    assert (status, body["principal"], body["stopped"]) == (200, "planner", True), body
    decision = body["decision"]
    assert decision["outcome"] == "executed", decision
    [entry] = own_stops(api.entries)
    assert entry["audit_id"] == decision["audit_id"] and entry["principal"] == "planner"
    assert entry["applied"] == decision["applied"] == {
        "scope": "own", "cancelled_by_client": True, "on_its_way": False,
        "stream_ended": moved["message_id"], "goals_cancelled": []}
    assert api.gov.streams.active is None and api.dispatcher.samples[-1] == ZERO
    assert [a for a, _ in api.dispatcher.calls] == ["move"]  # the robot was not halted


ARM = {"action": "arm_joint", "params": {"joints": ["elbow"], "positions": [0.8],
                                         "duration_s": 1.0}}


async def test_held_motion_it_withdrew_is_in_its_answer(api: Api) -> None:
    """Nothing of the principal's moves, but its arm motion waits for a human: the cancel
    withdraws it (it never runs) and says so — `withdrawn`, its pending id — beside `stopped:
    false` (nothing moved). Before, the answer was `stopped: false` alone, as if the cancel
    had done nothing."""
    status, held = await api.command("planner", ARM)
    assert (status, held["outcome"]) == (202, "pending_auth"), held
    status, body = await api.call("POST", "/api/command/cancel", "planner")
    assert (status, body) == (200, {"principal": "planner", "stopped": False,
                                    "withdrawn": [held["pending_id"]]}), body
    assert api.gov.pending() == []
    [entry] = [e for e in api.entries if e["event"] == "HITL_WITHDRAWN"]
    assert (entry["pending_id"], entry["principal"]) == (held["pending_id"], "planner"), entry
    assert own_stops(api.entries) == []


async def test_a_stop_and_a_withdrawal_are_both_in_its_answer(api: Api) -> None:
    status, moved = await api.command("planner", {"action": "move",
                                                  "params": {"linear_x": 0.3}})
    assert (status, moved["outcome"]) == (200, "executed"), moved
    status, held = await api.command("planner", ARM)
    assert (status, held["outcome"]) == (202, "pending_auth"), held
    status, body = await api.call("POST", "/api/command/cancel", "planner")
    assert (status, body["stopped"], body["withdrawn"]) == (200, True, [held["pending_id"]])
    assert body["decision"]["applied"]["stream_ended"] == moved["message_id"], body
