"""Red team 20: the RCAN message as attacker-controlled input, as far as the audit log must
record it.

Each test here failed on main (6969ad9) before its fix; see each test's docstring.
"""

from __future__ import annotations

import pytest

from rcan_rtps.governance.audit import verify
from tests.api.apihelpers import Api


def nested_body(action: str, depth: int) -> bytes:
    """A command whose params hold a value `depth` arrays deep (made as bytes: Python's json
    cannot write it)."""
    return (b'{"action":"%s","params":{"x":' % action.encode()
            + b"[" * depth + b"1.5" + b"]" * depth + b"}}")


@pytest.mark.parametrize("action", ["stop", "estop"])
async def test_a_stop_nested_hundreds_of_levels_deep_stops_and_is_audited(
        api: Api, action: str) -> None:
    """msgspec reads a body ~1000 levels deep, but sealing its audit entry (recursive
    canonical JSON) gave up at ~500: a stop or e-stop nested 500 deep reached the robot, was
    not in the audit log, and was answered 503 `failed` (the e-stop latched all the same).
    What is deeper than a message may nest is now read as null, with a warning, as for a
    stop deeper than any parser goes."""
    status, reply = await api.command("ops", raw=nested_body(action, 500))
    assert status == 200 and reply["outcome"] == "executed", reply
    assert api.dispatcher.calls == [(action, {})]
    entry = api.entry(reply["audit_id"])
    assert any("nested more than 32 levels deep" in w for w in entry["warnings"]), entry
    verify(api.tmp / "audit.jsonl", api.log.public_key if api.log else None)


async def test_a_command_nested_hundreds_of_levels_deep_is_refused_not_an_error(
        api: Api) -> None:
    """Any other message that deep is a schema failure for its depth, refused and audited.
    (A pin of the new rule, not a failure on main: there this move was refused for its
    unknown field; a message whose schema took the deep value would have failed as above.)"""
    status, reply = await api.command("ops", raw=nested_body("move", 500))
    assert status == 400 and reply["error_code"] == "SCHEMA_VALIDATION_FAILED", reply
    assert "nested" in reply["reason"]
    assert api.dispatcher.calls == []
    assert api.entry(reply["audit_id"])["event"] == "COMMAND_REJECTED"
