"""Priorities and locks over velocity streams (twist_mux-like), each decision audited.

The config (streamhelpers): USER 10, OWNER and CREATOR 50, principal `low-agent` 1; locks
`teleop` (50) and `top` (1000).
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from govhelpers import ADMIN, OPS, PLANNER, audit_entries, command, principal
from streamhelpers import stream_governor

from rcan_rtps.governance.governor import Decision, Governor
from rcan_rtps.governance.streams import Velocity
from rcan_rtps.rcan import Outcome, Role

LOW = principal("low-agent", Role.USER)  # a USER with its own, lower priority
OTHER_USER = principal("other", Role.USER)


async def _entries(gov: Governor) -> list[dict[str, Any]]:
    await asyncio.gather(*gov._tasks)
    return audit_entries(Path(gov.audit.path))


def _entry(entries: list[dict[str, Any]], d: Decision) -> dict[str, Any]:
    return next(e for e in entries if e["audit_id"] == d.audit_id)


def _ended(entries: list[dict[str, Any]]) -> list[tuple[str, str, str | None]]:
    """(whose stream, why, by whom) for every stream end: its own STREAM_ENDED entry, or the
    replacing move's `applied.replaces`."""
    owners = {e["message_id"]: e["principal"] for e in entries
              if e["event"] == "COMMAND_DISPATCHED"}
    ends = []
    for e in entries:
        if e["event"] == "STREAM_ENDED":
            ends.append((e["principal"], e["params"]["reason"], e["params"]["ended_by"]))
        elif e["event"] == "COMMAND_DISPATCHED" and "replaces" in (e["applied"] or {}):
            old = e["applied"]["replaces"]
            ends.append((owners[old["message_id"]], old["reason"], e["principal"]))
    return ends


async def test_a_higher_priority_move_preempts_and_a_lower_one_is_refused(tmp_path: Path) -> None:
    gov, wire, timer, _ = await stream_governor(tmp_path)
    low = await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)  # USER: 10
    high = await gov.decide(command("move", {"linear_x": 0.5}), OPS)  # OWNER: 50, preempts
    assert low.outcome is high.outcome is Outcome.EXECUTED
    refused = await gov.decide(command("move", {"linear_x": -0.5}), PLANNER)
    assert (refused.http_status, refused.outcome, refused.error_code, refused.reason) == (
        409, Outcome.DENIED, "COMMAND_REJECTED", "lower_priority")
    assert gov.streams.active is not None and gov.streams.active.owner == "ops"
    sent = len(wire.wire)
    timer.advance(0.5)
    assert all(v.linear_x > 0 for v in wire.wire[sent:])  # the refused move sent nothing
    same = await gov.decide(command("move", {"linear_x": 0.3}), ADMIN)  # equal: replaces
    assert same.outcome is Outcome.EXECUTED
    entries = await _entries(gov)
    assert _ended(entries) == [("planner", "preempted", "ops"), ("ops", "replaced", "root")]
    rejected = _entry(entries, refused)
    assert (rejected["event"], rejected["deny_reason"], rejected["principal"]) == (
        "COMMAND_REJECTED", "COMMAND_REJECTED:lower_priority", "planner")


async def test_a_principal_priority_wins_over_its_role(tmp_path: Path) -> None:
    gov, *_ = await stream_governor(tmp_path)
    await gov.decide(command("move", {"linear_x": 0.2}), OTHER_USER)  # USER role: 10
    d = await gov.decide(command("move", {"linear_x": 0.2}), LOW)  # by name: 1
    assert d.reason == "lower_priority"
    await gov.decide(command("stop"), OTHER_USER)  # once it stops, the low one may move
    assert (await gov.decide(command("move", {"linear_x": 0.2}), LOW)).outcome is \
        Outcome.EXECUTED


async def test_a_lock_blocks_lower_priorities_until_released(tmp_path: Path) -> None:
    gov, wire, timer, _ = await stream_governor(tmp_path)
    moving = await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    locked = await gov.decide(command("lock", {"name": "teleop"}), OPS)
    assert (locked.outcome, locked.applied) == (Outcome.EXECUTED, {"name": "teleop",
                                                                   "priority": 50})
    assert gov.streams.active is None and wire.wire[-1] == Velocity()  # the lower one ended
    blocked = await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    assert (blocked.http_status, blocked.reason) == (409, "motion_locked")
    allowed = await gov.decide(command("move", {"linear_x": 0.1}), OPS)  # at the lock's level
    assert allowed.outcome is Outcome.EXECUTED
    cannot = await gov.decide(command("unlock", {"name": "teleop"}), PLANNER)  # below it
    assert cannot.reason == "lower_priority"
    await gov.decide(command("stop"), OPS)
    released = await gov.decide(command("unlock", {"name": "teleop"}), OPS)
    assert released.outcome is Outcome.EXECUTED
    again = await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    assert again.outcome is Outcome.EXECUTED
    timer.advance(0.2)
    entries = await _entries(gov)
    assert [(e["event"], e["action_type"]) for e in (_entry(entries, locked),
                                                     _entry(entries, released))] == [
        ("COMMAND_DISPATCHED", "lock"), ("COMMAND_DISPATCHED", "unlock")]
    assert _entry(entries, blocked)["deny_reason"] == "COMMAND_REJECTED:motion_locked"
    assert _entry(entries, cannot)["deny_reason"] == "COMMAND_REJECTED:lower_priority"
    assert ("planner", "preempted", "ops") in _ended(entries)
    assert next(e for e in entries if e["event"] == "STREAM_ENDED")["message_id"] == \
        moving.message_id


async def test_unknown_and_unreachable_locks_are_refused(tmp_path: Path) -> None:
    gov, *_ = await stream_governor(tmp_path)
    unknown = await gov.decide(command("lock", {"name": "nope"}), ADMIN)
    too_high = await gov.decide(command("lock", {"name": "top"}), ADMIN)  # 1000 > 50
    assert (unknown.reason, too_high.reason) == ("unknown_lock", "lower_priority")
    entries = await _entries(gov)
    assert [_entry(entries, d)["event"] for d in (unknown, too_high)] == [
        "COMMAND_REJECTED", "COMMAND_REJECTED"]
    assert gov.streams.locks == {}
