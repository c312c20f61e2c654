"""The plain encoder's check that a list holds only floats, done in C through msgspec's
MessagePack encoder (`cdr._all_floats`, and the same test written out for fixed-size arrays):
it must say "all floats" exactly when every item's type is float, for every length around
MessagePack's array header sizes, and a bool, an int or a float subclass anywhere must never
be taken for a float. Refused lists reach the validator, whose error names the item."""

from __future__ import annotations

from decimal import Decimal
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from rcan_rtps.ros.errors import ValueFitError
from rcan_rtps.ros.serialization import Codec
from rcan_rtps.ros.typesys.cdr import _all_floats

pytestmark = pytest.mark.offline

CODEC = Codec()


class Real(float):
    """A float subclass: the validator takes it (isinstance), the fast check must not."""


ODD = [True, False, 1, 0, 2**63, 2**70, -1, "x", "1.00000", None, Decimal("1.5"),
       Real(1.5), [1.0], {}, b"\x00" * 8, "abcdefgh"]  # "abcdefgh": 9 bytes as MessagePack


def exactly_floats(values: list[Any]) -> bool:
    return all(type(v) is float for v in values)


@pytest.mark.parametrize("length", [0, 1, 15, 16, 17, 65535, 65536])
def test_lengths_at_every_header_size(length: int) -> None:
    values = [0.5] * length
    assert _all_floats(values)
    for at in {0, length // 2, length - 1} if length else set():
        for odd in ODD:
            assert not _all_floats([*values[:at], odd, *values[at + 1:]]), (at, odd)


@given(st.lists(st.one_of(st.floats(), st.sampled_from(ODD), st.integers()), max_size=40))
def test_all_floats_is_every_item_a_float(values: list[Any]) -> None:
    assert _all_floats(values) == exactly_floats(values)


@pytest.mark.parametrize("odd", [True, False, "1.0", None, Decimal("1.5"), [0.0]])
@pytest.mark.parametrize(("type_name", "field", "size"), [
    ("sensor_msgs/msg/LaserScan", "ranges", 720),          # a sequence
    ("sensor_msgs/msg/Imu", "orientation_covariance", 9),   # a fixed array, fixarray header
    ("geometry_msgs/msg/PoseWithCovariance", "covariance", 36)])  # array 16 header
def test_a_non_number_in_a_float_list_is_refused_naming_the_item(
        type_name: str, field: str, size: int, odd: Any) -> None:
    values = [0.25] * size
    values[size // 3] = odd
    with pytest.raises(ValueFitError) as caught:
        CODEC.of(type_name).encode_plain({field: values})
    assert f"{field}[{size // 3}]" in str(caught.value)


@pytest.mark.parametrize(("type_name", "field", "size"), [
    ("sensor_msgs/msg/LaserScan", "ranges", 720),
    ("geometry_msgs/msg/PoseWithCovariance", "covariance", 36)])
def test_ints_and_float_subclasses_are_numbers_like_the_validator_says(
        type_name: str, field: str, size: int) -> None:
    codec = CODEC.of(type_name)
    floats = [float(i % 7) for i in range(size)]
    expected = codec.encode_plain({field: floats})
    for mixed in ([int(v) for v in floats], [Real(v) for v in floats]):
        assert codec.encode_plain({field: mixed}) == expected
