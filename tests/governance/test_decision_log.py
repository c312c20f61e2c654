"""One log line per durable audit entry: decisions at INFO, safety events at WARNING."""

from __future__ import annotations

import logging

import pytest
from govhelpers import ADMIN, OPS, PLANNER, VIEWER, Harness, command

from rcan_rtps.governance.decision_log import SAFETY_EVENTS, log_entry


def _lines(caplog: pytest.LogCaptureFixture) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.name == "rcan_rtps.decisions"]


async def test_every_entry_is_one_line_with_its_principal_and_audit_id(
        harness: Harness, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="rcan_rtps.decisions")
    gov = await harness.governor()
    gov.audit.audited.subscribe(log_entry)
    decisions = [
        await gov.decide(command("move", {"linear_x": 0.2}), PLANNER),
        await gov.decide(command("move", {"linear_x": 99.0}), PLANNER),  # denied: >10 % over
        await gov.decide(command("estop"), VIEWER),
        await gov.decide(command("clear_estop"), OPS),
        await gov.decide(command("stop"), ADMIN),
    ]
    await gov.audit.close()  # runs the listeners still scheduled
    everything = _lines(caplog)
    # The e-stop ended the move's velocity stream: that is an entry (and a line) of its own.
    ended = [r for r in everything if r.getMessage().startswith("STREAM_ENDED")]
    assert [r.getMessage().split(" [")[0] for r in ended] == [
        "STREAM_ENDED by planner move (estopped)"]
    lines = [r for r in everything if r not in ended]
    assert [r.audit_id for r in lines] == [d.audit_id for d in decisions]  # type: ignore[attr-defined]
    assert [r.principal for r in lines] == [  # type: ignore[attr-defined]
        "planner", "planner", "viewer", "ops", "root"]
    assert [r.levelname for r in lines] == ["INFO", "INFO", "WARNING", "WARNING", "INFO"]
    assert lines[1].getMessage().startswith(
        "COMMAND_REJECTED by planner move -> safety_violation (COMMAND_REJECTED:velocity_limit)")
    assert lines[2].getMessage().startswith("ESTOP by viewer estop -> executed")


def test_safety_events_are_warnings() -> None:
    assert {e.value for e in SAFETY_EVENTS} >= {"ESTOP", "ESTOP_CLEARED",
                                                  "NETWORK_LOSS_SAFE_STOP", "COMMAND_FAILED"}
