"""Issue 23 item 1: stops are the most forgiving input, on every transport.

An authenticated body that is a JSON object in which any `action` says `estop`/`stop` (or an RCAN
SAFETY message with ESTOP/STOP, as the official `rcan` SDK builds it) is executed as that stop;
what else is wrong with it is audited and returned as `warnings` in a 200 reply. A duplicate key
in any other body is a 400 naming the key.
"""

from __future__ import annotations

import asyncio
import json
import uuid
from typing import Any

import pytest
from rcan.message import RCANMessage
from rcan.safety import make_estop_message, make_resume_message, make_stop_message

from tests.api.apihelpers import RURI, Api, auth
from tests.api.test_rcan3_messages import TARGET
from tests.api.test_stop_lane import _outcome

# Each was answered 400 on 599eb3c and the robot kept moving.
JUNK_STOPS: list[tuple[str, bytes]] = [
    ("a reason", b'{"action": "estop", "params": {"reason": "person in path"}}'),
    ("an unknown parameter", b'{"action": "estop", "params": {"speed": 0}}'),
    ("an unknown field", b'{"action": "estop", "urgent": true}'),
    ("a malformed message_id", b'{"action": "estop", "message_id": "not-a-uuid"}'),
    ("a numeric message_id", b'{"action": "estop", "message_id": 7}'),
    ("duplicate keys, estop first", b'{"action": "estop", "action": "move", '
                                    b'"params": {"linear_x": 0.3}}'),
    ("duplicate keys, estop last", b'{"action": "move", "params": {"linear_x": 0.3}, '
                                   b'"action": "estop"}'),
    ("a bad RURI", b'{"message_type": 1, "ruri": "rcan://nope", "action": "estop"}'),
    ("a bad envelope", b'{"message_type": 1, "action": "estop", "priority": "high"}'),
    ("ill-typed AI fields", b'{"action": "estop", "confidence": "very"}'),
    ("shouting", b'{"action": " ESTOP "}'),
    ("RCAN 3 `cmd`", b'{"rcan": "3.2", "cmd": "estop", "params": {}}'),
    ("a SAFETY message with junk", b'{"message_type": 6, "safety_event": "ESTOP", "x": 1}'),
    # Python's json.dumps writes NaN and Infinity (not JSON): answered 400 on 9523eb7.
    ("a NaN parameter", b'{"action": "estop", "params": {"speed": NaN}}'),
    ("an Infinity timestamp", b'{"message_type": 6, "safety_event": "ESTOP", '
                              b'"timestamp_ms": Infinity, "action": "estop", "action": "move"}'),
    # An unpaired surrogate escape is legal JSON text but no UTF-8: answered 400 on 9523eb7.
    ("an unpaired surrogate", rb'{"action": "estop", "params": {"reason": "\ud800"}, '
                              rb'"\udfff": "\udc00"}'),
    # More digits than Python's int() reads, so the lenient reader refused it too: answered
    # 400 on 7124936.
    ("a 5000-digit number", b'{"action": "estop", "params": {"speed": ' + b"9" * 5000 + b"}}"),
]


def _warned(status: int, body: dict[str, Any]) -> None:
    assert (status, body["outcome"]) == (200, "executed"), body
    assert body["warnings"], body


@pytest.mark.parametrize(("what", "raw"), JUNK_STOPS, ids=[w for w, _ in JUNK_STOPS])
async def test_a_rest_estop_with_anything_wrong_still_latches(api: Api, what: str,
                                                              raw: bytes) -> None:
    status, body = await api.command("viewer", raw=raw)
    if what == "a reason":  # a declared parameter: nothing to warn about
        assert (status, body["outcome"]) == (200, "executed") and "warnings" not in body
    else:
        _warned(status, body)
    assert api.gov.latch.latched
    assert [a for a, _ in api.dispatcher.calls] == ["estop"]
    entry = api.entry(body["audit_id"])
    assert (entry["event"], entry["sent_first"]) == ("ESTOP", True)
    assert entry.get("warnings") == body.get("warnings")


async def test_a_stop_with_anything_wrong_still_stops(api: Api) -> None:
    status, body = await api.command(
        "planner", raw=b'{"action": "stop", "params": {"now": true}, "message_id": "x"}')
    _warned(status, body)
    assert [a for a, _ in api.dispatcher.calls] == ["stop"]
    assert any("message_id 'x'" in w for w in body["warnings"])
    assert api.entry(body["audit_id"])["warnings"] == body["warnings"]


async def test_a_stop_with_an_unpaired_surrogate_stops_and_is_audited(api: Api) -> None:
    status, body = await api.command(
        "planner", raw=rb'{"action": "stop", "params": {"reason": "\udfff halt \ud800"}}')
    _warned(status, body)
    assert [a for a, _ in api.dispatcher.calls] == ["stop"]
    assert api.entry(body["audit_id"])["params"] == {"reason": "\ufffd halt \ufffd"}


@pytest.mark.parametrize("raw", [
    b'{"action": "move", "action": "move", "params": {}}',
    b'{"action": "move", "params": {"linear_x": 0.1, "linear_x": 2.0}}',
    b'{"action": "navigate", "params": {"x": 1, "y": 1, "yaw": 0, "y": 50}}',
])
async def test_a_duplicate_key_in_any_other_command_is_refused(api: Api, raw: bytes) -> None:
    status, body = await api.command("planner", raw=raw)
    assert (status, body["error_code"]) == (400, "SCHEMA_VALIDATION_FAILED"), body
    assert "duplicate key" in body["reason"] and body["path"].startswith("$.")
    assert api.dispatcher.calls == []


async def test_a_duplicate_key_in_an_approval_is_refused(api: Api) -> None:
    raw = json.dumps({"pending_id": "a"})[:-1].encode() + b', "pending_id": "b"}'
    status, body = await api.call("POST", "/api/hitl/authorize", "ops", raw=raw)
    assert (status, body["error_code"], body["path"]) == (
        400, "SCHEMA_VALIDATION_FAILED", "$.pending_id")


async def test_the_move_in_a_duplicated_estop_never_runs(api: Api) -> None:
    """`{"action":"estop","action":"move"}` ran the move on 599eb3c (last key won)."""
    status, body = await api.command(
        "planner", raw=b'{"action": "estop", "action": "move", "params": {"linear_x": 0.3}}')
    _warned(status, body)
    assert [a for a, _ in api.dispatcher.calls] == ["estop"] and not api.dispatcher.samples


# -- the official SDK's SAFETY messages (message_type 6) --------------------------------------


@pytest.mark.parametrize("make", [make_estop_message, make_stop_message])
async def test_the_sdks_safety_messages_stop(api: Api, make: Any) -> None:
    msg = make(ruri=RURI, reason="operator pressed the pendant")
    status, body = await api.command("planner", body=msg)
    assert (status, body["outcome"], body["message_id"]) == (200, "executed", msg["message_id"])
    assert "warnings" not in body  # exactly as the SDK builds it: nothing wrong
    action = "estop" if msg["safety_event"] == "ESTOP" else "stop"
    assert [a for a, _ in api.dispatcher.calls] == [action]
    assert api.gov.latch.latched is (action == "estop")
    entry = api.entry(body["audit_id"])
    assert entry["params"] == {"reason": "operator pressed the pendant"}


async def test_the_sdks_to_json_of_an_estop_with_a_nan_latches(api: Api) -> None:
    """`RCANMessage.to_json` is `json.dumps`: a NaN anywhere in it is written as `NaN`."""
    msg = RCANMessage(cmd="estop", target=TARGET, params={"speed": float("nan")},
                      timestamp=api.clock.time())
    status, body = await api.command("viewer", raw=msg.to_json().encode())
    _warned(status, body)
    assert (body["msg_id"], body["status"]) == (msg.msg_id, "ok")
    assert api.gov.latch.latched
    assert api.entry(body["audit_id"])["params"] == {"speed": None}


async def test_a_nan_in_anything_but_a_stop_is_still_refused(api: Api) -> None:
    msg = RCANMessage(cmd="move", target=TARGET, params={"linear_x": float("nan")},
                      timestamp=api.clock.time())
    status, body = await api.command("planner", raw=msg.to_json().encode())
    assert (status, body["error_code"], body["path"]) == (400, "SCHEMA_VALIDATION_FAILED", "$")
    assert api.dispatcher.calls == []


async def test_the_sdks_estop_latches_for_a_guest_even_for_another_robot(api: Api) -> None:
    msg = make_estop_message(ruri="rcan://registry.local/other/robot/unit-0001", reason="x")
    status, body = await api.command("viewer", body=msg)
    _warned(status, body)
    assert api.gov.latch.latched


async def test_the_sdks_resume_clears_only_for_an_owner(api: Api) -> None:
    await api.command("viewer", body=make_estop_message(ruri=RURI, reason="x"))
    status, body = await api.command("planner", body=make_resume_message(ruri=RURI, reason="ok"))
    assert (status, body["error_code"]) == (403, "INSUFFICIENT_PRIVILEGES")
    assert api.gov.latch.latched
    status, body = await api.command("ops", body=make_resume_message(ruri=RURI, reason="ok"))
    assert (status, body["outcome"]) == (200, "executed"), body
    assert not api.gov.latch.latched


async def test_a_resume_with_junk_is_refused_not_forgiven(api: Api) -> None:
    """Only stopping is forgiving: a malformed RESUME clears nothing."""
    await api.command("viewer", body=make_estop_message(ruri=RURI, reason="x"))
    msg = {**make_resume_message(ruri=RURI, reason="ok"), "extra": 1}
    status, body = await api.command("ops", body=msg)
    assert (status, body["error_code"]) == (400, "SCHEMA_VALIDATION_FAILED")
    assert api.gov.latch.latched


# -- the WebSocket ----------------------------------------------------------------------------


@pytest.mark.parametrize(("what", "raw"), JUNK_STOPS[1:], ids=[w for w, _ in JUNK_STOPS[1:]])
async def test_a_websocket_estop_with_anything_wrong_takes_the_lane(api: Api, what: str,
                                                                    raw: bytes) -> None:
    api.dispatcher.hold = asyncio.Event()  # a move stuck in dispatch holds the socket's queue
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        await ws.send_str(json.dumps({"action": "move", "params": {"linear_x": 0.1},
                                      "message_id": str(uuid.uuid4())}))
        await asyncio.wait_for(api.dispatcher.entered.wait(), timeout=60)
        await ws.send_bytes(raw)
        frame = await _outcome(ws)
        _warned(frame["http_status"], frame["body"])
        assert api.gov.latch.latched and not api.dispatcher.hold.is_set()
        api.dispatcher.hold.set()
