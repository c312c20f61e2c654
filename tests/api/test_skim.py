"""`Skeleton`: a large JSON text streamed into a small one of the same shape, each string cut to
its first `keep` bytes between whole characters and escapes (`api._skim`)."""

from __future__ import annotations

import json
from typing import Any

import msgspec
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rcan_rtps.api._skim import Skeleton

KEEP = 24

scalars = st.none() | st.booleans() | st.integers(-10**6, 10**6) | \
    st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=80)
keys = st.text("abcdefghijklmnopqrstuvwxyz_", max_size=KEEP)  # kept whole: cut, two may meet
values = st.recursive(scalars, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(
    keys, inner, max_size=4), max_leaves=20)


def _skeleton(text: bytes, cuts: list[int], keep: int = KEEP, cap: int = 10**6) -> Skeleton:
    skeleton = Skeleton(keep, cap)
    at = 0
    for cut in [*sorted(c % (len(text) + 1) for c in cuts), len(text)]:
        skeleton.feed(text[at:cut])
        at = cut
    return skeleton


def _encoded_size(text: str, ensure_ascii: bool) -> int:
    return len(json.dumps(text, ensure_ascii=ensure_ascii).encode()) - 2


def _cut_to_prefixes(original: Any, skimmed: Any, ensure_ascii: bool) -> None:
    """`skimmed` is `original` with each string a prefix of itself, whole if it fitted."""
    if isinstance(original, str):
        assert isinstance(skimmed, str) and original.startswith(skimmed)
        if _encoded_size(original, ensure_ascii) <= KEEP:
            assert skimmed == original
        else:  # cut at the last whole unit that fits: the next one would not have
            assert _encoded_size(skimmed, ensure_ascii) <= KEEP
            assert _encoded_size(original[:len(skimmed) + 1], ensure_ascii) > KEEP
    elif isinstance(original, list):
        assert isinstance(skimmed, list) and len(skimmed) == len(original)
        for a, b in zip(original, skimmed, strict=True):
            _cut_to_prefixes(a, b, ensure_ascii)
    elif isinstance(original, dict):
        assert isinstance(skimmed, dict) and skimmed.keys() == original.keys()
        for key in original:
            _cut_to_prefixes(original[key], skimmed[key], ensure_ascii)
    else:
        assert skimmed == original


@settings(max_examples=400, deadline=None)
@given(values, st.booleans(), st.sampled_from([None, 0, 2]), st.lists(st.integers(0, 10**4),
                                                                      max_size=8))
def test_a_skeleton_decodes_to_the_value_with_its_strings_cut(
        value: Any, ensure_ascii: bool, indent: int | None, cuts: list[int]) -> None:
    """Whatever the chunks, escapes (`\\u00e9`, surrogate pairs) or UTF-8: the skeleton is
    JSON, of the same shape, each string whole or a prefix cut between whole characters."""
    text = json.dumps(value, ensure_ascii=ensure_ascii, indent=indent).encode()
    skeleton = _skeleton(text, cuts)
    assert skeleton.size == len(text) and not skeleton.over
    _cut_to_prefixes(value, msgspec.json.decode(skeleton.text), ensure_ascii)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300), st.lists(st.integers(0, 400), max_size=6))
def test_any_bytes_are_skimmed_without_a_raise(data: bytes, cuts: list[int]) -> None:
    skeleton = _skeleton(data, cuts)
    assert len(skeleton.text) <= len(data) + 1  # (a string left open is not closed)


@pytest.mark.parametrize("string", ["é" * 40, "\U0001F600" * 40, "\\\"\n" * 40])
@pytest.mark.parametrize("ensure_ascii", [True, False])
def test_a_string_is_never_cut_inside_a_character_or_escape(string: str,
                                                            ensure_ascii: bool) -> None:
    text = json.dumps({"action": "stop", "reason": string}, ensure_ascii=ensure_ascii)
    for piece in (1, 5, 7, 1000):
        raw = text.encode()
        skeleton = _skeleton(raw, list(range(piece, len(raw), piece)), keep=25)
        reason = msgspec.json.decode(skeleton.text)["reason"]
        assert reason and string.startswith(reason) and skeleton.shortened == 1


def test_what_makes_a_body_large_is_dropped_and_its_shape_kept() -> None:
    text = json.dumps({"action": "estop", "reason": "x" * 10**6}, indent=4).encode() + \
        b" " * 10**6
    skeleton = _skeleton(text, list(range(0, len(text), 65536)), keep=8)
    assert skeleton.text == b'{"action":"estop","reason":"xxxxxxxx"}'
    assert (skeleton.size, skeleton.shortened) == (len(text), 1)


def test_a_body_large_by_its_shape_goes_over_the_cap() -> None:
    skeleton = Skeleton(keep=64, cap=1000)
    assert not skeleton.feed(json.dumps({"action": "stop", "x": [0] * 1000}).encode())
    assert skeleton.over


def test_a_string_of_escapes_is_skipped_whole() -> None:
    """Past the cut, escapes are skipped in one regex match: an escaped quote never ends a
    string, whichever chunk its backslash came in."""
    text = b'{"reason":"' + b'\\\\\\"' * 50000 + b'","action":"stop"}'
    for piece in (2, 3, 65536):
        skeleton = _skeleton(text, list(range(piece, len(text), piece)), keep=8)
        assert msgspec.json.decode(skeleton.text) == {"reason": '\\"\\"', "action": "stop"}
