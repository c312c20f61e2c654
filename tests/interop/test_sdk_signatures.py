"""Issue 24 item 5 against `rcan-rtps run --sim` (a real subprocess): the official `rcan` SDK
signs (`rcan.signing.sign_message` with an `MLDSAKeyPair`, ML-DSA-65), the bridge verifies.

The demo's config, with the USER `operator` bound to the SDK key and its policy `required`; the
OWNER `owner` has no `signatures` (off), except where it approves held commands under
`required` too (`approver_sim`): then only an SDK-signed AUTHORIZE releases them.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from rcan.address import RobotURI
from rcan.message import RCANMessage
from rcan.safety import make_estop_message, make_resume_message
from rcan.signing import MLDSAKeyPair, sign_message

from rcan_rtps.bridge.demo import OWNER_TOKEN_ENV, USER_TOKEN_ENV, demo_yaml
from tests.interop.test_demo import Demo, _example, _run_demo, call, wait_status

KEY = MLDSAKeyPair.generate()
OWNER_KEY = MLDSAKeyPair.generate()


def signed_demo_config(tmp_path: Path, domain_id: int, *, owner_signs: bool = False) -> Path:
    KEY.save_public(tmp_path / "operator.pub")
    text = demo_yaml(state_dir=tmp_path / "state", port=8765, domain_id=domain_id,
                     namespace="/robot1")
    operator = f"{{name: operator, role: USER, token_env: {USER_TOKEN_ENV}}}"
    assert operator in text
    text = text.replace(operator, (
        f"{{name: operator, role: USER, token_env: {USER_TOKEN_ENV}, signatures: "
        f"{{policy: required, keys: [{{kid: '{KEY.key_id}', public_key_file: operator.pub}}]}}}}"))
    if owner_signs:
        OWNER_KEY.save_public(tmp_path / "owner.pub")
        owner = f"{{name: owner, role: OWNER, token_env: {OWNER_TOKEN_ENV}}}"
        assert owner in text
        text = text.replace(owner, (
            f"{{name: owner, role: OWNER, token_env: {OWNER_TOKEN_ENV}, signatures: {{policy: "
            f"required, keys: [{{kid: '{OWNER_KEY.key_id}', public_key_file: owner.pub}}]}}}}"))
    path = tmp_path / "signed.rcan.yaml"
    path.write_text(text)
    return path


@pytest.fixture
def sim(tmp_path: Path, domain_id: int) -> Iterator[Demo]:
    config = signed_demo_config(tmp_path, domain_id)
    yield from _run_demo(tmp_path, domain_id, "--config", str(config))


@pytest.fixture
def approver_sim(tmp_path: Path, domain_id: int) -> Iterator[Demo]:
    config = signed_demo_config(tmp_path, domain_id, owner_signs=True)
    yield from _run_demo(tmp_path, domain_id, "--config", str(config))


@pytest.fixture
async def http() -> AsyncIterator[aiohttp.ClientSession]:
    async with aiohttp.ClientSession() as session:
        yield session


def audited(demo: Demo, audit_id: str) -> dict[str, Any]:
    for line in demo.audit.read_text().splitlines():
        entry: dict[str, Any] = json.loads(line)
        if entry["audit_id"] == audit_id:
            return entry
    raise AssertionError(f"{audit_id} is not in the audit log")


async def test_sdk_signed_commands_verify_and_a_flipped_byte_is_refused(
        sim: Demo, http: aiohttp.ClientSession) -> None:
    demo = sim
    status = await wait_status(http, demo, lambda s: s["ros"]["connected"] and
                               s["telemetry"]["position"] is not None)
    robot = RobotURI.parse(status["ruri"])
    start_x = status["telemetry"]["position"]["x"]

    async def send(body: dict[str, Any]) -> tuple[int, Any]:
        return await call(http, demo, demo.user, "POST", "/api/command", body)

    move = sign_message(RCANMessage(cmd="move", target=robot,
                                    params={"linear_x": 0.3, "duration_s": 1.0}), KEY)
    code, body = await send(move.to_dict())
    assert (code, body["status"], body["msg_id"]) == (200, "ok", move.msg_id), body
    entry = audited(demo, body["audit_id"])
    assert (entry["event"], entry["message_id"]) == ("COMMAND_DISPATCHED", move.msg_id)
    assert entry["rcan"]["sig"] == {"alg": "ml-dsa-65", "kid": KEY.key_id, "verified": True}
    await wait_status(http, demo, lambda s: s["telemetry"]["position"]["x"] > start_x + 0.05)

    flipped = sign_message(RCANMessage(cmd="move", target=robot,
                                       params={"linear_x": 0.3, "duration_s": 1.0}), KEY)
    tampered = flipped.to_dict()
    tampered["params"]["linear_x"] = 0.9  # one byte of the signed JSON: 3 → 9
    code, body = await send(tampered)
    assert (code, body["error_code"], body["reason"]) == (
        403, "SIGNATURE_INVALID", "bad_signature"), body
    entry = audited(demo, body["audit_id"])
    assert (entry["event"], entry["deny_reason"], entry["message_id"]) == (
        "COMMAND_REJECTED", "SIGNATURE_INVALID:bad_signature", flipped.msg_id)
    assert entry["rcan"]["sig"] == {"alg": "ml-dsa-65", "kid": KEY.key_id, "verified": False}

    unsigned = RCANMessage(cmd="move", target=robot, params={"linear_x": 0.1})
    code, body = await send(unsigned.to_dict())
    assert (code, body["error_code"], body["reason"]) == (
        403, "SIGNATURE_REQUIRED", "unsigned"), body
    assert audited(demo, body["audit_id"])["deny_reason"] == "SIGNATURE_REQUIRED:unsigned"


async def test_estops_latch_whatever_their_signature_says(
        sim: Demo, http: aiohttp.ClientSession) -> None:
    demo = sim
    status = await wait_status(http, demo, lambda s: s["ros"]["connected"])
    robot = RobotURI.parse(status["ruri"])

    async def send(token: str, body: dict[str, Any]) -> tuple[int, Any]:
        return await call(http, demo, token, "POST", "/api/command", body)

    async def clear() -> None:
        code, body = await send(demo.owner, make_resume_message(str(robot), "go"))
        assert (code, body["status"]) == (200, "ok"), body  # the owner's policy is off
        await wait_status(http, demo, lambda s: not s["estop"])

    # the SDK's SAFETY ESTOP carries no signature: under `required`, it still latches
    code, body = await send(demo.user, make_estop_message(str(robot), "drill"))
    assert (code, body["status"]) == (200, "ok"), body
    assert body["warnings"] == [
        "SIGNATURE_REQUIRED:unsigned: stopped all the same (a stop always stops)"]
    await wait_status(http, demo, lambda s: s["estop"])
    assert audited(demo, body["audit_id"])["warnings"] == body["warnings"]
    await clear()

    # an ESTOP COMMAND whose signature is another message's: latches too
    estop = sign_message(RCANMessage(cmd="estop", target=robot), KEY).to_dict()
    other = sign_message(RCANMessage(cmd="estop", target=robot), KEY).to_dict()
    code, body = await send(demo.user, {**estop, "sig": other["sig"]})
    assert (code, body["status"]) == (200, "ok"), body
    assert body["warnings"][0].startswith("SIGNATURE_INVALID:bad_signature"), body
    await wait_status(http, demo, lambda s: s["estop"])
    await clear()


async def test_only_an_sdk_signed_approval_releases_a_held_command(
        approver_sim: Demo, http: aiohttp.ClientSession) -> None:
    """The owner's bearer token alone (stolen, say) releases nothing under `required`."""
    demo = approver_sim
    status = await wait_status(http, demo, lambda s: s["ros"]["connected"])
    robot = RobotURI.parse(status["ruri"])
    arm = sign_message(RCANMessage(cmd="arm_joint", target=robot, params={
        "joints": ["elbow"], "positions": [0.8], "duration_s": 1}), KEY)
    code, body = await call(http, demo, demo.user, "POST", "/api/command", arm.to_dict())
    assert (code, body["status"]) == (202, "pending"), body
    pending_id = body["pending_id"]
    code, listed = await call(http, demo, demo.owner, "GET", "/api/hitl/pending")
    (held,) = listed["pending"]
    command_message_id = held["original_command"]["message_id"]

    code, body = await call(http, demo, demo.owner, "POST", "/api/hitl/authorize",
                            {"pending_id": pending_id})
    assert (code, body["error_code"], body["reason"]) == (
        403, "SIGNATURE_REQUIRED", "unsigned"), body
    assert audited(demo, body["audit_id"])["deny_reason"] == "SIGNATURE_REQUIRED:unsigned"

    def approval(key: MLDSAKeyPair, pending: str) -> dict[str, Any]:
        params = {"decision": "approve", "pending_id": pending,
                  "command_message_id": command_message_id}
        signed: dict[str, Any] = sign_message(RCANMessage(cmd="AUTHORIZE", target=robot,
                                                          params=params), key).to_dict()
        return signed

    code, body = await call(http, demo, demo.owner, "POST", "/api/command",
                            approval(KEY, pending_id))  # the operator's key: not the owner's
    assert (code, body["error_code"], body["reason"]) == (
        403, "SIGNATURE_INVALID", "kid_of_another_principal"), body
    moved = approval(OWNER_KEY, pending_id)
    moved["params"]["pending_id"] = "0" * 32  # signed for another pending_id
    code, body = await call(http, demo, demo.owner, "POST", "/api/command", moved)
    assert (code, body["error_code"], body["reason"]) == (
        403, "SIGNATURE_INVALID", "bad_signature"), body

    signed = approval(OWNER_KEY, pending_id)
    code, body = await call(http, demo, demo.owner, "POST", "/api/command", signed)
    assert (code, body["outcome"], body["msg_id"]) == (200, "executed", signed["msg_id"]), body
    entry = audited(demo, body["audit_id"])
    assert entry["event"] == "HITL_AUTHORIZED"
    assert entry["approvals"][0]["sig"] == {"alg": "ml-dsa-65", "kid": OWNER_KEY.key_id,
                                            "verified": True}
    code, body = await call(http, demo, demo.owner, "POST", "/api/command", signed)
    assert (code, body["error_code"]) == (409, "REPLAY_DETECTED"), body


async def test_the_operator_example_signs_its_approvals_with_the_sdk(
        approver_sim: Demo, http: aiohttp.ClientSession, tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    demo = approver_sim
    status = await wait_status(http, demo, lambda s: s["ros"]["connected"])
    arm = sign_message(RCANMessage(cmd="arm_joint", target=RobotURI.parse(status["ruri"]),
                                   params={"joints": ["elbow"], "positions": [0.8],
                                           "duration_s": 1}), KEY)
    code, body = await call(http, demo, demo.user, "POST", "/api/command", arm.to_dict())
    assert code == 202, body
    unsigned = await asyncio.to_thread(_example, "operator_approve.py", demo, demo.owner, "--yes")
    assert "authorize: 403 denied unsigned" in unsigned.stdout, unsigned
    assert "approvals must be signed" in unsigned.stderr
    OWNER_KEY.save(tmp_path / "owner.key")
    monkeypatch.setenv("RCAN_SIGNING_KEY", str(tmp_path / "owner.key"))
    signed = await asyncio.to_thread(_example, "operator_approve.py", demo, demo.owner, "--yes")
    assert "authorize: 200 executed" in signed.stdout, signed
