"""Signed approvals: an approver whose signature policy is `required` releases held motion
only with an approval signed by one of its own keys — a bearer token alone (stolen, say)
releases nothing. Denials and withdrawals keep the robot still: they pass unsigned.

The official SDK signs: `sign_message(RCANMessage(cmd="AUTHORIZE", target, params={decision,
pending_id, command_message_id}), key)` (ML-DSA-65); Ed25519 over the SDK's bytes is ours.
Principals here: `ops` (OWNER) requires signatures, `ops2` (OWNER) verifies a signature when
one is given, `root` (CREATOR) has none (off); `planner` (USER) issues what is held (the
harness gates arm_joint for an OWNER).
"""

from __future__ import annotations

import base64
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from rcan.message import RCANMessage
from rcan.signing import MLDSAKeyPair, _canonical_message_bytes, sign_message

from tests.api.apihelpers import Api, auth, next_frame
from tests.api.test_authorize import ARM, authorize
from tests.api.test_rcan3_messages import TARGET

OPS_KEY = MLDSAKeyPair.generate()
OPS2_KEY = MLDSAKeyPair.generate()
STRANGER_KEY = MLDSAKeyPair.generate()
OPS_ED = Ed25519PrivateKey.generate()


def _config(tmp: Path) -> dict[str, str]:
    OPS_KEY.save_public(tmp / "ops.pub")
    OPS2_KEY.save_public(tmp / "ops2.pub")
    ed = base64.b64encode(OPS_ED.public_key().public_bytes_raw()).decode()
    return {
        "ops": f"signatures: {{policy: required, keys: [{{kid: '{OPS_KEY.key_id}', "
               f"public_key_file: {tmp / 'ops.pub'}}}, {{kid: ops-ed, alg: ed25519, "
               f"public_key: {ed}}}]}}",
        "ops2": f"signatures: {{keys: [{{kid: '{OPS2_KEY.key_id}', "
                f"public_key_file: {tmp / 'ops2.pub'}}}]}}",
    }


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[Api]:
    harness = await Api(tmp_path, principal_extra=_config(tmp_path)).start()
    yield harness
    await harness.close()


async def held(api: Api) -> tuple[str, str]:
    """A command held for an OWNER: its pending_id and the message_id its PENDING_AUTH shows."""
    status, body = await api.command("planner", ARM)
    assert status == 202, body
    shown = next(p for p in api.gov.pending() if p.pending_id == body["pending_id"])
    return body["pending_id"], shown.original_command["message_id"]


def review(api: Api, pending_id: str, command_message_id: str, decision: str = "approve",
           **params: Any) -> RCANMessage:
    return RCANMessage(cmd="AUTHORIZE", target=TARGET, timestamp=api.clock.time(),
                       params={"decision": decision, "pending_id": pending_id,
                               "command_message_id": command_message_id, **params})


def signed(msg: RCANMessage, key: MLDSAKeyPair = OPS_KEY) -> dict[str, Any]:
    body: dict[str, Any] = sign_message(msg, key).to_dict()
    return body


def ed_signed(msg: RCANMessage) -> dict[str, Any]:
    value = OPS_ED.sign(_canonical_message_bytes(msg))
    msg.signature = {"alg": "ed25519", "kid": "ops-ed",
                     "value": base64.urlsafe_b64encode(value).decode()}
    body: dict[str, Any] = msg.to_dict()
    return body


def refused(status: int, body: dict[str, Any], code: str, reason: str) -> None:
    assert (status, body["error_code"], body["reason"]) == (403, code, reason), body


async def test_a_signed_approval_releases_the_held_command(api: Api) -> None:
    pending_id, message_id = await held(api)
    body = signed(review(api, pending_id, message_id, reason="cell clear"))
    status, reply = await api.command("ops", body)
    assert (status, reply["outcome"], reply["msg_id"]) == (200, "executed", body["msg_id"]), reply
    entry = api.entry(reply["audit_id"])
    assert entry["event"] == "HITL_AUTHORIZED"
    (approval,) = entry["approvals"]
    assert (approval["principal"], approval["message_id"], approval["reason"]) == (
        "ops", body["msg_id"], "cell clear")
    assert approval["sig"] == {"alg": "ml-dsa-65", "kid": OPS_KEY.key_id, "verified": True}
    assert [a for a, _ in api.dispatcher.calls] == ["arm_joint"]


async def test_an_ed25519_signed_approval_releases_it_too(api: Api) -> None:
    pending_id, message_id = await held(api)
    status, reply = await api.command("ops", ed_signed(review(api, pending_id, message_id)))
    assert (status, reply["outcome"]) == (200, "executed"), reply


async def test_an_unsigned_approval_releases_nothing_under_required(api: Api) -> None:
    pending_id, message_id = await held(api)
    # the REST endpoint's body carries no signature: refused, audited by its pending_id
    status, reply = await api.call("POST", "/api/hitl/authorize", "ops",
                                   body={"pending_id": pending_id})
    refused(status, reply, "SIGNATURE_REQUIRED", "unsigned")
    entry = api.entry(reply["audit_id"])
    assert (entry["event"], entry["action_type"], entry["pending_id"], entry["deny_reason"]) == (
        "COMMAND_REJECTED", "hitl_authorize", pending_id, "SIGNATURE_REQUIRED:unsigned")
    # rcan-spec's AUTHORIZE (which has no signature), and the SDK's envelope unsigned
    for body in (authorize("APPROVE", thought_id=None, pending_id=pending_id,
                           principal_id=None),
                 review(api, pending_id, message_id).to_dict()):
        status, reply = await api.command("ops", body)
        refused(status, reply, "SIGNATURE_REQUIRED", "unsigned")
    assert [p.pending_id for p in api.gov.pending()] == [pending_id]
    assert api.dispatcher.calls == []


def _tampered_reason(body: dict[str, Any]) -> None:
    body["params"]["reason"] = "not what was signed"


def _tampered_timestamp(body: dict[str, Any]) -> None:
    body["timestamp"] += 0.001


@pytest.mark.parametrize(("sign", "tamper", "reason"), [
    (signed, _tampered_reason, "bad_signature"),
    (signed, _tampered_timestamp, "bad_signature"),
    (lambda m: signed(m, OPS2_KEY), None, "kid_of_another_principal"),
    (lambda m: signed(m, STRANGER_KEY), None, "unknown_kid"),
])
async def test_a_bad_or_foreign_signature_is_refused_and_audited(
        api: Api, sign: Any, tamper: Any, reason: str) -> None:
    pending_id, message_id = await held(api)
    body = sign(review(api, pending_id, message_id))
    if tamper is not None:
        tamper(body)
    status, reply = await api.command("ops", body)
    refused(status, reply, "SIGNATURE_INVALID", reason)
    entry = api.entry(reply["audit_id"])
    assert (entry["event"], entry["deny_reason"], entry["message_id"]) == (
        "COMMAND_REJECTED", f"SIGNATURE_INVALID:{reason}", body["msg_id"])
    assert entry["rcan"]["sig"] == {"alg": "ml-dsa-65", "kid": body["sig"]["kid"],
                                    "verified": False}
    assert api.gov.pending() and api.dispatcher.calls == []


async def test_a_signature_approves_only_the_held_command_it_names(api: Api) -> None:
    first, first_message = await held(api)
    second, _ = await held(api)
    # signed for the first, its pending_id changed to the second's: no longer the signed bytes
    body = signed(review(api, first, first_message))
    body["params"]["pending_id"] = second
    status, reply = await api.command("ops", body)
    refused(status, reply, "SIGNATURE_INVALID", "bad_signature")
    # signed truly for the second's pending_id but the first's message_id: the signer did not
    # review the second command
    body = signed(review(api, second, first_message))
    status, reply = await api.command("ops", body)
    refused(status, reply, "SIGNATURE_INVALID", "signed_for_another_command")
    entry = api.entry(reply["audit_id"])
    assert (entry["action_type"], entry["pending_id"], entry["deny_reason"]) == (
        "hitl_authorize", second, "SIGNATURE_INVALID:signed_for_another_command")
    assert entry["rcan"]["sig"]["verified"] is True
    assert len(api.gov.pending()) == 2 and api.dispatcher.calls == []
    # unsigned (ops2 verifies only what is signed), it names another command all the same
    status, reply = await api.command("ops2", review(api, second, first_message).to_dict())
    assert (status, reply["error_code"], reply["reason"]) == (
        409, "COMMAND_REJECTED", "not_the_held_command"), reply
    assert len(api.gov.pending()) == 2 and api.dispatcher.calls == []


@pytest.mark.parametrize("spelt", [str.upper, lambda mid: f"urn:uuid:{mid}",
                                   lambda mid: mid.replace("-", "")])
async def test_the_held_command_is_named_by_its_uuid_however_spelt(api: Api, spelt: Any
                                                                    ) -> None:
    """A UUID is one message id however it is spelt (the replay window and the command path
    read it so): an approval signed for the held command's message_id in capitals, as a URN
    or without hyphens names that command. Before, it was refused 403 SIGNATURE_INVALID
    `signed_for_another_command`: the signer had signed for this very command."""
    pending_id, message_id = await held(api)
    status, reply = await api.command("ops", signed(review(api, pending_id,
                                                           spelt(message_id))))
    assert (status, reply["outcome"]) == (200, "executed"), reply
    assert [a for a, _ in api.dispatcher.calls] == ["arm_joint"]


async def test_a_signed_approval_for_another_robot_is_audited_with_its_signature(
        api: Api) -> None:
    """A signed approval addressed to another robot releases nothing here (400 INVALID_RURI
    `not_this_robot`), and its refusal is audited as every refused AUTHORIZE is: with the
    signature's alg, kid and whether it verified. Before, that entry had no `rcan` at all:
    whose key had signed an approval sent to the wrong robot was not on record."""
    pending_id, message_id = await held(api)
    msg = review(api, pending_id, message_id)
    msg.target = TARGET.replace("a200-0001", "a200-0002")
    body = signed(msg)
    status, reply = await api.command("ops", body)
    assert (status, reply["error_code"], reply["reason"]) == (
        400, "INVALID_RURI", "not_this_robot"), reply
    entry = api.entry(reply["audit_id"])
    assert (entry["event"], entry["message_id"]) == ("COMMAND_REJECTED", body["msg_id"])
    assert entry["rcan"]["sig"] == {"alg": "ml-dsa-65", "kid": OPS_KEY.key_id,
                                    "verified": True}, entry
    assert api.gov.pending() and api.dispatcher.calls == []


async def test_a_signed_approval_is_used_once_and_only_while_fresh(api: Api) -> None:
    pending_id, message_id = await held(api)
    body = signed(review(api, pending_id, message_id))
    status, reply = await api.command("ops", body)
    assert (status, reply["outcome"]) == (200, "executed"), reply
    status, reply = await api.command("ops", body)  # the same approval again
    assert (status, reply["error_code"]) == (409, "REPLAY_DETECTED"), reply
    pending_id, message_id = await held(api)
    stale = review(api, pending_id, message_id)
    stale.timestamp -= 31.0  # older than bridge.security.replay_window_s (30 s)
    status, reply = await api.command("ops", signed(stale))
    assert (status, reply["error_code"]) == (408, "MESSAGE_STALE"), reply
    assert [p.pending_id for p in api.gov.pending()] == [pending_id]
    assert [a for a, _ in api.dispatcher.calls] == ["arm_joint"]


async def test_denials_and_withdrawals_need_no_signature(api: Api) -> None:
    pending_id, message_id = await held(api)
    status, reply = await api.call("POST", "/api/hitl/deny", "ops",
                                   body={"pending_id": pending_id})
    assert (status, reply["outcome"]) == (200, "denied"), reply
    pending_id, message_id = await held(api)
    status, reply = await api.command("ops", authorize("REJECT", thought_id=None,
                                                       pending_id=pending_id, principal_id=None))
    assert (status, reply["outcome"]) == (200, "denied"), reply
    pending_id, message_id = await held(api)
    status, reply = await api.call("POST", "/api/hitl/withdraw", "ops",
                                   body={"pending_id": pending_id})
    assert (status, reply["outcome"]) == (200, "denied"), reply
    assert api.entry(reply["audit_id"])["event"] == "HITL_WITHDRAWN"
    # a denial that is signed must verify, though
    pending_id, message_id = await held(api)
    body = signed(review(api, pending_id, message_id, decision="deny"))
    body["params"]["reason"] = "changed"
    status, reply = await api.command("ops", body)
    refused(status, reply, "SIGNATURE_INVALID", "bad_signature")
    assert [p.pending_id for p in api.gov.pending()] == [pending_id]
    assert api.dispatcher.calls == []


async def test_verify_takes_unsigned_approvals_and_refuses_bad_signatures(api: Api) -> None:
    pending_id, message_id = await held(api)
    body = signed(review(api, pending_id, message_id), OPS2_KEY)
    body["params"]["reason"] = "changed"
    status, reply = await api.command("ops2", body)
    refused(status, reply, "SIGNATURE_INVALID", "bad_signature")
    status, reply = await api.command("ops2", signed(review(api, pending_id, message_id),
                                                     OPS2_KEY))
    assert (status, reply["outcome"]) == (200, "executed"), reply
    pending_id, _ = await held(api)
    status, reply = await api.call("POST", "/api/hitl/authorize", "ops2",
                                   body={"pending_id": pending_id})
    assert (status, reply["outcome"]) == (200, "executed"), reply
    pending_id, _ = await held(api)
    status, reply = await api.call("POST", "/api/hitl/authorize", "root",  # off
                                   body={"pending_id": pending_id})
    assert (status, reply["outcome"]) == (200, "executed"), reply


async def test_the_websocket_takes_signed_approvals_only(api: Api) -> None:
    pending_id, message_id = await held(api)
    async with api.http.ws_connect("/api/ws", headers=auth("ops")) as ws:
        await ws.send_str(json.dumps(review(api, pending_id, message_id).to_dict()))
        frame = await next_frame(ws, "outcome")
        assert (frame["http_status"], frame["body"]["error_code"]) == (
            403, "SIGNATURE_REQUIRED"), frame
        assert api.dispatcher.calls == []
        await ws.send_str(json.dumps(signed(review(api, pending_id, message_id))))
        frame = await next_frame(ws, "outcome")
        assert (frame["http_status"], frame["body"]["outcome"]) == (200, "executed"), frame
    assert [a for a, _ in api.dispatcher.calls] == ["arm_joint"]


async def test_whoami_tells_the_console_whose_approvals_must_be_signed(api: Api) -> None:
    may = {who: (await api.call("GET", "/api/whoami", who))[1]["may"]
           for who in ("ops", "ops2", "root")}
    assert [may[who]["must_sign_approvals"] for who in ("ops", "ops2", "root")] == [
        True, False, False]
