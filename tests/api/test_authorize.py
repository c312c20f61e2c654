"""Issue 24: AUTHORIZE (§16.4) is a HiTL review in a message, through the same governed path
as POST /api/hitl/authorize and /deny (role checks, n-of-m, audit); and every reply to a 3.x
message carries msg_id and status, salvaged stops and 400s included.

AUTHORIZE's shape: tests/data/rcan-spec/authorize.json (numbered 45, the canonical AUTHORIZE;
see SOURCE.md).
"""

from __future__ import annotations

import base64
import json
from pathlib import Path
from typing import Any

from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from rcan.message import RCANMessage
from rcan.safety import make_estop_message

from tests.api.apihelpers import Api, auth, next_frame

TARGET = "rcan://registry.local/clearpath/husky/v1/a200-0001"
DATA = Path(__file__).parents[1] / "data" / "rcan-spec"
# Held for an OWNER (the harness gates arm_joint).
ARM = {"action": "arm_joint", "params": {"joints": ["elbow"], "positions": [0.8],
                                         "duration_s": 1}}


def authorize(decision: str, **fields: Any) -> dict[str, Any]:
    """authorize.json's first example, numbered 45, for this robot."""
    example = json.loads((DATA / "authorize.json").read_text())["examples"][0]
    body = {**example, "message_type": 45, "ruri": TARGET, "decision": decision, **fields}
    return {k: v for k, v in body.items() if v is not None}


async def test_authorize_approves_a_held_command_like_the_endpoint(api: Api) -> None:
    _, held = await api.command("planner", ARM)
    pending_id = held["pending_id"]
    message = authorize("APPROVE", thought_id=None, pending_id=pending_id,
                        principal_id=None)
    status, body = await api.command("planner", message)  # USER: not an approver
    assert (status, body["status"], body["msg_id"]) == (403, "blocked",
                                                        message["message_id"]), body
    assert api.entry(body["audit_id"])["action_type"] == "hitl_authorize"
    status, body = await api.command("ops", message)
    assert (status, body["outcome"], body["status"]) == (200, "executed", "ok"), body
    assert body["msg_id"] == message["message_id"]
    entry = api.entry(body["audit_id"])
    assert entry["event"] == "HITL_AUTHORIZED"
    assert entry["approvals"][0]["message_id"] == message["message_id"]
    assert [a for a, _ in api.dispatcher.calls] == ["arm_joint"]


async def test_authorize_by_thought_id_and_reject(api: Api) -> None:
    held = {"action": "move", "params": {"linear_x": 0.2, "duration_s": 1},
            "ai_model": "planner-7b", "confidence": 0.2, "thought_id": "thought_abc123def456"}
    status, body = await api.command("planner", held)  # below the confidence gate
    assert status == 202, body
    status, body = await api.command("ops", authorize("REJECT", principal_id="ops"))
    assert (status, body["outcome"], body["status"]) == (200, "denied", "blocked"), body
    assert api.entry(body["audit_id"])["event"] == "HITL_DENIED"
    status, body = await api.command("ops", authorize("APPROVE", principal_id="ops"))
    assert (status, body["reason"], body["status"]) == (404, "pending_not_found", "blocked")
    assert api.dispatcher.calls == []


async def test_a_thought_id_once_held_by_another_command_approves_nothing(api: Api) -> None:
    """Bait and switch: the owner reviews a slow move held under a thought id; its issuer
    withdraws it and holds a fast one under the same id; the owner's AUTHORIZE, naming the
    thought it reviewed, ran the fast move on 9523eb7. A thought id that named another held
    command names none (a pending_id is never reused)."""
    def held(linear_x: float) -> dict[str, Any]:
        return {"action": "move", "params": {"linear_x": linear_x, "duration_s": 1},
                "ai_model": "planner-7b", "confidence": 0.2,
                "thought_id": "thought_abc123def456"}

    status, bait = await api.command("planner", held(0.1))  # below the confidence gate
    assert status == 202, bait
    await api.call("POST", "/api/hitl/withdraw", "planner", body={"pending_id": bait["pending_id"]})
    status, switch = await api.command("planner", held(1.0))
    assert status == 202, switch
    status, body = await api.command("ops", authorize("APPROVE", principal_id="ops"))
    assert (status, body["reason"]) == (404, "pending_not_found"), body
    assert api.dispatcher.calls == [] and [p.pending_id for p in api.gov.pending()] == [
        switch["pending_id"]]
    message = authorize("APPROVE", principal_id="ops", thought_id=None,
                        pending_id=switch["pending_id"])
    status, body = await api.command("ops", message)  # named by its own id, it may be approved
    assert (status, body["outcome"]) == (200, "executed"), body


async def test_authorize_names_its_sender_truly(api: Api) -> None:
    await api.command("planner", ARM)
    message = authorize("APPROVE", thought_id=None, pending_id=api.gov.pending()[0].pending_id)
    status, body = await api.command("ops", message)  # principal_id: someone else's
    assert (status, body["reason"]) == (403, "principal_id_not_yours"), body
    assert api.gov.pending() and api.dispatcher.calls == []


async def test_authorize_counts_toward_n_of_m(tmp_path: Path) -> None:
    gates = "[{action: arm_joint, require_auth: true, authorized_roles: [OWNER], approvals: 2}]"
    harness = await Api(tmp_path, gates=gates).start()
    try:
        await harness.command("planner", ARM)
        pending_id = harness.gov.pending()[0].pending_id
        first = authorize("approve", thought_id=None, pending_id=pending_id, principal_id=None)
        status, body = await harness.command("ops", first)
        assert (status, body["status"]) == (202, "pending"), body
        second = {**first, "message_id": "6db4c5d6-e7f8-9012-abcd-123456789012"}
        status, body = await harness.command("ops2", second)
        assert (status, body["status"]) == (200, "ok"), body
    finally:
        await harness.close()

async def test_the_websocket_takes_authorize(api: Api) -> None:
    _, held = await api.command("planner", ARM)
    message = authorize("APPROVE", thought_id=None, pending_id=held["pending_id"],
                        principal_id=None)
    async with api.http.ws_connect("/api/ws", headers=auth("ops")) as ws:
        await ws.send_str(json.dumps(message))
        frame = await next_frame(ws, "outcome")
        assert (frame["http_status"], frame["body"]["status"]) == (200, "ok"), frame
    assert [a for a, _ in api.dispatcher.calls] == ["arm_joint"]


# -- item 3: every reply to a 3.x message carries msg_id and status ------------------------


async def test_a_salvaged_sdk_stop_still_carries_its_id(api: Api) -> None:
    estop = {**make_estop_message(ruri=TARGET, reason="drill"), "urgency": "high"}
    status, body = await api.command("viewer", estop)  # unknown field: salvaged, executed
    assert (status, body["outcome"]) == (200, "executed") and body["warnings"], body
    assert (body["msg_id"], body["status"]) == (estop["message_id"], "ok"), body
    stop = {**RCANMessage(cmd="stop", target=TARGET, params={"why": 1}).to_dict()}
    status, body = await api.command("planner", stop)  # unknown param: salvaged
    assert (status, body["msg_id"], body["status"]) == (200, stop["msg_id"], "ok"), body


async def test_a_400_of_a_versioned_message_carries_its_id(api: Api) -> None:
    msg = RCANMessage(cmd="move", target=TARGET, params={"linear_xx": 0.3},
                      timestamp=api.clock.time()).to_dict()
    status, body = await api.command("planner", msg)
    assert (status, body["error_code"]) == (400, "SCHEMA_VALIDATION_FAILED"), body
    assert (body["msg_id"], body["status"]) == (msg["msg_id"], "blocked"), body
    bad_ruri = {**msg, "params": {"linear_x": 0.1}, "target": "rcan://nowhere",
                "msg_id": "m-ruri"}
    status, body = await api.command("planner", bad_ruri)
    assert (status, body["error_code"], body["msg_id"]) == (400, "INVALID_RURI", "m-ruri"), body
    status, body = await api.command("planner", {"action": "mvoe"})  # 1.2: none
    assert status == 400 and "msg_id" not in body and "status" not in body


async def test_under_a_required_signature_policy_authorize_is_refused(tmp_path: Path) -> None:
    """rcan-spec defines no signature for AUTHORIZE (nor INVOKE): a principal whose policy is
    `required` is refused its approval, as an unsigned COMMAND would be (a signed approval is
    the SDK's envelope: test_signed_approvals.py, where an unsigned denial passes)."""
    key = base64.b64encode(Ed25519PrivateKey.generate().public_key().public_bytes_raw())
    required = (f"signatures: {{policy: required, keys: [{{kid: ops-ed, alg: ed25519, "
                f"public_key: {key.decode()}}}]}}")
    harness = await Api(tmp_path, principal_extra={"ops": required}).start()
    try:
        _, held = await harness.command("planner", ARM)
        message = authorize("APPROVE", thought_id=None, pending_id=held["pending_id"],
                            principal_id=None)
        status, body = await harness.command("ops", message)
        assert (status, body["error_code"]) == (403, "SIGNATURE_REQUIRED"), body
        assert body["msg_id"] == message["message_id"]
        assert harness.gov.pending() and harness.dispatcher.calls == []
        invoke = {"type": "INVOKE", "skill": "go_home", "msg_id": "inv-1"}
        status, body = await harness.command("ops", invoke)
        assert (status, body["error_code"]) == (403, "SIGNATURE_REQUIRED"), body
        # nor INVOKE_CANCEL (a `stop` is what stops a robot whatever its signature says)
        cancel = {"type": "INVOKE_CANCEL", "payload": {"msg_id": "inv-1"}}
        status, body = await harness.command("ops", cancel)
        assert (status, body["error_code"]) == (403, "SIGNATURE_REQUIRED"), body
    finally:
        await harness.close()
