"""Issue 24 items 1 and 3: the official `rcan` SDK's messages are first-class input.

The SDK is the oracle of the RCAN side (as rclpy is of the wire): every COMMAND here is built by
`rcan.message.RCANMessage` and sent as its `to_dict()`; SAFETY by `rcan.safety`. Replies to
them carry `msg_id` and `status` (`rcan.message.RCANResponse` reads them) beside today's fields.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from rcan.message import RCANMessage, RCANResponse
from rcan.safety import make_estop_message, make_resume_message

from tests.api.apihelpers import RURI, Api, auth, next_frame

# The robot of apihelpers (configured in the 1.2 form), addressed in the 2.1+ form the SDK
# insists on: the same robot.
TARGET = "rcan://registry.local/clearpath/husky/v1/a200-0001"
DATA = Path(__file__).parents[1] / "data" / "rcan-spec"


def sdk_command(api: Api, cmd: str, params: dict[str, Any] | None = None,
                **fields: Any) -> dict[str, Any]:
    msg = RCANMessage(cmd=cmd, target=TARGET, params=params or {},
                      timestamp=api.clock.time(), **fields)
    body: dict[str, Any] = msg.to_dict()
    return body


async def test_the_sdks_command_executes_and_is_audited(api: Api) -> None:
    msg = sdk_command(api, "move", {"linear_x": 0.4, "duration_s": 1.0}, confidence=0.9)
    msg["ai"] = {"model": "planner-7b"}  # the SDK has no field for it; §16.1 wants it
    status, body = await api.command("planner", msg)
    assert (status, body["outcome"]) == (200, "executed"), body
    reply = RCANResponse.from_dict(body)  # the SDK reads our reply
    assert (reply.msg_id, reply.status, reply.ok) == (msg["msg_id"], "ok", True)
    assert api.dispatcher.calls[0][0] == "move"
    entry = api.entry(body["audit_id"])
    assert (entry["event"], entry["action_type"]) == ("COMMAND_DISPATCHED", "move")
    assert entry["message_id"] == msg["msg_id"]
    assert entry["params"] == {"linear_x": 0.4, "duration_s": 1.0}
    assert entry["ai"] == {"confidence": 0.9, "model": "planner-7b", "provider": None,
                           "thought_id": None}
    assert entry["rcan"] == {"version": "3.2"}


@pytest.mark.parametrize(("who", "cmd", "params", "http", "status"), [
    ("planner", "move", {"linear_x": 3.0}, 409, "blocked"),  # over the velocity limit
    ("viewer", "move", {"linear_x": 0.1}, 403, "blocked"),  # GUEST: no control
    ("planner", "arm_joint", {"joints": ["elbow"], "positions": [0.5], "duration_s": 1.0},
     202, "pending"),  # the arm waits for an owner
])
async def test_replies_carry_the_sdks_status(api: Api, who: str, cmd: str,
                                             params: dict[str, Any], http: int,
                                             status: str) -> None:
    msg = sdk_command(api, cmd, params)
    code, body = await api.command(who, msg)
    assert (code, body["msg_id"], body["status"]) == (http, msg["msg_id"], status), body


async def test_an_unknown_parameter_is_refused_never_a_zero(api: Api) -> None:
    status, body = await api.command("planner", sdk_command(api, "move", {"linear_xx": 0.4}))
    assert (status, body["error_code"]) == (400, "SCHEMA_VALIDATION_FAILED"), body
    assert (body["path"], "linear_xx" in body["reason"]) == ("$.params", True), body
    assert api.dispatcher.calls == []


async def test_a_cmd_outside_the_registry_names_the_known_actions(api: Api) -> None:
    status, body = await api.command("planner", sdk_command(api, "move_forward"))
    assert (status, body["path"]) == (400, "$.cmd"), body
    assert "navigate" in body["reason"]


async def test_unknown_envelope_fields_are_ignored_and_recorded(api: Api) -> None:
    """§3.5: what a sender adds to a versioned message is ignored (and audited by name)."""
    msg = sdk_command(api, "move", {"linear_x": 0.2, "duration_s": 1.0}, sender="ops-console",
                      scope="control", qos=1, firmware_hash="sha256:" + "ab" * 32,
                      attestation_ref="https://robot.example/.well-known/rcan-sbom.json")
    msg["field_of_rcan_3_9"] = {"anything": True}
    status, body = await api.command("planner", msg)
    assert (status, body["status"]) == (200, "ok"), body
    facts = api.entry(body["audit_id"])["rcan"]
    assert facts["ignored"] == ["field_of_rcan_3_9", "qos", "scope", "sender"]
    assert facts["firmware_hash"] == msg["firmware_hash"]
    assert facts["attestation_ref"] == msg["attestation_ref"]


async def test_the_1_2_forms_stay_strict(api: Api) -> None:
    short = {"action": "move", "params": {"linear_x": 0.1}, "qos": 1}
    envelope = {"message_type": 1, "ruri": RURI, "action": "move", "qos": 1}
    for body in (short, envelope):
        status, reply = await api.command("planner", body)
        assert (status, reply["error_code"]) == (400, "SCHEMA_VALIDATION_FAILED"), reply
        assert "`qos`" in reply["reason"]


@pytest.mark.parametrize("version", ["2.0", "4.1", "x.y", "11"])
async def test_another_major_is_version_incompatible_and_audited(api: Api,
                                                                 version: str) -> None:
    msg = {**sdk_command(api, "move", {"linear_x": 0.1}), "rcan": version,
           "rcan_version": version}
    status, body = await api.command("planner", msg)
    assert (status, body["error_code"]) == (400, "VERSION_INCOMPATIBLE"), body
    assert (body["msg_id"], body["status"]) == (msg["msg_id"], "blocked")
    entry = api.entry(body["audit_id"])
    assert entry["deny_reason"].startswith("VERSION_INCOMPATIBLE")
    assert api.dispatcher.calls == []


async def test_a_newer_minor_is_accepted(api: Api) -> None:
    msg = {**sdk_command(api, "stop"), "rcan": "3.9", "rcan_version": "3.9"}
    status, body = await api.command("planner", msg)
    assert (status, body["status"]) == (200, "ok"), body


async def test_rcan_and_rcan_version_must_agree(api: Api) -> None:
    msg = {**sdk_command(api, "move", {"linear_x": 0.1}), "rcan": "3.1"}
    status, body = await api.command("planner", msg)
    assert (status, body["path"]) == (400, "$.rcan"), body


async def test_a_command_that_also_says_estop_is_the_estop(api: Api) -> None:
    """An ignored field must not hide a stop: the strongest stop in the body wins."""
    msg = {**sdk_command(api, "move", {"linear_x": 0.3}), "action": "estop"}
    status, body = await api.command("viewer", msg)
    assert (status, body["outcome"]) == (200, "executed"), body
    assert body["warnings"] and api.gov.latch.latched
    assert [a for a, _ in api.dispatcher.calls] == ["estop"]


async def test_an_incompatible_estop_still_latches(api: Api) -> None:
    msg = {**sdk_command(api, "estop"), "rcan": "9.0", "rcan_version": "9.0"}
    status, body = await api.command("viewer", msg)
    assert (status, body["outcome"]) == (200, "executed"), body
    assert any("VERSION" in w or "9.0" in w for w in body["warnings"]), body
    assert api.gov.latch.latched


async def test_the_sdks_safety_replies_carry_its_id(api: Api) -> None:
    estop = make_estop_message(ruri=TARGET, reason="drill")
    status, body = await api.command("viewer", estop)
    assert (status, body["msg_id"], body["status"]) == (200, estop["message_id"], "ok")
    resume = make_resume_message(ruri=TARGET, reason="clear")
    status, body = await api.command("planner", resume)
    assert (status, body["msg_id"], body["status"]) == (403, resume["message_id"], "blocked")
    assert api.gov.latch.latched


def heartbeat(api: Api, **fields: Any) -> dict[str, Any]:
    """HEARTBEAT as rcan-spec defines it (tests/data/rcan-spec/heartbeat.json)."""
    return {"message_type": 4, "ruri": TARGET, "timestamp_ms": int(api.clock.time() * 1000),
            "message_id": "f6a7b8c9-d0e1-2345-fabc-456789012345", "latency_budget_ms": 500,
            **fields}


async def test_a_heartbeat_message_holds_the_control_session(api: Api) -> None:
    status, _ = await api.command("planner", sdk_command(api, "move", {"linear_x": 0.2}))
    assert status == 200  # a held move: as long as planner's session lasts
    api.clock.advance(50)  # session_timeout_s is 60
    logged = len(api.entries)
    status, body = await api.command("planner", heartbeat(api))
    assert len(api.entries) == logged  # a HEARTBEAT is no command: not audited
    assert (status, body["ok"], body["status"], body["principal"]) == (200, True, "ok",
                                                                       "planner"), body
    assert body["msg_id"] == "f6a7b8c9-d0e1-2345-fabc-456789012345"
    api.clock.advance(50)
    await api.gov.sweep()
    assert [a for a, _ in api.dispatcher.calls] == ["move"]  # no safe stop
    api.clock.advance(11)  # 61 s of silence
    await api.gov.sweep()
    assert [a for a, _ in api.dispatcher.calls] == ["move", "stop"]


async def test_the_heartbeat_shape_is_rcan_specs(api: Api) -> None:
    """The spec's own HEARTBEAT examples are accepted, and nothing beside them (no version).

    The schema file numbers HEARTBEAT 5, from before the canonical table (§3, and the SDK's
    MessageType) made it 4 and 5 CONFIG: the examples are sent as 4 (SOURCE.md)."""
    shapes = json.loads((DATA / "heartbeat.json").read_text())
    for example in shapes["examples"]:
        status, body = await api.command("viewer", {**example, "message_type": 4,
                                                    "ruri": TARGET})
        assert (status, body["status"]) == (200, "ok"), body
    status, body = await api.command("viewer", heartbeat(api, load=0.3))
    assert (status, "`load`" in body["reason"]) == (400, True), body


async def test_the_websocket_speaks_the_sdks_messages_too(api: Api) -> None:
    """Same intake as REST: SDK COMMAND, HEARTBEAT, and the replay window."""
    msg = sdk_command(api, "move", {"linear_x": 0.2, "duration_s": 1.0})
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        for body, http, status in ((msg, 200, "ok"), (heartbeat(api), 200, "ok"),
                                   (msg, 409, "blocked")):
            await ws.send_str(json.dumps(body))
            frame = await next_frame(ws, "outcome")
            assert (frame["http_status"], frame["body"]["status"]) == (http, status), frame
    assert [a for a, _ in api.dispatcher.calls] == ["move"]
