"""Red team 20: the RCAN message as attacker-controlled input, as far as the audit log must
record it.

Each test here failed on main (6969ad9) before its fix; see each test's docstring.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from rcan_rtps.api._keys import CHECKS
from rcan_rtps.governance.audit import verify
from tests.api.apihelpers import Api
from tests.api.test_rcan3_messages import sdk_command


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


async def _restarted(api: Api, after_s: float) -> Api:
    """The bridge stopped and started again on the same audit log, `after_s` later (its
    e-stop, latched by the motion the first run left, cleared)."""
    then = api.clock.time()
    await api.close()
    again = Api(api.tmp)
    again.clock.advance(then + after_s - again.clock.time())
    await again.start()
    status, _ = await again.command("ops", {"action": "clear_estop"})
    assert status == 200
    return again


async def test_a_command_replayed_after_a_restart_is_refused(tmp_path: Path) -> None:
    """The replay window lived in memory only: a captured (even signed) RCAN 3.x command sent
    again within its window after the bridge restarted was executed a second time — the
    robot moved on a replay. The ids the log's entries name whose messages could still be
    fresh are now remembered at start."""
    api = await Api(tmp_path).start()
    msg = sdk_command(api, "move", {"linear_x": 0.3, "duration_s": 1.0})
    assert (await api.command("planner", msg))[0] == 200
    again = await _restarted(api, after_s=3)
    try:
        status, body = await again.command("planner", msg)
        assert (status, body["error_code"]) == (409, "REPLAY_DETECTED"), body
        assert [action for action, _ in again.dispatcher.calls] == ["clear_estop"]
        # a stop replayed so still stops; a new message moves; an old id goes stale as ever
        stop = sdk_command(again, "stop")
        stop["msg_id"] = msg["msg_id"]
        status, body = await again.command("planner", stop)
        assert (status, body["outcome"]) == (200, "executed"), body
        assert (await again.command("planner", sdk_command(
            again, "move", {"linear_x": 0.3, "duration_s": 1.0})))[0] == 200
    finally:
        await again.close()


async def test_ids_of_a_previous_run_are_forgotten_once_stale(tmp_path: Path) -> None:
    """Only what could still be fresh is remembered: a start long after reads nothing back
    that would refuse a new message (ids are a client's to reuse once stale)."""
    api = await Api(tmp_path).start()
    msg = sdk_command(api, "move", {"linear_x": 0.3, "duration_s": 1.0})
    assert (await api.command("planner", msg))[0] == 200
    again = await _restarted(api, after_s=60)
    try:
        replay = again.app[CHECKS].replay if again.app else None
        assert replay is not None and len(replay) == 0
    finally:
        await again.close()


async def test_a_replay_after_a_restart_is_refused_whatever_the_case_of_its_uuid(
        tmp_path: Path) -> None:
    """The log names a message by its id's canonical spelling (a UUID in lower case), the
    window kept it as sent: a message whose msg_id is an upper-case UUID (signed so,
    unchangeable) passed again after a restart. One UUID is one id, however it is spelled."""
    api = await Api(tmp_path).start()
    msg = sdk_command(api, "move", {"linear_x": 0.3, "duration_s": 1.0})
    msg["msg_id"] = msg["msg_id"].upper()
    assert (await api.command("planner", msg))[0] == 200
    again = await _restarted(api, after_s=3)
    try:
        status, body = await again.command("planner", msg)
        assert (status, body.get("error_code")) == (409, "REPLAY_DETECTED"), body
        msg["msg_id"] = msg["msg_id"].lower()  # the same id
        status, body = await again.command("planner", msg)
        assert (status, body.get("error_code")) == (409, "REPLAY_DETECTED"), body
    finally:
        await again.close()
