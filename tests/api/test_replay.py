"""Issue 24 item 4: the §8.3 replay window for messages carrying rcan_version >= 1.5.

Stale (408 MESSAGE_STALE) and replayed (409 REPLAY_DETECTED) messages are refused and audited,
without their payload; a stale or replayed stop still stops, with a warning. The 1.2 forms keep
the idempotent retry.
"""

from __future__ import annotations

import json
import uuid
from typing import Any

from rcan.safety import make_estop_message, make_resume_message, make_stop_message

from tests.api.apihelpers import Api
from tests.api.test_rcan3_messages import TARGET, sdk_command
from tests.api.test_stop_lane import WS_BACKLOG, _cmd, _held_socket, _outcome


def versioned(msg: dict[str, Any], api: Api, age_s: float = 0.0) -> dict[str, Any]:
    """An SDK SAFETY message that says its version (the SDK leaves it out)."""
    return {**msg, "rcan_version": "3.2", "timestamp_ms": int((api.clock.time() - age_s) * 1000)}


def _refused(status: int, body: dict[str, Any], http: int, code: str) -> None:
    assert (status, body["error_code"], body["status"]) == (http, code, "blocked"), body


async def test_a_stale_command_is_refused_and_audited_without_its_payload(api: Api) -> None:
    msg = sdk_command(api, "move", {"linear_x": 0.3})
    api.clock.advance(31)  # the default window is 30 s
    status, body = await api.command("planner", msg)
    _refused(status, body, 408, "MESSAGE_STALE")
    assert body["msg_id"] == msg["msg_id"]
    entry = api.entry(body["audit_id"])
    assert (entry["event"], entry["message_id"]) == ("COMMAND_REJECTED", msg["msg_id"])
    assert entry["deny_reason"].startswith("MESSAGE_STALE")
    assert entry["params"] is None and entry["action_type"] is None
    assert api.dispatcher.calls == []


async def test_a_replayed_command_is_refused_and_audited(api: Api) -> None:
    msg = sdk_command(api, "move", {"linear_x": 0.3, "duration_s": 1.0})
    assert (await api.command("planner", msg))[0] == 200
    api.clock.advance(5)
    status, body = await api.command("planner", msg)
    _refused(status, body, 409, "REPLAY_DETECTED")
    assert api.entry(body["audit_id"])["deny_reason"] == "REPLAY_DETECTED"
    status, body = await api.command("ops", msg)  # whoever sends it again
    _refused(status, body, 409, "REPLAY_DETECTED")
    assert [a for a, _ in api.dispatcher.calls] == ["move"]


async def test_clocks_a_little_ahead_are_allowed(api: Api) -> None:
    ahead = sdk_command(api, "stop")
    ahead["timestamp"] += 4.5  # within clock_ahead_s (5 s)
    assert (await api.command("planner", ahead))[0] == 200
    far = sdk_command(api, "move", {"linear_x": 0.1})
    far["timestamp"] += 6.0
    status, body = await api.command("planner", far)
    _refused(status, body, 408, "MESSAGE_STALE")
    assert "ahead" in body["reason"]


async def test_the_window_is_configurable(tmp_path: Any) -> None:
    api = await Api(tmp_path, bridge_extra="security: {replay_window_s: 60}").start()
    try:
        msg = sdk_command(api, "stop")
        api.clock.advance(45)
        status, body = await api.command("planner", msg)
        assert (status, body["status"]) == (200, "ok"), body
    finally:
        await api.close()


async def test_a_stale_or_replayed_stop_still_stops(api: Api) -> None:
    stop = versioned(make_stop_message(ruri=TARGET, reason="drill"), api, age_s=11)
    status, body = await api.command("planner", stop)  # SAFETY's window is 10 s
    assert (status, body["outcome"], body["status"]) == (200, "executed", "ok"), body
    assert any(w.startswith("MESSAGE_STALE") for w in body["warnings"]), body
    estop = versioned(make_estop_message(ruri=TARGET, reason="drill"), api)
    for _ in range(2):
        status, body = await api.command("viewer", estop)
        assert (status, body["outcome"]) == (200, "executed"), body
    assert any(w.startswith("REPLAY_DETECTED") for w in body["warnings"]), body
    assert api.gov.latch.latched
    sdk_stop = sdk_command(api, "stop")
    api.clock.advance(31)
    status, body = await api.command("planner", sdk_stop)
    assert (status, body["outcome"]) == (200, "executed"), body
    assert body["warnings"] and api.entry(body["audit_id"])["warnings"] == body["warnings"]


async def test_a_stale_or_replayed_resume_clears_nothing(api: Api) -> None:
    assert (await api.command("viewer", make_estop_message(ruri=TARGET, reason="x")))[0] == 200
    stale = versioned(make_resume_message(ruri=TARGET, reason="ok"), api, age_s=11)
    status, body = await api.command("ops", stale)
    _refused(status, body, 408, "MESSAGE_STALE")
    fresh = versioned(make_resume_message(ruri=TARGET, reason="ok"), api)
    assert (await api.command("ops", fresh))[0] == 200
    assert not api.gov.latch.latched
    assert (await api.command("viewer", make_estop_message(ruri=TARGET, reason="y")))[0] == 200
    status, body = await api.command("ops", fresh)
    _refused(status, body, 409, "REPLAY_DETECTED")
    assert api.gov.latch.latched


async def test_1_2_messages_keep_the_idempotent_retry(api: Api) -> None:
    """No rcan_version: no window; a repeated message_id is the first outcome again."""
    body = {"action": "move", "params": {"linear_x": 0.2, "duration_s": 1.0},
            "message_id": str(uuid.uuid4())}
    first = await api.command("planner", body)
    api.clock.advance(60)  # past any replay window, within the 10 min of retries
    again = await api.command("planner", body)
    assert first == again and first[0] == 200
    assert [a for a, _ in api.dispatcher.calls] == ["move"]


async def test_a_message_a_full_socket_queue_refused_may_be_sent_again(api: Api) -> None:
    """A versioned message refused 429 by a full WebSocket queue was never taken: its retry
    is decided, not refused as a replay (before: 409 REPLAY_DETECTED, its id spent by a
    message nothing was done with). Once decided, the same message again is a replay."""
    ws = await _held_socket(api)
    for _ in range(WS_BACKLOG):
        await ws.send_str(_cmd("move", params={"linear_x": 0.1}))
    msg = sdk_command(api, "move", {"linear_x": 0.2, "duration_s": 1.0})
    await ws.send_str(json.dumps(msg))
    refused = await _outcome(ws)
    assert (refused["http_status"], refused["body"]["reason"]) == (429, "too_many_in_flight")
    api.dispatcher.hold.set()
    assert [(await _outcome(ws))["http_status"] for _ in range(1 + WS_BACKLOG)] == \
        [200] * (1 + WS_BACKLOG)
    for expected in (200, 409):  # its retry, then a replay of it
        await ws.send_str(json.dumps(msg))
        frame = await _outcome(ws)
        assert frame["http_status"] == expected, frame
    await ws.close()


async def test_a_timestamp_past_any_float_is_refused_clearly_and_a_stop_still_stops(
        api: Api, caplog: Any) -> None:
    """A `timestamp_ms` of 401 digits (JSON integers have no bound; one turned into seconds
    overflowed a float): the e-stop that carries it still latches, a stop still stops,
    anything else is refused 400 with its path — never 503 internal_error with a traceback
    (before: every one of these, the e-stop included, was refused so, nothing stopped)."""
    huge = 10**400
    estop = {**make_estop_message(ruri=TARGET, reason="drill"), "rcan_version": "3.2",
             "timestamp_ms": huge}
    status, body = await api.command("viewer", estop)
    assert (status, body["outcome"]) == (200, "executed"), body
    assert api.gov.latch.latched
    stop = {"message_type": 1, "ruri": TARGET, "action": "stop", "rcan_version": "3.2",
            "timestamp_ms": huge}
    status, body = await api.command("planner", stop)
    assert (status, body["outcome"]) == (200, "executed"), body
    others = [
        {"message_type": 1, "ruri": TARGET, "action": "move", "rcan_version": "3.2",
         "parameters": {"linear_x": 0.1}, "timestamp_ms": huge},
        {"message_type": 4, "rcan_version": "3.2", "timestamp_ms": huge},
        {"type": "INVOKE", "skill": "nudge", "msg_id": "i-huge", "rcan_version": "3.2",
         "timestamp_ms": huge},
        {"type": "INVOKE", "skill": "nudge", "msg_id": "i-huge-2", "rcan_version": "3.2",
         "timestamp_ms": huge, "timestamp": 1.0},
    ]
    for other in others:
        status, body = await api.command("planner", other)
        assert (status, body["error_code"], body["path"]) == (
            400, "SCHEMA_VALIDATION_FAILED", "$.timestamp_ms"), body
    assert "Traceback" not in caplog.text and "unexpectedly" not in caplog.text
    assert [a for a, _ in api.dispatcher.calls if a == "move"] == []
