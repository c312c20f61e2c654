"""Issue 24 item 5: signed RCAN 3.x COMMANDs, trusted keys and a policy per principal.

The SDK signs (`rcan.signing.sign_message`, ML-DSA-65); Ed25519 over the SDK's bytes is ours.
Principals of the harness here: `planner` (USER) verifies when a message is signed, `ops`
(OWNER) requires signatures, `lessee` has no `signatures` (off).
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
from rcan.safety import make_estop_message, make_resume_message
from rcan.signing import MLDSAKeyPair, _canonical_message_bytes, sign_message

from rcan_rtps.config import ConfigError
from rcan_rtps.governance import AuthConfigError
from rcan_rtps.governance.signatures import Signatures
from tests.api.apihelpers import Api, auth, make_config, next_frame
from tests.api.test_rcan3_messages import TARGET

PLANNER_KEY = MLDSAKeyPair.generate()
OPS_KEY = MLDSAKeyPair.generate()
STRANGER_KEY = MLDSAKeyPair.generate()
OPS_ED = Ed25519PrivateKey.generate()


def signatures_config(tmp: Path) -> dict[str, str]:
    PLANNER_KEY.save_public(tmp / "planner.pub")  # raw bytes, as the SDK saves them
    OPS_KEY.save_public(tmp / "ops.pub")
    ed = base64.b64encode(OPS_ED.public_key().public_bytes_raw()).decode()
    return {
        "planner": f"signatures: {{keys: [{{kid: '{PLANNER_KEY.key_id}', "
                   f"public_key_file: {tmp / 'planner.pub'}}}]}}",
        "ops": f"signatures: {{policy: required, keys: [{{kid: ops-ed, alg: ed25519, "
               f"public_key: {ed}}}, {{kid: '{OPS_KEY.key_id}', "
               f"public_key_file: {tmp / 'ops.pub'}}}]}}",
    }


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[Api]:
    harness = await Api(tmp_path, principal_extra=signatures_config(tmp_path)).start()
    yield harness
    await harness.close()


def message(api: Api, cmd: str, params: dict[str, Any] | None = None,
            **fields: Any) -> RCANMessage:
    return RCANMessage(cmd=cmd, target=TARGET, params=params or {},
                       timestamp=api.clock.time(), **fields)


def sdk_signed(msg: RCANMessage, key: MLDSAKeyPair = PLANNER_KEY) -> dict[str, Any]:
    body: dict[str, Any] = sign_message(msg, key).to_dict()
    return body


def ed_signed(msg: RCANMessage, kid: str = "ops-ed") -> dict[str, Any]:
    value = OPS_ED.sign(_canonical_message_bytes(msg))
    msg.signature = {"alg": "ed25519", "kid": kid,
                     "value": base64.urlsafe_b64encode(value).decode()}
    body: dict[str, Any] = msg.to_dict()
    return body


def refused(status: int, body: dict[str, Any], code: str, reason: str) -> None:
    assert (status, body["error_code"], body["reason"], body["status"]) == (
        403, code, reason, "blocked"), body


async def test_an_sdk_signed_command_executes_and_its_key_is_audited(api: Api) -> None:
    body = sdk_signed(message(api, "move", {"linear_x": 0.4, "duration_s": 1.0}))
    status, reply = await api.command("planner", body)
    assert (status, reply["status"]) == (200, "ok"), reply
    entry = api.entry(reply["audit_id"])
    assert entry["rcan"]["sig"] == {"alg": "ml-dsa-65", "kid": PLANNER_KEY.key_id,
                                    "verified": True}
    assert [a for a, _ in api.dispatcher.calls] == ["move"]


def _tampered_params(body: dict[str, Any]) -> None:
    body["params"]["linear_x"] = 0.5


def _tampered_timestamp(body: dict[str, Any]) -> None:
    body["timestamp"] += 0.001


def _tampered_target(body: dict[str, Any]) -> None:
    body["target"] = "rcan://registry.local/clearpath/husky/v1.0/a200-0001"  # same robot


def _tampered_value(body: dict[str, Any]) -> None:
    value = body["sig"]["value"]
    middle = len(value) // 2
    body["sig"]["value"] = value[:middle] + ("A" if value[middle] != "A" else "B") + \
        value[middle + 1:]


@pytest.mark.parametrize("tamper", [_tampered_params, _tampered_timestamp, _tampered_target,
                                    _tampered_value])
async def test_a_changed_byte_is_refused_audited_and_leaves_the_id_unused(
        api: Api, tamper: Any) -> None:
    original = sdk_signed(message(api, "move", {"linear_x": 0.4, "duration_s": 1.0}))
    body = json.loads(json.dumps(original))
    tamper(body)
    status, reply = await api.command("planner", body)
    refused(status, reply, "SIGNATURE_INVALID", "bad_signature")
    assert reply["msg_id"] == original["msg_id"]
    entry = api.entry(reply["audit_id"])
    assert (entry["event"], entry["deny_reason"]) == (
        "COMMAND_REJECTED", "SIGNATURE_INVALID:bad_signature")
    assert entry["rcan"]["sig"] == {"alg": "ml-dsa-65", "kid": PLANNER_KEY.key_id,
                                    "verified": False}
    assert api.dispatcher.calls == []
    status, reply = await api.command("planner", original)  # its msg_id was not used up
    assert (status, reply["status"]) == (200, "ok"), reply


@pytest.mark.parametrize(("sign", "reason"), [
    (lambda m: sdk_signed(m, STRANGER_KEY), "unknown_kid"),
    (lambda m: sdk_signed(m, OPS_KEY), "kid_of_another_principal"),  # ops's key, not planner's
    (lambda m: ed_signed(m, kid=PLANNER_KEY.key_id), "alg_mismatch"),
    (lambda m: {**sdk_signed(m), "sig": {"alg": "rsa-pss", "kid": PLANNER_KEY.key_id,
                                          "value": "AAAA"}}, "unsupported_alg"),
    (lambda m: {**sdk_signed(m), "sig": {"alg": "ml-dsa-65", "kid": PLANNER_KEY.key_id,
                                          "value": "AAAA"}}, "malformed_signature"),
])
async def test_a_signature_verifies_only_with_a_key_of_its_sender(
        api: Api, sign: Any, reason: str) -> None:
    status, reply = await api.command("planner", sign(message(api, "move",
                                                              {"linear_x": 0.2})))
    refused(status, reply, "SIGNATURE_INVALID", reason)
    assert api.entry(reply["audit_id"])["deny_reason"] == f"SIGNATURE_INVALID:{reason}"
    assert api.dispatcher.calls == []


async def test_verify_passes_unsigned_messages_required_refuses_them(api: Api) -> None:
    unsigned = message(api, "move", {"linear_x": 0.2, "duration_s": 1.0}).to_dict()
    status, reply = await api.command("planner", unsigned)
    assert (status, reply["status"]) == (200, "ok"), reply
    unsigned = message(api, "move", {"linear_x": 0.2, "duration_s": 1.0}).to_dict()
    status, reply = await api.command("ops", unsigned)
    refused(status, reply, "SIGNATURE_REQUIRED", "unsigned")
    assert reply["msg_id"] == unsigned["msg_id"]
    assert api.entry(reply["audit_id"])["deny_reason"] == "SIGNATURE_REQUIRED:unsigned"
    # the 1.2 forms carry no signature at all
    short = {"action": "move", "params": {"linear_x": 0.2},
             "message_id": "7d0c6f1e-2a43-4a8e-9a41-0a6f1f6b2c11"}
    status, reply = await api.command("ops", short)
    assert (status, reply["error_code"], reply["reason"]) == (
        403, "SIGNATURE_REQUIRED", "unsigned"), reply
    assert "msg_id" not in reply  # a 1.2 reply
    assert api.entry(reply["audit_id"])["message_id"] == short["message_id"]
    assert len(api.dispatcher.calls) == 1


async def test_required_takes_ml_dsa_and_ed25519(api: Api) -> None:
    for body in (sdk_signed(message(api, "move", {"linear_x": 0.2}), OPS_KEY),
                 ed_signed(message(api, "stop"))):
        status, reply = await api.command("ops", body)
        assert (status, reply["status"]) == (200, "ok"), reply
        assert api.entry(reply["audit_id"])["rcan"]["sig"]["verified"] is True


async def test_under_required_confidence_and_ai_must_be_signed(api: Api) -> None:
    loose = sdk_signed(message(api, "move", {"linear_x": 0.2}, confidence=0.9), OPS_KEY)
    status, reply = await api.command("ops", loose)
    refused(status, reply, "SIGNATURE_REQUIRED", "confidence_outside_signed_params")
    loose = sdk_signed(message(api, "move", {"linear_x": 0.2}), OPS_KEY)
    loose["ai"] = {"model": "planner-7b"}
    status, reply = await api.command("ops", loose)
    refused(status, reply, "SIGNATURE_REQUIRED", "ai_outside_signed_params")
    inside = sdk_signed(message(api, "move", {"linear_x": 0.2, "duration_s": 1.0,
                                              "confidence": 0.9,
                                              "ai": {"model": "planner-7b"}}), OPS_KEY)
    status, reply = await api.command("ops", inside)
    assert (status, reply["status"]) == (200, "ok"), reply
    entry = api.entry(reply["audit_id"])
    assert (entry["ai"]["confidence"], entry["ai"]["model"]) == (0.9, "planner-7b")
    assert entry["params"] == {"linear_x": 0.2, "duration_s": 1.0}
    # beside params under `verify`: still accepted (only `required` insists); an AI command
    # names its model (§16.1)
    beside = sdk_signed(message(api, "move", {"linear_x": 0.2}, confidence=0.9))
    beside["ai"] = {"model": "planner-7b"}
    status, reply = await api.command("planner", beside)
    assert (status, reply["status"]) == (200, "ok"), reply


async def test_a_governance_field_twice_is_refused(api: Api) -> None:
    body = sdk_signed(message(api, "move", {"linear_x": 0.2, "confidence": 0.9},
                              confidence=0.9), OPS_KEY)
    status, reply = await api.command("ops", body)
    assert (status, reply["error_code"], reply["path"]) == (
        400, "SCHEMA_VALIDATION_FAILED", "$.params.confidence"), reply


async def test_stops_stop_whatever_their_signature_says(api: Api) -> None:
    status, reply = await api.command("ops", make_estop_message(ruri=TARGET, reason="drill"))
    assert (status, reply["outcome"]) == (200, "executed"), reply
    assert reply["warnings"] == [
        "SIGNATURE_REQUIRED:unsigned: stopped all the same (a stop always stops)"]
    assert api.gov.latch.latched
    assert api.entry(reply["audit_id"])["warnings"] == reply["warnings"]
    bad = sdk_signed(message(api, "estop"))
    bad["sig"]["value"] = sdk_signed(message(api, "estop"))["sig"]["value"]  # another's
    status, reply = await api.command("planner", bad)
    assert (status, reply["outcome"]) == (200, "executed"), reply
    assert reply["warnings"][0].startswith("SIGNATURE_INVALID:bad_signature")
    # clearing is no stop: under `required` RESUME must come signed (a signed clear_estop)
    status, reply = await api.command("ops", make_resume_message(ruri=TARGET, reason="go"))
    refused(status, reply, "SIGNATURE_REQUIRED", "unsigned")
    assert api.gov.latch.latched
    status, reply = await api.command("ops", ed_signed(message(api, "clear_estop")))
    assert (status, reply["outcome"]) == (200, "executed"), reply
    assert not api.gov.latch.latched


async def test_off_records_a_signature_as_unverified(api: Api) -> None:
    status, reply = await api.command("lessee", sdk_signed(message(api, "stop"), STRANGER_KEY))
    assert (status, reply["status"]) == (200, "ok"), reply
    assert api.entry(reply["audit_id"])["rcan"]["sig"] == {
        "alg": "ml-dsa-65", "kid": STRANGER_KEY.key_id, "verified": False}


async def test_the_websocket_applies_its_principals_policy(api: Api) -> None:
    async with api.http.ws_connect("/api/ws", headers=auth("ops")) as ws:
        await ws.send_str(json.dumps(message(api, "move", {"linear_x": 0.1}).to_dict()))
        frame = await next_frame(ws, "outcome")
        assert (frame["http_status"], frame["body"]["error_code"]) == (
            403, "SIGNATURE_REQUIRED"), frame
        await ws.send_str(json.dumps(sdk_signed(message(api, "move", {"linear_x": 0.1}),
                                                OPS_KEY)))
        frame = await next_frame(ws, "outcome")
        assert frame["body"]["status"] == "ok", frame


# -- config -------------------------------------------------------------------------------


def test_a_kid_belongs_to_one_principal(tmp_path: Path) -> None:
    public = base64.b64encode(OPS_ED.public_key().public_bytes_raw()).decode()
    key = f"signatures: {{keys: [{{kid: shared, alg: ed25519, public_key: {public}}}]}}"
    with pytest.raises(ConfigError, match="kid 'shared' is bound to two principals"):
        make_config(tmp_path, principal_extra={"planner": key, "ops": key})


@pytest.mark.parametrize(("key", "problem"), [
    ("{kid: k, alg: ed25519}", "exactly one of `public_key` or `public_key_file`"),
    ("{kid: k, alg: rsa, public_key: AAAA}", "Invalid enum value 'rsa'"),
    ("{kid: 'a b', public_key: AAAA}", "regex"),
])
def test_a_key_entry_is_checked(tmp_path: Path, key: str, problem: str) -> None:
    with pytest.raises(ConfigError, match=problem):
        make_config(tmp_path, principal_extra={"planner": f"signatures: {{keys: [{key}]}}"})


@pytest.mark.parametrize(("key", "problem"), [
    ("{kid: k, public_key_file: /nonexistent/k.pub}", "cannot read /nonexistent/k.pub"),
    ("{kid: k, public_key: AAAA}", "3 bytes; an ml-dsa-65 public key is 1952"),
    ("{kid: k, alg: ed25519, public_key_file: %(ml)s}",
     "is neither the 32 raw bytes of an ed25519 public key nor a PEM"),
])
def test_a_key_that_does_not_load_stops_the_start(tmp_path: Path, key: str,
                                                  problem: str) -> None:
    PLANNER_KEY.save_public(tmp_path / "ml.pub")
    config = make_config(tmp_path, principal_extra={
        "planner": f"signatures: {{keys: [{key % {'ml': tmp_path / 'ml.pub'}}]}}"})
    with pytest.raises(AuthConfigError, match=problem):
        Signatures.from_config(config.bridge.api)
