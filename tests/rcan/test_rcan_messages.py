"""Boundary validation of COMMAND bodies, RURIs and the exported JSON Schema."""

from __future__ import annotations

import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import rcan_rtps.rcan as rcan
from rcan_rtps.rcan import (
    ArmJointParams,
    InvalidRuriError,
    MoveParams,
    NavigateParams,
    SchemaValidationError,
    openapi_schemas,
    parse_ruri,
    validate_command,
)

RURI = "rcan://registry.local/clearpath/husky/a200-0001"


def body(obj: object) -> bytes:
    return json.dumps(obj).encode()


def test_public_api_is_exactly_the_export_list() -> None:
    public = {n for n in vars(rcan) if not n.startswith("_") and not n.islower()}
    public |= {n for n in vars(rcan) if n.islower() and callable(getattr(rcan, n))}
    assert len(set(rcan.__all__)) == len(rcan.__all__)
    assert set(rcan.__all__) == public


def test_short_form_normalises_with_defaults_and_generated_id() -> None:
    cmd = validate_command(body({"action": "move", "params": {"linear_x": 0.5}}),
                           new_id=lambda: "generated")
    assert cmd.params == MoveParams(linear_x=0.5, linear_y=0.0, angular_z=0.0)
    assert cmd.requested == {"linear_x": 0.5}
    assert cmd.message_id == "generated"
    assert cmd.ai is None


def test_envelope_and_short_forms_normalise_to_the_same_command() -> None:
    mid = "0b6c3c9e-58cd-4bd1-9a51-2f1b2e1d33a0"
    short = validate_command(body({
        "action": "navigate", "params": {"x": 1, "y": 2, "yaw": 0.5}, "message_id": mid,
        "ai_provider": "openai", "ai_model": "gpt-4o", "confidence": 0.9, "thought_id": "t1",
    }))
    env = validate_command(body({
        "message_type": 1, "ruri": RURI, "action": "navigate", "message_id": mid,
        "parameters": {"x": 1, "y": 2, "yaw": 0.5}, "timestamp_ms": 1, "priority": 2,
        "ai": {"provider": "openai", "model": "gpt-4o", "confidence": 0.9, "thought_id": "t1"},
    }))
    assert short.params == env.params == NavigateParams(x=1.0, y=2.0, yaw=0.5)
    assert short.ai == env.ai
    assert short.message_id == env.message_id == mid
    assert env.ruri == RURI


@pytest.mark.parametrize(
    ("raw", "path"),
    [
        (b'{"action":"move","params":{"linear_x":NaN}}', "$"),
        (b'{"action":"move","params":{"linear_x":Infinity}}', "$"),
        (b'{"action":"move","params":{"linear_x":-Infinity}}', "$"),
        (b'{"action":"move","params":{"linear_x":1e400}}', "$.params.linear_x"),
        (b'{"action":"move","params":{"angular_z":-1e400}}', "$.params.angular_z"),
        (b'{"action":"move","params":{"linear_x":' + b"9" * 400 + b"}}", "$.params.linear_x"),
        (b'{"action":"move","params":{"linear_x":"fast"}}', "$.params.linear_x"),
        (b'{"action":"move","params":{"linear_x":true}}', "$.params.linear_x"),
        (b'{"action":"move","params":{"speed":1}}', "$.params"),
        (b'{"action":"fly"}', "$.action"),
        (b'{"action":"move","params":{"now":1}}', "$.params"),
        (b'{"action":"move","confidence":1.5}', "$.confidence"),
        (b'{"action":"move","message_id":"not-a-uuid"}', "$.message_id"),
        (b'{"action":"navigate","params":{"x":1,"y":2}}', "$.params"),
        (b'{"action":"arm_joint","params":{"joints":["a"],"positions":[1,2],"duration_s":1}}',
         "$.params"),
        (b'{"action":"arm_joint","params":{"joints":["a"],"positions":[1],"duration_s":0}}',
         "$.params.duration_s"),
        (b'{"action":"arm_joint","params":{"joints":["a"],"positions":[null],"duration_s":1}}',
         "$.params.positions[0]"),
        (b'{"message_type":1,"ruri":"' + RURI.encode() + b'","action":"move",'
         b'"parameters":{"linear_x":[1]}}', "$.parameters.linear_x"),
        (b"[1, 2]", "$"),
        (b"{", "$"),
        (b"", "$"),
    ],
)
def test_schema_failures_name_the_field(raw: bytes, path: str) -> None:
    with pytest.raises(SchemaValidationError) as info:
        validate_command(raw)
    assert info.value.error_code == "SCHEMA_VALIDATION_FAILED"
    assert info.value.path == path


def test_role_claims_are_kept_for_the_governor_not_trusted() -> None:
    cmd = validate_command(body({"action": "stop", "role": "CREATOR"}))
    assert cmd.claimed_role == "CREATOR"
    cmd = validate_command(body({"action": "stop", "role_level": 5}))
    assert cmd.claimed_role == 5


def test_envelope_with_bad_ruri_is_invalid_ruri() -> None:
    with pytest.raises(InvalidRuriError) as info:
        validate_command(body({"message_type": 1, "ruri": "rcan://x/y/z/short", "action": "move"}))
    assert info.value.error_code == "INVALID_RURI"


@pytest.mark.parametrize(
    "text",
    [
        "rcan://Registry.local/a/b/abcdefgh",  # uppercase
        "rcan://r/a/b/abcdefg",  # device-id too short
        "http://r/a/b/abcdefgh",
        "rcan://r/a/abcdefgh",
        "rcan://r/a/b/abcdefgh:0",
        "rcan://r/a/b/abcdefgh:99999",
        "rcan://r/a/b/abcdefgh/cap/extra",
        "rcan://r/a/b/abcd efgh",
        "",
    ],
)
def test_invalid_ruris(text: str) -> None:
    with pytest.raises(InvalidRuriError):
        parse_ruri(text)


def test_ruri_round_trip_with_port_and_capability() -> None:
    ruri = parse_ruri("rcan://registry.local/clearpath/husky/a200-0001:8765/nav")
    assert (ruri.port, ruri.capability, ruri.device_id) == (8765, "nav", "a200-0001")
    assert str(ruri) == "rcan://registry.local/clearpath/husky/a200-0001:8765/nav"
    assert ruri.robot == RURI


def test_openapi_schemas_cover_the_messages() -> None:
    schemas = openapi_schemas()
    for name in ("ShortCommand", "EnvelopeCommand", "MoveParams", "Status", "PendingAuth",
                 "Authorize", "DecisionBody", "ErrorBody"):
        assert name in schemas
    move = schemas["MoveParams"]
    assert move["additionalProperties"] is False
    assert move["properties"]["linear_x"]["maximum"] == 1e9
    json.dumps(schemas)  # serialisable as-is


_any_number = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(10**400), max_value=10**400),
)


@settings(max_examples=200, deadline=None)
@given(field=st.sampled_from(["linear_x", "linear_y", "angular_z"]), value=_any_number)
def test_nothing_non_finite_passes_move(field: str, value: float) -> None:
    text = "NaN" if isinstance(value, float) and math.isnan(value) else repr(value)
    text = {"inf": "Infinity", "-inf": "-Infinity"}.get(text, text)
    raw = f'{{"action":"move","params":{{"{field}":{text}}}}}'.encode()
    try:
        cmd = validate_command(raw)
    except SchemaValidationError:
        return
    assert isinstance(cmd.params, MoveParams)
    assert math.isfinite(getattr(cmd.params, field))


@settings(max_examples=100, deadline=None)
@given(values=st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=1, max_size=4))
def test_nothing_non_finite_passes_arm_joint(values: list[float]) -> None:
    names = [f"j{i}" for i in range(len(values))]
    nums = ",".join({"nan": "NaN", "inf": "1e999", "-inf": "-1e999"}.get(repr(v), repr(v))
                    for v in values)
    raw = (f'{{"action":"arm_joint","params":{{"joints":{json.dumps(names)},'
           f'"positions":[{nums}],"duration_s":1.0}}}}').encode()
    try:
        cmd = validate_command(raw)
    except SchemaValidationError:
        assert not all(math.isfinite(v) and abs(v) <= 1e9 for v in values)
        return
    assert isinstance(cmd.params, ArmJointParams)
    assert all(math.isfinite(p) for p in cmd.params.positions)
