"""Issue 24: INVOKE / INVOKE_CANCEL (§19) and AUTHORIZE (§16.4) as rcan-spec writes them.

The shapes are rcan-spec's own examples, kept in tests/data/rcan-spec/ with their source
(SOURCE.md): the JSON schemas' `examples` and the §19 prose's. Where they number a message
differently from the canonical table (§3, the SDK's MessageType) the canonical number is sent.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from rcan.message import MessageType, RCANMessage

from rcan_rtps.rcan import (
    Authorization,
    Invoke,
    InvokeCancel,
    InvokeResult,
    NormalizedCommand,
    SchemaValidationError,
    invoke_command,
    reply_id,
    validate_command,
    validate_message,
)

DATA = Path(__file__).parents[1] / "data" / "rcan-spec"
PROSE = json.loads((DATA / "section-19-examples.json").read_text())


def examples(name: str) -> list[dict[str, Any]]:
    found: list[dict[str, Any]] = json.loads((DATA / name).read_text())["examples"]
    return found


def parse(body: dict[str, Any]) -> Any:
    return validate_message(json.dumps(body).encode())


@pytest.mark.parametrize("example", [*examples("invoke-message.json"), PROSE["invokeMessage"]])
def test_the_specs_invoke_examples_parse(example: dict[str, Any]) -> None:
    invoke = parse(example)
    assert isinstance(invoke, Invoke)
    assert (invoke.skill, invoke.msg_id, invoke.params) == (
        example["skill"], example["msg_id"], example.get("params", {}))
    assert invoke.timeout_ms == example.get("timeout_ms", 30_000)  # §19.2's default
    assert invoke.envelope.msg_id == example["msg_id"]  # INVOKE_RESULT's reply_to


def test_an_invoke_by_the_canonical_number_and_section_3s_skill_id() -> None:
    invoke = parse({"message_type": 11, "skill_id": "go_home", "msg_id": "m1"})
    assert isinstance(invoke, Invoke) and invoke.skill == "go_home"


def test_an_invoke_without_msg_id_gets_one() -> None:
    """§19.2: the receiver makes a UUID v4 and answers with it as reply_to."""
    invoke = parse({"type": "INVOKE", "skill": "go_home"})
    assert isinstance(invoke, Invoke) and not invoke.client_msg_id
    assert len(invoke.msg_id) == 36 and invoke.envelope.msg_id == invoke.msg_id


@pytest.mark.parametrize(("body", "path"), [
    ({"type": "INVOKE"}, "$.skill"),
    ({"type": "INVOKE", "skill": "Pick And Place"}, "$.skill"),  # §19.7's naming rule
    ({"type": "INVOKE", "skill": "a", "skill_id": "b"}, "$.skill_id"),
    ({"type": "INVOKE", "skill": "a", "timeout_ms": 0}, "$.timeout_ms"),
    ({"type": "INVOKE", "skill": "a", "speed": 3}, "$"),  # no version: strict
])
def test_a_malformed_invoke_is_a_schema_error(body: dict[str, Any], path: str) -> None:
    with pytest.raises(SchemaValidationError) as caught:
        parse(body)
    assert caught.value.path == path, caught.value


def test_a_versioned_invoke_ignores_and_records_unknown_fields() -> None:
    invoke = parse({"type": "INVOKE", "skill": "a", "rcan_version": "3.2", "speed": 3})
    assert invoke.envelope.ignored == ("speed",)
    assert invoke.envelope.audit_facts() == {"version": "3.2", "skill": "a",
                                             "ignored": ["speed"]}


def test_the_specs_cancel_shapes_parse() -> None:
    prose = parse(PROSE["invokeCancel"])
    assert isinstance(prose, InvokeCancel)
    assert (prose.invoke_id, prose.reason, prose.cancel_timeout_ms) == (
        "abc-123", "User aborted navigation task", 5000)
    for example in examples("invoke-cancel.json"):
        flat = parse({**example, "message_type": 13})  # the schema says 15 (SOURCE.md)
        assert isinstance(flat, InvokeCancel)
        assert (flat.invoke_id, flat.principal_id, flat.message_id) == (
            example["cancel_msg_id"], example["principal_id"], example["message_id"])
        assert "tok_example" not in repr(flat)  # the session token is not kept


def test_a_cancel_names_one_invoke() -> None:
    with pytest.raises(SchemaValidationError):
        parse({"type": "INVOKE_CANCEL"})
    with pytest.raises(SchemaValidationError):
        parse({"type": "INVOKE_CANCEL", "payload": {"msg_id": "a"}, "cancel_msg_id": "b"})


def test_the_specs_authorize_examples_parse() -> None:
    verdicts = []
    for example in examples("authorize.json"):
        message = parse({**example, "message_type": 45})  # the schema says 9 (SOURCE.md)
        assert isinstance(message, Authorization)
        assert (message.thought_id, message.principal_id, message.message_id) == (
            example["thought_id"], example["principal_id"], example["message_id"])
        verdicts.append(message.verdict)
    assert verdicts == ["approve", "deny"]  # APPROVE, REJECT


@pytest.mark.parametrize(("decision", "verdict"), [("approve", "approve"), ("deny", "deny")])
def test_section_16_4s_decision_words(decision: str, verdict: str) -> None:
    message = parse({"type": "AUTHORIZE", "pending_id": "p1", "decision": decision})
    assert isinstance(message, Authorization) and message.verdict == verdict


@pytest.mark.parametrize("body", [
    {"message_type": 45, "decision": "APPROVE"},  # names no held command
    {"message_type": 45, "decision": "APPROVE", "pending_id": "p", "thought_id": "t"},
    {"message_type": 45, "decision": "MAYBE", "pending_id": "p"},
])
def test_a_malformed_authorize_is_a_schema_error(body: dict[str, Any]) -> None:
    with pytest.raises(SchemaValidationError):
        parse(body)


TARGET = "rcan://registry.local/clearpath/husky/v1/a200-0001"


def sdk_message(kind: MessageType, payload: dict[str, Any]) -> tuple[RCANMessage, Any]:
    """A message of the official SDK's envelope (`RCANMessage.to_dict()`: rcan_version,
    msg_id, timestamp in Unix seconds, target…), with the number and payload `to_dict()`
    drops put back (tests/interop/test_sdk_invoke), and what it parses to."""
    message = RCANMessage(type=kind, target=TARGET, payload=payload)
    put_back = {"payload": payload} if kind is MessageType.INVOKE_CANCEL else payload
    return message, parse(message.to_dict() | {"message_type": int(kind)} | put_back)


def test_the_sdks_envelope_times_each_of_them_and_names_a_cancel_and_an_authorize() -> None:
    """The SDK's envelope gives its time as `timestamp` (seconds): read as §8.3's sent time
    when `timestamp_ms` is not given (before, an SDK-built INVOKE was refused MESSAGE_STALE,
    no timestamp); its `msg_id` is an INVOKE_CANCEL's or AUTHORIZE's own id (§19.4's
    `msg_id` is in `payload`, naming the INVOKE)."""
    sent, invoke = sdk_message(MessageType.INVOKE, {"skill_id": "nudge"})
    assert isinstance(invoke, Invoke)
    assert (invoke.msg_id, invoke.envelope.sent_at_s) == (sent.msg_id, sent.timestamp)
    sent, cancel = sdk_message(MessageType.INVOKE_CANCEL, {"msg_id": invoke.msg_id})
    assert isinstance(cancel, InvokeCancel)
    assert (cancel.invoke_id, cancel.message_id, cancel.envelope.msg_id,
            cancel.envelope.sent_at_s) == (invoke.msg_id, sent.msg_id, sent.msg_id,
                                           sent.timestamp)
    sent, authorize = sdk_message(MessageType.AUTHORIZE, {"pending_id": "p1",
                                                          "decision": "approve"})
    assert isinstance(authorize, Authorization)
    assert (authorize.message_id, authorize.envelope.sent_at_s) == (sent.msg_id,
                                                                    sent.timestamp)


@pytest.mark.parametrize(("extra", "path"), [
    ({"timestamp": 1000.0, "timestamp_ms": 2_000_000}, "$.timestamp"),
    ({"msg_id": "a", "message_id": "b"}, "$.msg_id"),
])
def test_a_cancel_that_gives_its_time_or_id_twice_must_agree(extra: dict[str, Any],
                                                             path: str) -> None:
    body = {**PROSE["invokeCancel"], "rcan_version": "3.2", **extra}
    with pytest.raises(SchemaValidationError) as caught:
        parse(body)
    assert caught.value.path == path, caught.value
    assert isinstance(parse({**body, "timestamp_ms": 1_000_000, "message_id": "a"}
                            if "timestamp" in extra else {**body, "message_id": "a"}),
                      InvokeCancel)


def test_none_of_them_is_a_command() -> None:
    for body in (PROSE["invokeMessage"], PROSE["invokeCancel"],
                 {"message_type": 45, "decision": "APPROVE", "pending_id": "p"}):
        with pytest.raises(SchemaValidationError):
            validate_command(json.dumps(body).encode())


def test_an_invoke_that_also_says_estop_is_the_estop() -> None:
    body = {"type": "INVOKE", "skill": "go_home", "rcan_version": "3.2", "action": "estop"}
    stop = parse(body)
    assert isinstance(stop, NormalizedCommand) and stop.action == "estop" and stop.warnings


def test_an_invoke_becomes_its_skills_command() -> None:
    invoke = parse({"type": "INVOKE", "skill": "go_to", "msg_id": "m-7",
                    "params": {"x": 1.5}})
    command = invoke_command(invoke, "navigate", {"x": 1.5, "y": 0, "yaw": 0})
    assert (command.action, command.message_id, command.requested) == (
        "navigate", "m-7", {"x": 1.5, "y": 0, "yaw": 0})
    with pytest.raises(SchemaValidationError) as caught:
        invoke_command(invoke, "navigate", {"x": "far", "y": 0, "yaw": 0})
    assert caught.value.path == "$.params.x"


def test_invoke_result_has_the_specs_shape() -> None:
    """What the bridge answers validates against rcan-spec's INVOKE_RESULT fields: §19.3's,
    and the conformance suite's names for two of them (invoke_id = reply_to, payload =
    result or {})."""
    import msgspec

    for example in (PROSE["invokeResult"], PROSE["invokeFailure"], PROSE["invokeNotFound"],
                    PROSE["invokeCancelledResult"]):
        written = {**example, "invoke_id": example["reply_to"],
                   "payload": example.get("result", {})}
        result = msgspec.convert(written, InvokeResult)
        assert json.loads(msgspec.json.encode(result)) == written
    with pytest.raises(msgspec.ValidationError, match="invoke_id"):
        msgspec.convert(PROSE["invokeResult"], InvokeResult)  # never written without it


@pytest.mark.parametrize(("body", "expected"), [
    (b'{"rcan_version": "3.2", "msg_id": "m-1", "cmd": 5}', "m-1"),
    (b'{"rcan": "3.2", "message_id": "m-2"}', "m-2"),
    (b'{"msg_id": "m-3", "action": "move"}', None),  # not of the 3.x generation
    (b'{"rcan_version": "3.2", "msg_id": "m-4",', None),  # not JSON
])
def test_the_id_a_refusal_echoes(body: bytes, expected: str | None) -> None:
    assert reply_id(body) == expected
