"""The generated per-type codecs against cyclonedds' own codec and the reference encoder, for
every type the bundle defines (886 names: messages, services, actions and their parts).

For generated values: the typed and the plain encoder give exactly the bytes cyclonedds writes
for the same message (and the test-only reference encoder); both decoders give back the
values; valid values never leave the plain encoder's fast path; bad values raise the same
`ValueFitError` as the strict validator; truncated or garbled bytes raise `CdrDecodeError`
and nothing else; big-endian CDR decodes like little-endian.
"""

from __future__ import annotations

import math
from collections import defaultdict
from typing import Any

import pytest
from cyclonedds.idl._support import Endianness
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rcan_rtps.ros.errors import CdrDecodeError, ValueFitError
from rcan_rtps.ros.typesys.cdr import CdrCodecs
from rcan_rtps.ros.typesys.ddstypes import DdsTypes
from rcan_rtps.ros.typesys.store import TypeStore
from rcan_rtps.ros.typesys.values import MessageValues

from .cdr_reference import encode
from .offline_data import TEST_IDL, load
from .strategies import LISTED_TYPES, extreme_values, values_for

pytestmark = pytest.mark.offline

STORE = TypeStore([TEST_IDL], distro="jazzy")
VALUES = MessageValues(DdsTypes(STORE))
CODECS = CdrCodecs(VALUES.types, VALUES)
ALL_TYPES = sorted({**load("rihs01_jazzy.json")["hashes"],
                    **load("rihs01_official_jazzy.json")["hashes"]})
BY_PACKAGE: dict[str, list[str]] = defaultdict(list)
for _name in ALL_TYPES:
    BY_PACKAGE[_name.split("/")[0]].append(_name)
HEADER = bytes([0, 1, 0, 0])
SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[
    HealthCheck.too_slow, HealthCheck.data_too_large])


def check_both_ways(type_name: str, value: dict[str, Any]) -> bytes:
    codec = CODECS.of(type_name)
    message = VALUES.build(type_name, value)
    expected = bytes(message.serialize())
    fallbacks = codec.fallbacks
    assert codec.encode_plain(value) == expected, f"{type_name}: plain encoder differs"
    assert codec.fallbacks == fallbacks, f"{type_name}: valid values left the fast path"
    assert codec.encode(message) == expected, f"{type_name}: typed encoder differs"
    plain = VALUES.to_plain(type_name, message)
    assert codec.decode_plain(expected) == plain
    assert VALUES.to_plain(type_name, codec.decode(expected)) == plain
    return expected


def test_every_bundled_type_is_covered() -> None:
    assert len(ALL_TYPES) > 800 and len(BY_PACKAGE) >= 25


@pytest.mark.parametrize("package", sorted(BY_PACKAGE))
@SETTINGS
@given(data=st.data())
def test_generated_values_match_cyclonedds_both_ways(package: str, data: st.DataObject) -> None:
    type_name = data.draw(st.sampled_from(BY_PACKAGE[package]))
    value = data.draw(values_for(STORE, type_name))
    wire = check_both_ways(type_name, value)
    reference, _ = encode(STORE, type_name, value)
    assert wire == HEADER + reference


@pytest.mark.parametrize("end", ["default", "min", "max"])
def test_every_type_at_its_defaults_and_extremes(end: str) -> None:
    for type_name in ALL_TYPES:
        value = {} if end == "default" else extreme_values(STORE, type_name, end)
        check_both_ways(type_name, value)


@pytest.mark.parametrize("type_name", LISTED_TYPES)
@SETTINGS
@given(data=st.data())
def test_big_endian_cdr_decodes_like_little_endian(type_name: str, data: st.DataObject) -> None:
    value = data.draw(values_for(STORE, type_name))
    message = VALUES.build(type_name, value)
    big = bytes(message.serialize(endianness=Endianness.Big))
    assert big[:2] == b"\x00\x00"
    codec = CODECS.of(type_name)
    plain = VALUES.to_plain(type_name, message)
    assert codec.decode_plain(big) == plain
    assert VALUES.to_plain(type_name, codec.decode(big)) == plain


def test_numeric_sequences_take_arrays_and_decode_to_arrays() -> None:
    from array import array
    codec = CODECS.of("sensor_msgs/msg/LaserScan")
    fallbacks = codec.fallbacks  # (the codec is shared: other tests' bad values count too)
    ranges = array("f", [0.5, 1.5, math.inf])
    as_array = codec.encode_plain({"ranges": ranges, "intensities": array("f")})
    assert as_array == codec.encode_plain({"ranges": [0.5, 1.5, math.inf]})
    decoded = codec.decode(as_array)
    assert decoded.ranges == ranges and decoded.ranges.typecode == "f"
    assert codec.fallbacks == fallbacks
    # an array of the wrong width is not reinterpreted: it is checked like a list
    with pytest.raises(ValueFitError):
        codec.encode_plain({"ranges": array("d", [1e39])})


def test_byte_fields_decode_without_a_copy() -> None:
    codec = CODECS.of("sensor_msgs/msg/Image")
    pixels = bytes(range(256)) * 12
    data = codec.encode_plain({"height": 1, "width": 1024, "step": 3072, "data": pixels})
    image = codec.decode(data)
    assert isinstance(image.data, memoryview) and image.data.readonly
    assert image.data.obj is data and image.data == pixels


# -- bad values: the same error as the strict validator ------------------------------------
_ANY = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70)
    | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=300) | st.binary(),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=5), inner,
                                                                 max_size=3),
    max_leaves=8)


def _poke(value: Any, data: st.DataObject) -> Any:
    """`value` with one field, item or the whole replaced by anything at all."""
    if isinstance(value, dict) and value and data.draw(st.booleans()):
        key = data.draw(st.sampled_from(sorted(value)))
        return {**value, key: _poke(value[key], data)}
    if isinstance(value, list) and value and data.draw(st.booleans()):
        i = data.draw(st.integers(0, len(value) - 1))
        return [*value[:i], _poke(value[i], data), *value[i + 1:]]
    return data.draw(_ANY)


BAD_VALUE_TYPES = [*LISTED_TYPES, "test_msgs/msg/BasicTypes", "test_msgs/msg/Arrays",
                   "test_msgs/msg/BoundedSequences", "test_msgs/msg/WStrings",
                   "test_msgs/msg/UnboundedSequences"]


@pytest.mark.parametrize("type_name", BAD_VALUE_TYPES)
@settings(max_examples=150, deadline=None, suppress_health_check=[
    HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
def test_bad_values_fail_like_the_validator(type_name: str, data: st.DataObject) -> None:
    value = _poke(data.draw(values_for(STORE, type_name)), data)
    try:
        expected: bytes | str = bytes(VALUES.build(type_name, value).serialize())
    except ValueFitError as exc:
        expected = str(exc)
    except (UnicodeEncodeError, OverflowError, TypeError, ValueError):
        return  # the validator let it through and cyclonedds refused it: not comparable
    try:
        ours: bytes | str = CODECS.of(type_name).encode_plain(value)
    except ValueFitError as exc:
        ours = str(exc)
    assert ours == expected


# -- bad bytes: CdrDecodeError, never anything else ------------------------------------
@pytest.mark.parametrize("type_name", [*LISTED_TYPES, "test_msgs/msg/Strings",
                                       "test_msgs/msg/WStrings", "test_msgs/msg/Arrays"])
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_every_truncation_is_a_decode_error(type_name: str, data: st.DataObject) -> None:
    wire = CODECS.of(type_name).encode_plain(data.draw(values_for(STORE, type_name)))
    codec = CODECS.of(type_name)
    body_end = len(wire)
    for cut in range(body_end):
        # a cut inside the final padding (none in these bodies) would still decode
        for decode in (codec.decode, codec.decode_plain):
            with pytest.raises(CdrDecodeError):
                decode(wire[:cut])


@pytest.mark.parametrize("type_name", LISTED_TYPES)
@settings(max_examples=100, deadline=None)
@given(body=st.binary(max_size=200))
def test_random_bytes_decode_or_fail_cleanly(type_name: str, body: bytes) -> None:
    codec = CODECS.of(type_name)
    for data in (HEADER + body, body):
        try:
            codec.decode_plain(data)
            codec.decode(data)
        except CdrDecodeError:
            pass


@pytest.mark.parametrize("data", [b"\x01\x02\x03", bytearray(b"\x01\x02\x03"), [1, 2, 3],
                                  memoryview(b"\x01\x02\x03"),
                                  memoryview(b"\x01\x02\x03\x00").cast("B")[:3]])
def test_a_typed_byte_field_may_be_any_buffer_or_ints(data: Any) -> None:
    codec = CODECS.of("std_msgs/msg/ByteMultiArray")
    message = VALUES.build("std_msgs/msg/ByteMultiArray", {"data": b"\x01\x02\x03"})
    expected = codec.encode(message)
    message.data = data
    assert codec.encode(message) == expected


def test_a_typed_byte_field_counts_bytes_not_items() -> None:
    from array import array
    codec = CODECS.of("std_msgs/msg/UInt8MultiArray")
    message = VALUES.build("std_msgs/msg/UInt8MultiArray", {"data": b"\x00" * 8})
    expected = codec.encode(message)
    message.data = memoryview(array("d", [0.0]))  # one item of 8 bytes
    assert codec.encode(message) == expected
