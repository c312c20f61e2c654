"""Issue 23 item 1, at the parser: whatever else a body gets wrong, if it says stop it is a stop;
any other body with a repeated key is refused."""

from __future__ import annotations

import json
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rcan_rtps.rcan import SchemaValidationError, validate_command
from rcan_rtps.rcan._salvage import Pairs, _Reader, _Shallow, duplicate_key

_scalars = (st.none() | st.booleans() | st.integers()
            | st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=12))
_values = st.recursive(
    _scalars,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner,
                                                                max_size=3),
    max_leaves=12,
)
_keys = st.sampled_from(["action", "params", "parameters", "message_id", "message_type",
                         "ruri", "role", "ai", "confidence", "timestamp_ms", "cmd", "x"]) \
    | st.text(max_size=8)


def _text(pairs: list[tuple[str, Any]]) -> bytes:
    """A JSON object in exactly this order, repeated keys and all."""
    return ("{" + ", ".join(f"{json.dumps(k)}: {json.dumps(v)}" for k, v in pairs)
            + "}").encode()


@settings(max_examples=400, deadline=None)
@given(junk=st.lists(st.tuples(_keys, _values), max_size=6), where=st.integers(0, 6),
       word=st.sampled_from(["estop", "ESTOP", " estop ", "Estop"]),
       key=st.sampled_from(["action", "cmd"]))
def test_any_object_that_says_estop_is_an_estop(junk: list[tuple[str, Any]], where: int,
                                                word: str, key: str) -> None:
    pairs = list(junk)
    pairs.insert(min(where, len(pairs)), (key, word))
    cmd = validate_command(_text(pairs))
    assert cmd.action == "estop"


@settings(max_examples=300, deadline=None)
@given(junk=st.lists(st.tuples(_keys, _values), max_size=6), where=st.integers(0, 6))
def test_an_estop_beside_a_stop_is_the_estop(junk: list[tuple[str, Any]], where: int) -> None:
    pairs = [("action", "stop"), *junk]
    pairs.insert(min(where, len(pairs)), ("action", "estop"))
    assert validate_command(_text(pairs)).action == "estop"


@settings(max_examples=300, deadline=None)
@given(junk=st.lists(st.tuples(_keys, _values), max_size=6),
       event=st.sampled_from(["ESTOP", "STOP"]))
def test_any_safety_message_that_says_stop_is_that_stop(junk: list[tuple[str, Any]],
                                                        event: str) -> None:
    pairs = [*junk, ("message_type", 6), ("safety_event", event)]
    if any(k in ("action", "cmd") and isinstance(v, str)
           and v.strip().lower() == "estop" for k, v in junk):
        return  # an e-stop said elsewhere in the body wins (tested above)
    assert validate_command(_text(pairs)).action == ("estop" if event == "ESTOP" else "stop")


def _reference_duplicate(raw: bytes) -> bool:
    found = False

    def hook(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        nonlocal found
        keys = [k for k, _ in pairs]
        found = found or len(keys) != len(set(keys))
        return dict(pairs)

    json.loads(raw, object_pairs_hook=hook)
    return found


@settings(max_examples=500, deadline=None)
@given(pairs=st.lists(st.tuples(st.sampled_from(["a", "b", "c:d", "ä", ""]), _values),
                      max_size=5),
       nested=st.booleans())
def test_duplicate_detection_matches_a_full_parse(pairs: list[tuple[str, Any]],
                                                  nested: bool) -> None:
    raw = _text(pairs)
    if nested:
        raw = b'{"params": ' + raw + b', "list": [' + raw + b"]}"
    found = duplicate_key(raw, json.loads(raw))
    assert (found is not None) == _reference_duplicate(raw)


@pytest.mark.parametrize(("raw", "path"), [
    (b'{"action": "move", "action": "navigate"}', "$.action"),
    (b'{"action": "move", "params": {"linear_x": 0.1, "linear_x": 5}}', "$.params.linear_x"),
    (b'{"action": "arm_joint", "params": {"points": [{"a": 1, "a": 2}]}}', "$.params.points[0].a"),
    (b'{"action": "clear_estop", "action": "clear_estop"}', "$.action"),
])
def test_other_bodies_with_a_repeated_key_are_refused_naming_it(raw: bytes, path: str) -> None:
    with pytest.raises(SchemaValidationError) as info:
        validate_command(raw)
    assert info.value.path == path and "duplicate key" in info.value.detail


def test_colons_inside_strings_do_not_hide_or_invent_duplicates() -> None:
    raw = b'{"action": "move", "ruri": "rcan://a:1/b", "params": {"linear_x": 0.1}}'
    assert duplicate_key(raw, json.loads(raw)) is None
    raw = b'{"a:": 1, "a:": 2}'
    found = duplicate_key(raw, json.loads(raw))
    assert found is not None and found.key == "a:"


def test_a_salvaged_stop_keeps_what_is_valid() -> None:
    mid = "5b1e0f8e-8b0c-4d55-9b2a-1f1bb9f3a4a1"
    cmd = validate_command(json.dumps({
        "action": "stop", "message_id": mid, "ai_model": "planner-7b", "confidence": 0.4,
        "params": {"reason": "door opened", "bogus": 1}}).encode())
    assert (cmd.action, cmd.message_id, cmd.client_message_id) == ("stop", mid, True)
    assert cmd.ai is not None and (cmd.ai.model, cmd.ai.confidence) == ("planner-7b", 0.4)
    assert cmd.requested == {"reason": "door opened", "bogus": 1}
    assert cmd.warnings == ("$.params: Object contains unknown field `bogus`",)


_json_values = st.recursive(
    _scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                max_size=4),
    max_leaves=30,
)


@settings(max_examples=400, deadline=None)
@given(value=_json_values, indent=st.sampled_from([None, 0, 2]))
def test_the_shallow_reader_reads_what_pythons_json_reads(value: Any, indent: int | None) -> None:
    """`_Shallow` (for what is nested too deeply for Python's json) against json.loads, the
    reference, on anything shallower than its depth; pairs kept alike."""
    text = json.dumps(value, indent=indent)
    assert _Shallow(text, _Reader(), pairs=False).read() == json.loads(text)
    assert _Shallow(text, _Reader(), pairs=True).read() == json.loads(
        text, object_pairs_hook=Pairs)


@pytest.mark.parametrize("text", ['{"a": 1,}', '{"a" 1}', "[1 2]", '{"a": [}', "[[[", '{"a": 1} x',
                                  '{"a": ' + "[" * 40 + "]" * 39 + "}", "{'a': 1}"])
def test_the_shallow_reader_refuses_what_is_not_json(text: str) -> None:
    with pytest.raises(ValueError):
        _Shallow(text, _Reader(), pairs=False).read()
