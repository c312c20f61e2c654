"""Every row of the profile's outcome table, e-stop latch, idempotency, exactly-one-entry."""

from __future__ import annotations

import asyncio
import json
from typing import Any

import pytest
from govhelpers import ADMIN, OPS, PLANNER, RURI, VIEWER, Harness, command, principal

from rcan_rtps.governance import outcomes
from rcan_rtps.governance.audit import verify
from rcan_rtps.governance.governor import Decision, Governor
from rcan_rtps.governance.rbac import Principal
from rcan_rtps.rcan import ErrorCode, Outcome, Role, SchemaValidationError, validate_command


def one_new_entry(harness: Harness, before: int) -> dict[str, Any]:
    entries = harness.entries
    assert len(entries) == before + 1, "exactly one decisive entry per command"
    return entries[-1]


def check(decision: Decision, status: int, outcome: Outcome,
          code: ErrorCode | None = None, reason: str | None = None) -> None:
    assert (decision.http_status, decision.outcome) == (status, outcome)
    assert decision.error_code == code
    if reason is not None:
        assert decision.reason == reason


async def test_executed_is_clamped_and_reports_applied(harness: Harness, gov: Governor) -> None:
    d = await gov.decide(command("move", {"linear_x": 1.05, "angular_z": -0.2}), PLANNER)
    check(d, 200, Outcome.EXECUTED)
    # Held (no duration_s), from a standstill with no acceleration limits: no ramp.
    assert d.applied == {"linear_x": 1.0, "linear_y": 0.0, "angular_z": -0.2,
                         "duration_s": None, "ramp_from": [0.0, 0.0, 0.0], "ramp_s": 0.0}
    assert harness.dispatcher.calls == [("move", {"linear_x": 1.0, "linear_y": 0.0,
                                                  "angular_z": -0.2, "duration_s": None})]
    entry = one_new_entry(harness, 0)
    assert (entry["event"], entry["outcome"], entry["audit_id"]) == (
        "COMMAND_DISPATCHED", "executed", d.audit_id)
    assert entry["params"] == {"linear_x": 1.05, "angular_z": -0.2}  # as requested
    assert entry["applied"] == d.applied  # as sent
    assert entry["ros2_topic"] == "/robot1/move"
    assert (entry["principal"], entry["role"]) == ("planner", "USER")
    assert d.body().applied == d.applied


async def test_ai_identity_is_audited(harness: Harness, gov: Governor) -> None:
    cmd = command("stop", ai_provider="openai", ai_model="gpt-4o", confidence=0.94,
                  thought_id="chatcmpl-abc123")
    await gov.decide(cmd, PLANNER)
    assert harness.entries[-1]["ai"] == {"provider": "openai", "model": "gpt-4o",
                                         "confidence": 0.94, "thought_id": "chatcmpl-abc123"}


async def test_pending_auth_row(harness: Harness, gov: Governor) -> None:
    cmd = command("arm_joint", {"joints": ["j1"], "positions": [0.3], "duration_s": 2})
    d = await gov.decide(cmd, PLANNER)
    check(d, 202, Outcome.PENDING_AUTH)
    assert d.pending_id and d.expires_at_ms == int(harness.clock.time() * 1000) + 300_000
    entry = one_new_entry(harness, 0)
    assert (entry["event"], entry["pending_id"]) == ("PENDING_AUTH", d.pending_id)
    assert harness.dispatcher.calls == []


async def test_schema_failure_row(harness: Harness, gov: Governor) -> None:
    with pytest.raises(SchemaValidationError) as info:
        validate_command(b'{"action":"move","params":{"linear_x":"fast"}}')
    d = await gov.reject_request(PLANNER, outcomes.schema_failed(info.value.path))
    check(d, 400, Outcome.DENIED, ErrorCode.SCHEMA_VALIDATION_FAILED, "$.params.linear_x")
    assert one_new_entry(harness, 0)["deny_reason"] == (
        "SCHEMA_VALIDATION_FAILED:$.params.linear_x")


async def test_unauthenticated_row_is_not_audited(harness: Harness, gov: Governor) -> None:
    d = await gov.reject_request(None, outcomes.UNAUTHENTICATED)
    check(d, 401, Outcome.DENIED, ErrorCode.UNAUTHENTICATED)
    assert d.audit_id is None
    assert not (harness.tmp / "audit.jsonl").read_bytes()


async def test_payload_too_large_row(harness: Harness, gov: Governor) -> None:
    d = await gov.reject_request(VIEWER, outcomes.PAYLOAD_TOO_LARGE)
    check(d, 413, Outcome.DENIED, ErrorCode.PAYLOAD_TOO_LARGE)
    assert one_new_entry(harness, 0)["outcome"] == "denied"


@pytest.mark.parametrize(
    ("who", "cmd"),
    [
        (VIEWER, command("move", {"linear_x": 0.1})),
        (PLANNER, command("clear_estop")),
        (PLANNER, command("move", {"linear_x": 0.1}, role="OWNER")),  # claims more than its token
        (PLANNER, command("move", {"linear_x": 0.1}, role_level=9)),
        (PLANNER, command("move", {"linear_x": 0.1}, role="ROOT")),
    ],
)
async def test_role_too_low_row(harness: Harness, gov: Governor, who: Any, cmd: Any) -> None:
    d = await gov.decide(cmd, who)
    check(d, 403, Outcome.DENIED, ErrorCode.INSUFFICIENT_PRIVILEGES)
    assert one_new_entry(harness, 0)["event"] == "COMMAND_REJECTED"
    assert harness.dispatcher.calls == []


@pytest.mark.parametrize("action", ["stop", "estop"])
@pytest.mark.parametrize("claim", [{"role": "OWNER"}, {"role_level": 9}, {"role": "ROOT"}])
async def test_a_stop_claiming_more_than_its_token_still_stops(
        harness: Harness, gov: Governor, action: str, claim: dict[str, Any]) -> None:
    """Any authenticated request that says stop, stops: the claim is a warning, not a 403."""
    d = await gov.decide(command(action, **claim), PLANNER)
    check(d, 200, Outcome.EXECUTED)
    assert d.warnings and "role claim" in d.warnings[0]
    entry = one_new_entry(harness, 0)
    assert entry["action_type"] == action and entry["warnings"] == d.warnings
    assert [c[0] for c in harness.dispatcher.calls] == [action]


async def test_claiming_no_more_than_the_token_is_harmless(gov: Governor) -> None:
    d = await gov.decide(command("stop", role="USER"), PLANNER)
    assert d.outcome is Outcome.EXECUTED


@pytest.mark.parametrize("field", ["linear_x", "linear_y", "angular_z"])
async def test_velocity_over_limit_row(harness: Harness, gov: Governor, field: str) -> None:
    limit = 0.5 if field == "angular_z" else 1.0
    d = await gov.decide(command("move", {field: -limit * 1.11}), PLANNER)
    check(d, 409, Outcome.SAFETY_VIOLATION, ErrorCode.COMMAND_REJECTED, "velocity_limit")
    entry = one_new_entry(harness, 0)
    assert (entry["outcome"], entry["deny_reason"]) == (
        "safety_violation", "COMMAND_REJECTED:velocity_limit")
    assert harness.dispatcher.calls == []


@pytest.mark.parametrize("field", ["linear_x", "linear_y", "angular_z"])
async def test_with_velocity_exceed_deny_off_any_excess_is_clamped_not_refused(
        harness: Harness, field: str) -> None:
    """Bridge spec §10.2: "clamping or denial per config" — `velocity_exceed_deny: false`
    clamps even a request far over the limit, and what is sent is within it."""
    gov = await harness.governor(safety_extra="velocity_exceed_deny: false")
    limit = 0.5 if field == "angular_z" else 1.0
    d = await gov.decide(command("move", {field: -limit * 5}), PLANNER)
    check(d, 200, Outcome.EXECUTED)
    assert d.applied is not None and d.applied[field] == -limit
    [(action, sent)] = harness.dispatcher.calls
    assert (action, sent[field]) == ("move", -limit)
    assert one_new_entry(harness, 0)["params"] == {field: -limit * 5}  # as requested


async def test_estop_active_row(harness: Harness, gov: Governor) -> None:
    await gov.decide(command("estop"), VIEWER)
    goal = {"x": 1, "y": 1, "yaw": 0}
    for cmd in (command("move", {"linear_x": 0.1}), command("navigate", goal)):
        d = await gov.decide(cmd, OPS)
        check(d, 409, Outcome.DENIED, ErrorCode.COMMAND_REJECTED, "estop_active")
    assert [e["event"] for e in harness.entries] == ["ESTOP", "COMMAND_REJECTED",
                                                     "COMMAND_REJECTED"]
    d = await gov.decide(command("stop"), PLANNER)  # stopping stays possible
    assert d.outcome is Outcome.EXECUTED


@pytest.mark.parametrize(
    "goal",
    [{"x": 11, "y": 0, "yaw": 0}, {"x": 10, "y": 0, "yaw": 0},
     {"x": 0, "y": 0, "yaw": 0, "frame_id": "odom"}],
)
async def test_outside_workspace_row(harness: Harness, gov: Governor, goal: Any) -> None:
    d = await gov.decide(command("navigate", goal), PLANNER)
    check(d, 409, Outcome.SAFETY_VIOLATION, ErrorCode.COMMAND_REJECTED, "workspace_violation")
    one_new_entry(harness, 0)


async def test_inside_workspace_executes(gov: Governor) -> None:
    d = await gov.decide(command("navigate", {"x": 9.9, "y": -9.9, "yaw": 1}), PLANNER)
    assert d.outcome is Outcome.EXECUTED


async def test_confidence_block_row(harness: Harness) -> None:
    gov = await harness.governor("confidence_gate: {min_confidence: 0.7, on_fail: block}")
    d = await gov.decide(command("move", {"linear_x": 0.1}, confidence=0.69,
                                 ai_model="m"), PLANNER)
    check(d, 409, Outcome.DENIED, ErrorCode.COMMAND_REJECTED, "confidence_below_gate")
    d = await gov.decide(command("move", {"linear_x": 0.1}, ai_model="m"), PLANNER)
    check(d, 409, Outcome.DENIED, ErrorCode.COMMAND_REJECTED, "confidence_below_gate")
    d = await gov.decide(command("move", {"linear_x": 0.1}, confidence=0.7, ai_model="m"),
                         PLANNER)
    assert d.outcome is Outcome.EXECUTED
    d = await gov.decide(command("move", {"linear_x": 0.1}), PLANNER)  # no AI: a human's
    assert d.outcome is Outcome.EXECUTED
    d = await gov.decide(command("estop", confidence=0.01), PLANNER)  # never gated
    assert d.outcome is Outcome.EXECUTED


async def test_confidence_escalate_goes_pending(harness: Harness) -> None:
    gov = await harness.governor("confidence_gate: {min_confidence: 0.7, on_fail: escalate}")
    d = await gov.decide(command("move", {"linear_x": 0.1}, confidence=0.2,
                                 ai_model="m"), PLANNER)
    check(d, 202, Outcome.PENDING_AUTH)


async def test_rate_limit_row(harness: Harness, gov: Governor) -> None:
    move = {"linear_x": 0.1}
    decisions = [await gov.decide(command("move", move), principal("v", Role.USER))
                 for _ in range(101)]
    assert all(d.outcome is Outcome.EXECUTED for d in decisions[:100])
    check(decisions[100], 429, Outcome.DENIED, ErrorCode.RATE_LIMITED)
    assert harness.entries[-1]["deny_reason"] == "RATE_LIMITED"
    harness.clock.advance(0.6)  # 100/min refills one every 0.6 s
    d = await gov.decide(command("move", move), principal("v", Role.USER))
    assert d.outcome is Outcome.EXECUTED


async def test_estop_is_never_rate_limited(gov: Governor) -> None:
    slow = Principal("slow", Role.USER, rate_limit_per_min=1)
    move = command("move", {"linear_x": 0.1})
    assert (await gov.decide(move, slow)).outcome is Outcome.EXECUTED
    assert (await gov.decide(move, slow)).error_code is ErrorCode.RATE_LIMITED
    for _ in range(5):  # stop and e-stop: never rate-limited
        assert (await gov.decide(command("stop"), slow)).outcome is Outcome.EXECUTED
        d = await gov.decide(command("estop", message_id=MID), slow)  # not even as a retry
        assert d.outcome is Outcome.EXECUTED


async def test_robot_unavailable_row(harness: Harness, gov: Governor) -> None:
    harness.dispatcher.available = False
    d = await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    check(d, 503, Outcome.FAILED, ErrorCode.ROBOT_UNAVAILABLE)
    entry = one_new_entry(harness, 0)
    assert (entry["event"], entry["outcome"]) == ("COMMAND_DISPATCHED", "failed")


@pytest.mark.logs_traceback  # (a fault injected on purpose)
async def test_dispatch_exception_is_failed_not_a_crash(harness: Harness, gov: Governor) -> None:
    harness.dispatcher.raises = RuntimeError("bridge bug")
    d = await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    check(d, 503, Outcome.FAILED, ErrorCode.ROBOT_UNAVAILABLE, "dispatch_error")
    # Write-ahead: the decision entry, then COMMAND_FAILED for the send that failed.
    ahead, failed = harness.entries
    assert (ahead["event"], ahead["outcome"]) == ("COMMAND_DISPATCHED", "executed")
    assert (failed["event"], failed["outcome"]) == ("COMMAND_FAILED", "failed")
    assert failed["message_id"] == ahead["message_id"] and failed["audit_id"] == d.audit_id


async def test_command_for_another_robot_is_refused(harness: Harness, gov: Governor) -> None:
    body = {"message_type": 1, "ruri": "rcan://registry.local/clearpath/husky/other-0002",
            "action": "move", "parameters": {"linear_x": 0.1}}
    d = await gov.decide(validate_command(json.dumps(body).encode()), PLANNER)
    check(d, 400, Outcome.DENIED, ErrorCode.INVALID_RURI, "not_this_robot")
    body["ruri"] = RURI + "/nav"
    d = await gov.decide(validate_command(json.dumps(body).encode()), PLANNER)
    assert d.outcome is Outcome.EXECUTED


@pytest.mark.parametrize("action", ["stop", "estop"])
async def test_a_stop_addressed_to_another_robot_still_stops(
        harness: Harness, gov: Governor, action: str) -> None:
    """It reached this robot's bridge, authenticated: stopping is the safe reading."""
    other = "rcan://registry.local/clearpath/husky/other-0002"
    body = {"message_type": 1, "ruri": other, "action": action}
    d = await gov.decide(validate_command(json.dumps(body).encode()), PLANNER)
    check(d, 200, Outcome.EXECUTED)
    assert d.warnings == [f"addressed to {other}, not this robot ({RURI})"]
    assert [c[0] for c in harness.dispatcher.calls] == [action]


@pytest.mark.logs_traceback  # (a fault injected on purpose)
async def test_failing_safety_check_denies(harness: Harness, gov: Governor,
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(*_: object) -> None:
        raise ZeroDivisionError

    move_policy = gov._safety.policies["move"]  # type: ignore[attr-defined]
    monkeypatch.setattr(move_policy, "checks", (*move_policy.checks, broken))
    d = await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    check(d, 409, Outcome.DENIED, ErrorCode.COMMAND_REJECTED, "safety_check_error")
    assert harness.dispatcher.calls == []


# -- e-stop latch across a restart ----------------------------------------------------------


async def test_estop_latch_survives_restart_and_clears_only_by_owner(harness: Harness) -> None:
    gov = await harness.governor()
    assert (await gov.decide(command("estop"), VIEWER)).outcome is Outcome.EXECUTED
    await harness.restart()
    gov = await harness.governor()
    assert gov.latch.latched
    d = await gov.decide(command("move", {"linear_x": 0.1}), PLANNER)
    assert d.reason == "estop_active"
    d = await gov.decide(command("clear_estop"), PLANNER)
    check(d, 403, Outcome.DENIED, ErrorCode.INSUFFICIENT_PRIVILEGES)
    assert gov.latch.latched
    d = await gov.decide(command("clear_estop"), OPS)
    assert d.outcome is Outcome.EXECUTED and not gov.latch.latched
    assert harness.entries[-1]["event"] == "ESTOP_CLEARED"
    await harness.restart()
    gov = await harness.governor()
    assert not gov.latch.latched
    assert (await gov.decide(command("move", {"linear_x": 0.1}), PLANNER)).outcome is (
        Outcome.EXECUTED)
    verify(harness.tmp / "audit.jsonl", harness.logs[0].public_key)


async def test_unreadable_estop_state_starts_latched(harness: Harness) -> None:
    (harness.tmp / "estop.state").write_text("{garbage")
    gov = await harness.governor()
    assert gov.latch.latched


async def test_failed_clear_keeps_the_latch(harness: Harness, gov: Governor) -> None:
    await gov.decide(command("estop"), VIEWER)
    harness.dispatcher.available = False
    d = await gov.decide(command("clear_estop"), OPS)
    assert d.outcome is Outcome.FAILED and gov.latch.latched


# -- idempotency ----------------------------------------------------------------------------

MID = "0b6c3c9e-58cd-4bd1-9a51-2f1b2e1d33a0"


async def test_retry_returns_first_outcome_without_executing_twice(
    harness: Harness, gov: Governor
) -> None:
    first = await gov.decide(command("move", {"linear_x": 0.3}, message_id=MID), PLANNER)
    again = await gov.decide(command("move", {"linear_x": 0.3}, message_id=MID), PLANNER)
    assert again == first
    assert len(harness.dispatcher.calls) == 1
    assert len(harness.entries) == 1
    harness.clock.advance(601)  # the window is 10 minutes
    later = await gov.decide(command("move", {"linear_x": 0.3}, message_id=MID), PLANNER)
    assert later.audit_id != first.audit_id
    assert len(harness.dispatcher.calls) == 2


async def test_concurrent_duplicates_execute_once(harness: Harness, gov: Governor) -> None:
    cmd = command("move", {"linear_x": 0.3}, message_id=MID)
    decisions = await asyncio.gather(*(gov.decide(cmd, PLANNER) for _ in range(20)))
    assert len({d.audit_id for d in decisions}) == 1
    assert len(harness.dispatcher.calls) == 1
    assert len(harness.entries) == 1


async def test_refusals_are_replayed_too_and_ids_are_per_principal(
    harness: Harness, gov: Governor
) -> None:
    too_fast = command("move", {"linear_x": 5}, message_id=MID)
    first = await gov.decide(too_fast, PLANNER)
    assert (await gov.decide(too_fast, PLANNER)).audit_id == first.audit_id
    # Another principal cannot pre-empt or read someone else's message_id.
    other = await gov.decide(command("stop", message_id=MID), ADMIN)
    assert other.outcome is Outcome.EXECUTED


# -- concurrency ----------------------------------------------------------------------------


async def test_1000_concurrent_decisions_leave_a_verifying_chain(harness: Harness) -> None:
    gov = await harness.governor()
    cmds = [command("move", {"linear_x": (i % 7) / 10}) for i in range(1000)]
    decisions = await asyncio.gather(*(gov.decide(c, ADMIN) for c in cmds))
    assert all(d.outcome is Outcome.EXECUTED for d in decisions)
    # The end of a stream replaced meanwhile is audited by a task of its own, which may still
    # be writing (a busy machine): the chain is read once they are done.
    await asyncio.gather(*gov._tasks)
    head = verify(harness.tmp / "audit.jsonl", harness.logs[0].public_key)
    # Each move replaced the stream of the one before. Every stream's end is audited: in the
    # entry of the move that replaced it (`applied.replaces`, the stream running when that
    # move was decided), or, when another one had started meanwhile, in an entry of its own.
    ended = [e for e in harness.entries if e["event"] == "STREAM_ENDED"]
    assert head.count == 1000 + len(ended)
    replaced = {e["applied"]["replaces"]["message_id"] for e in harness.entries
                if e["event"] == "COMMAND_DISPATCHED" and "replaces" in e["applied"]}
    running = {gov.streams.active.message_id} if gov.streams.active else set()
    assert {c.message_id for c in cmds} == replaced | {e["message_id"] for e in ended} | running
    entries = [e for e in harness.entries if e["event"] != "STREAM_ENDED"]
    assert [e["event"] for e in entries] == ["COMMAND_DISPATCHED"] * 1000
    assert {e["audit_id"] for e in entries} == {d.audit_id for d in decisions}
    assert {e["message_id"] for e in entries} == {c.message_id for c in cmds}


async def test_a_cancelled_caller_still_gets_its_command_audited(
    harness: Harness, gov: Governor
) -> None:
    task = asyncio.create_task(gov.decide(command("move", {"linear_x": 0.1}), PLANNER))
    await asyncio.sleep(0)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    await asyncio.gather(*gov._tasks)
    assert [e["event"] for e in harness.entries] == ["COMMAND_DISPATCHED"]


@pytest.mark.parametrize("steps", range(12))
async def test_a_caller_cancelled_at_any_step_leaves_audit_and_robot_agreeing(
    harness: Harness, gov: Governor, steps: int
) -> None:
    """Cancelled after `steps` loop turns: a decision once begun runs to its end all the same,
    so every command audited as dispatched also reached the dispatcher."""
    cmds = [command("move", {"linear_x": 0.1 + k / 100}) for k in range(3)]
    callers = [asyncio.create_task(gov.decide(c, PLANNER)) for c in cmds]
    for _ in range(steps):
        await asyncio.sleep(0)
    for caller in callers:
        caller.cancel()
    await asyncio.gather(*callers, return_exceptions=True)
    await asyncio.gather(*gov._tasks)
    dispatched = [e for e in harness.entries if e["event"] == "COMMAND_DISPATCHED"]
    assert len(dispatched) == len(harness.dispatcher.calls)
    # Cancelled before its first step a caller has asked nothing; after it, all its command.
    assert len(dispatched) == (0 if steps == 0 else len(cmds))


async def test_a_decision_task_cancelled_before_it_ran_does_not_leave_its_caller_waiting(
    gov: Governor
) -> None:
    caller = asyncio.create_task(gov.decide(command("move", {"linear_x": 0.1}), PLANNER))
    for _ in range(100):  # until the caller has handed the decision to its task
        if gov._tasks:
            break
        await asyncio.sleep(0)
    assert gov._tasks, "the decision runs in a task of its own"
    for task in gov._tasks:
        task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await asyncio.wait_for(caller, 5.0)


@pytest.mark.logs_traceback  # (a fault injected on purpose)
async def test_a_failing_decision_reaches_its_caller_or_the_log(
    gov: Governor, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    async def broken(*_: Any) -> Decision:
        await asyncio.sleep(0)
        raise RuntimeError("decision bug")

    monkeypatch.setattr(gov, "_decide", broken)
    with pytest.raises(RuntimeError, match="decision bug"):
        await gov.decide(command("move", {"linear_x": 0.1}), PLANNER)
    caller = asyncio.create_task(gov.decide(command("move", {"linear_x": 0.1}), PLANNER))
    await asyncio.sleep(0)
    caller.cancel()
    await asyncio.gather(caller, return_exceptions=True)
    await asyncio.gather(*gov._tasks)
    assert any("after its caller left" in r.getMessage() and r.exc_info
               for r in caplog.records)


async def test_lifecycle_and_session_loss(harness: Harness, gov: Governor) -> None:
    await gov.start()
    await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    harness.clock.advance(1.0)
    gov.heartbeat(PLANNER)
    harness.clock.advance(1.5)
    await gov.sweep()  # heartbeat kept it alive
    assert harness.entries[-1]["event"] == "COMMAND_DISPATCHED"
    harness.clock.advance(0.6)
    await gov.sweep()
    entry = [e for e in harness.entries if e["event"] != "STREAM_ENDED"][-1]
    assert (entry["event"], entry["principal"], entry["outcome"]) == (
        "NETWORK_LOSS_SAFE_STOP", "planner", "executed")
    assert harness.dispatcher.calls[-1] == ("stop", {})
    await gov.sweep()  # once per loss
    await gov.stop()
    assert [e["event"] for e in harness.entries if e["event"] != "STREAM_ENDED"] == [
        "BRIDGE_STARTED", "COMMAND_DISPATCHED", "NETWORK_LOSS_SAFE_STOP", "BRIDGE_STOPPED"]
    assert [(e["params"]["reason"], e["principal"]) for e in harness.entries
            if e["event"] == "STREAM_ENDED"] == [("session_lost", "planner")]


@pytest.mark.parametrize("timeout_s", [0.5, 10.0])
async def test_the_session_timeout_is_the_configs(harness: Harness, timeout_s: float) -> None:
    """Profile §10.8: the silence a session survives is `safety.session_timeout_s`, not the
    default 2.0 — shorter (a robot that must stop sooner) or longer."""
    gov = await harness.governor(safety_extra=f"session_timeout_s: {timeout_s}")
    await gov.start()
    await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    harness.clock.advance(timeout_s * 0.9)
    await gov.sweep()
    assert "NETWORK_LOSS_SAFE_STOP" not in [e["event"] for e in harness.entries]
    harness.clock.advance(timeout_s * 0.2)
    await gov.sweep()
    assert [e["event"] for e in harness.entries].count("NETWORK_LOSS_SAFE_STOP") == 1
    assert harness.dispatcher.calls[-1] == ("stop", {})
    await gov.stop()


@pytest.mark.logs_traceback  # (a fault injected on purpose)
async def test_broken_audit_log_refuses_commands(harness: Harness, gov: Governor) -> None:
    gov.audit._broken = OSError("disk gone")
    d = await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    assert (d.http_status, d.outcome, d.reason) == (503, Outcome.FAILED, "audit_unavailable")
    assert harness.dispatcher.calls == []


async def test_only_stops_skip_the_held_turn_of_a_group_commit(
    gov: Governor, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An e-stop, a `stop` and a session-loss stop reach the robot without waiting for more
    entries to share their fsync; everything else may wait the loop turn."""
    urgent: dict[str, bool] = {}
    append, seal = gov.audit.append, gov.audit.seal

    def spied(record: Any, kw: dict[str, Any]) -> None:
        urgent[record.event.value + ":" + str(record.action_type)] = kw.get("urgent", False)

    async def spying(record: Any, **kw: Any) -> Any:
        spied(record, kw)
        return await append(record, **kw)

    def spying_seal(record: Any, **kw: Any) -> Any:  # a stop's entry, sealed with its halt
        spied(record, kw)
        return seal(record, **kw)

    monkeypatch.setattr(gov.audit, "append", spying)
    monkeypatch.setattr(gov.audit, "seal", spying_seal)
    await gov.decide(command("move", {"linear_x": 0.1}), PLANNER)
    await gov.decide(command("stop"), PLANNER)
    await gov.safe_stop(PLANNER)
    await gov.decide(command("estop"), PLANNER)
    await gov.decide(command("clear_estop"), ADMIN)
    assert urgent == {
        "COMMAND_DISPATCHED:move": False, "COMMAND_DISPATCHED:stop": True,
        "STREAM_ENDED:move": False,  # the stream's zero went out at once; this only records it
        "NETWORK_LOSS_SAFE_STOP:stop": True, "ESTOP:estop": True,
        "ESTOP_CLEARED:clear_estop": False,
    }
