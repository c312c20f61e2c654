"""Issue 23 item 9: what a restart takes up, and e-stop floods.

- the latch is the stricter of the latch file and the signed audit chain (a file rewritten to
  `latched: false` no longer starts the robot unlatched);
- motion locks persist across restarts (re-engaged and recorded; one no longer configured is
  recorded as released);
- e-stops repeated while latched are each answered and sent, and recorded together.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from govhelpers import OPS, PLANNER, VIEWER, Harness, audit_entries, command
from streamhelpers import stream_governor

from rcan_rtps.governance.audit import AuditLog
from rcan_rtps.governance.governor import Governor
from rcan_rtps.governance.resume import resume
from rcan_rtps.rcan import Outcome


async def _stopped(gov: Governor) -> None:
    await gov.stop()
    await gov.audit.close()


@pytest.mark.parametrize("how", ["rewritten", "deleted", "clean stop", "crash"])
async def test_a_latch_file_saying_clear_does_not_outrank_the_audit(harness: Harness,
                                                                    how: str) -> None:
    gov = await harness.governor()
    await gov.start()
    assert (await gov.decide(command("estop"), VIEWER)).outcome is Outcome.EXECUTED
    if how == "crash":
        await gov.audit.close()  # no BRIDGE_STOPPED: the log ends at the e-stop
    else:
        await _stopped(gov)
    state = harness.tmp / "estop.state"
    if how == "deleted":
        state.unlink()
    else:
        state.write_text(json.dumps({"latched": False, "by": "someone", "at_ms": 1}))
    harness.logs.clear()
    gov = await harness.governor()
    assert gov.latch.latched, "the signed log's e-stop was never cleared"
    await gov.start()
    started = harness.entries[-1]
    assert (started["event"], started["params"]["estop_latched"]) == ("BRIDGE_STARTED", True)
    d = await gov.decide(command("move", {"linear_x": 0.1}), PLANNER)
    assert d.reason == "estop_active"
    await _stopped(gov)


async def test_a_cleared_estop_starts_clear(harness: Harness) -> None:
    gov = await harness.governor()
    await gov.start()
    await gov.decide(command("estop"), VIEWER)
    assert (await gov.decide(command("clear_estop"), OPS)).outcome is Outcome.EXECUTED
    await _stopped(gov)
    harness.logs.clear()
    gov = await harness.governor()
    assert not gov.latch.latched
    await gov.start()
    await _stopped(gov)


@pytest.mark.logs_traceback  # (a fault injected on purpose)
async def test_a_clear_that_was_not_persisted_stays_latched_after_a_crash(
        harness: Harness) -> None:
    """ESTOP_CLEARED written, then the latch file write failed (COMMAND_FAILED): latched."""
    gov = await harness.governor()
    await gov.start()
    await gov.decide(command("estop"), VIEWER)
    state = harness.tmp / "estop.state"
    state.unlink()
    state.mkdir()  # the atomic write of the clear fails now
    d = await gov.decide(command("clear_estop"), OPS)
    assert d.outcome is Outcome.FAILED and gov.latch.latched
    await gov.audit.close()
    state.rmdir()
    state.write_text(json.dumps({"latched": False}))
    harness.logs.clear()
    gov = await harness.governor()
    assert gov.latch.latched
    await gov.audit.close()


async def test_locks_are_held_again_after_a_restart(tmp_path: Path) -> None:
    gov, _, _, _ = await stream_governor(tmp_path)
    await gov.start()
    for action in ("lock", "unlock", "lock"):
        d = await gov.decide(command(action, {"name": "teleop"}), OPS)
        assert d.outcome is Outcome.EXECUTED
    await gov.audit.close()  # a crash: the lock was never released
    for _ in range(2):  # and a clean restart after that keeps it too
        gov, _, _, _ = await stream_governor(tmp_path)
        await gov.start()
        refused = await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)  # USER: 10 < 50
        assert (refused.outcome, refused.reason) == (Outcome.DENIED, "motion_locked")
        started = [e for e in audit_entries(tmp_path / "audit.jsonl")
                   if e["event"] == "BRIDGE_STARTED"][-1]
        assert started["params"]["locks"] == {"teleop": "ops"}
        await _stopped(gov)
    gov, _, _, _ = await stream_governor(tmp_path)
    await gov.start()
    assert (await gov.decide(command("unlock", {"name": "teleop"}), OPS)).outcome is \
        Outcome.EXECUTED
    await _stopped(gov)
    assert resume(tmp_path / "audit.jsonl").locks == {}


async def test_a_lock_the_config_dropped_is_recorded_as_released(tmp_path: Path) -> None:
    gov, _, _, _ = await stream_governor(tmp_path)
    await gov.start()
    await gov.decide(command("lock", {"name": "teleop"}), OPS)
    await _stopped(gov)
    config = Harness(tmp_path, gov._clock).config()  # type: ignore[arg-type]  # no locks
    log = await AuditLog.open(config.bridge.audit.path, config.bridge.audit.key_path)
    gov = Governor.from_config(config, audit=log, dispatcher=gov._dispatcher)
    await gov.start()
    started = audit_entries(tmp_path / "audit.jsonl")[-1]
    assert started["params"]["locks"] == {} and started["params"]["locks_released"] == ["teleop"]
    await _stopped(gov)


async def test_repeated_estops_are_answered_sent_and_recorded_together(
        harness: Harness) -> None:
    gov = await harness.governor()
    await gov.start()
    first = await gov.decide(command("estop"), VIEWER)
    before = len(harness.entries)
    repeats = [await gov.decide(command("estop", {"reason": "again"}), who)
               for who in [VIEWER] * 300 + [PLANNER] * 20]
    assert {(d.http_status, d.audit_id) for d in repeats} == {(200, first.audit_id)}
    assert len([c for c in harness.dispatcher.calls if c[0] == "estop"]) == 321  # all sent
    assert len(harness.entries) == before  # nothing written yet: the flood costs no disk
    assert (await gov.decide(command("clear_estop"), OPS)).outcome is Outcome.EXECUTED
    written = harness.entries[before:]
    tallies = {e["principal"]: e["params"]["count"] for e in written
               if e["event"] == "ESTOP_REPEATED"}
    assert tallies == {"viewer": 300, "planner": 20}
    assert written[-1]["event"] == "ESTOP_CLEARED"  # the repeats it cleared come first
    again = await gov.decide(command("estop"), VIEWER)  # a new e-stop: a new entry
    assert again.audit_id != first.audit_id and harness.entries[-1]["event"] == "ESTOP"
    await _stopped(gov)


async def test_repeats_are_recorded_every_minute_and_at_stop(harness: Harness) -> None:
    gov = await harness.governor()
    await gov.start()
    await gov.decide(command("estop"), VIEWER)
    await gov.decide(command("estop", message_id="not-a-uuid"), VIEWER)
    await gov.sweep()
    assert harness.entries[-1]["event"] == "ESTOP"
    harness.clock.advance(61)
    await gov.sweep()
    entry = harness.entries[-1]
    assert (entry["event"], entry["params"]["count"]) == ("ESTOP_REPEATED", 1)
    assert "not a UUID" in entry["warnings"][0]  # the entry's: request content (bounded)
    await gov.decide(command("estop"), PLANNER)
    await _stopped(gov)
    counted = [e for e in harness.entries if e["event"] == "ESTOP_REPEATED"]
    assert [(e["principal"], e["params"]["count"]) for e in counted] == [("viewer", 1),
                                                                          ("planner", 1)]
    assert harness.entries[-1]["params"]["estop_latched"] is True  # BRIDGE_STOPPED
