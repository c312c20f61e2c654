"""The Thought log alone (§16.5): a thought id is its first sender's; others who name it get
records of their own, bounded per id, and never rewrite the first."""

from __future__ import annotations

from rcan_rtps.governance.thoughts import NAMERS, ThoughtLog
from rcan_rtps.rcan import Role
from tests.governance.govhelpers import OPS, command, principal


def _named(log: ThoughtLog, sender: str, model: str) -> None:
    sent = command("move", {"linear_x": 0.1, "duration_s": 1}, ai_provider="acme",
                   ai_model=model, ai_reasoning=f"{sender}'s reason", thought_id="th")
    log.remember(sent, principal(sender, Role.USER), 0, outcome="executed", audit_id=None)


def test_the_first_sender_keeps_the_thought_and_sees_who_else_named_it() -> None:
    log = ThoughtLog()
    _named(log, "planner", "m1")
    for n in range(NAMERS + 3):  # more senders than kept per id
        _named(log, f"p{n}", f"forged-{n}")
    _named(log, "planner", "m2")  # the first sender's own later command does update it
    first = log.read("th", OPS)
    assert first is not None
    assert (first.principal, first.model, first.reasoning) == ("planner", "m2",
                                                               "planner's reason")
    assert first.also_named_by == [f"p{n}" for n in range(NAMERS - 1)]
    theirs = log.read("th", OPS, "p0")
    assert theirs is not None and (theirs.model, theirs.also_named_by[:1]) == (
        "forged-0", ["planner"])
    assert log.read("th", OPS, f"p{NAMERS}") is None  # past the bound: the audit has it


def _thought(log: ThoughtLog, thought_id: str, n: int = 0) -> None:
    sent = command("stop", {}, ai_provider="acme", ai_model="m", thought_id=thought_id)
    log.remember(sent, principal("planner", Role.USER), n, outcome="executed", audit_id=None)


def test_the_log_keeps_the_newest_thoughts_and_each_ones_newest_commands() -> None:
    """docs/rcan-profile.md §16.5: the last 1 024 thoughts, each with up to 64 commands (a
    bridge that ran for months must not grow without bound; the audit log has everything)."""
    log = ThoughtLog()
    for n in range(70):
        _thought(log, "busy", n)
    busy = log.read("busy", OPS)
    assert busy is not None and len(busy.commands) == 64
    for n in range(1024):
        _thought(log, f"t{n}")
    assert log.read("busy", OPS) is None  # the oldest let go first
    assert log.read("t0", OPS) is not None and log.read("t1023", OPS) is not None
