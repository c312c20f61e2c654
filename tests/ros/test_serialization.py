"""`rcan_rtps.ros.serialize` / `deserialize`: rclpy's bytes, both ways, and clear errors."""

from __future__ import annotations

from typing import Any

import pytest

from rcan_rtps.ros import (
    CdrDecodeError,
    Codec,
    TypeStore,
    UnknownTypeError,
    ValueFitError,
    deserialize,
    serialize,
)

from .offline_data import TEST_IDL, load

pytestmark = pytest.mark.offline

VECTORS: list[dict[str, Any]] = load("cdr_vectors.json")["vectors"]
IDS = [v["name"] for v in VECTORS]
TWIST = "geometry_msgs/msg/Twist"


@pytest.fixture(scope="module")
def codec() -> Codec:
    return Codec(TypeStore([TEST_IDL], distro="jazzy"))  # the bundle plus test_msgs


@pytest.mark.parametrize("vector", VECTORS, ids=IDS)
def test_rclpy_bytes_both_ways(codec: Codec, vector: dict[str, Any]) -> None:
    data = codec.serialize(vector["type"], vector["values"])
    assert data.hex() == vector["hex"]
    assert codec.deserialize(vector["type"], data, plain=True) == vector["values"]
    typed = codec.deserialize(vector["type"], bytes.fromhex(vector.get("rclpy_hex",
                                                                       vector["hex"])))
    assert codec.serialize(vector["type"], typed).hex() == vector["hex"]


def test_module_functions_use_the_bundle() -> None:
    data = serialize(TWIST, {"linear": {"x": 0.5}, "angular": {"z": -1.0}})
    assert data[:4] == b"\x00\x01\x00\x00" and len(data) == 4 + 48
    twist = deserialize(TWIST, memoryview(data))
    assert (twist.linear.x, twist.angular.z) == (0.5, -1.0)
    assert deserialize(TWIST, data, plain=True)["angular"] == {"x": 0.0, "y": 0.0, "z": -1.0}


@pytest.mark.parametrize("data, words", [
    (b"", "encapsulation missing"),
    (b"\x00\x07\x00\x00" + bytes(48), "not plain CDR (encapsulation 00 07 00 00)"),
    (b"\x00\x01\x00\x00" + bytes(20), "24 bytes do not decode"),
])
def test_bytes_that_are_not_the_type(data: bytes, words: str) -> None:
    with pytest.raises(CdrDecodeError) as caught:
        deserialize(TWIST, data)
    assert words in str(caught.value) and TWIST in str(caught.value)


def test_values_that_do_not_fit_name_the_field() -> None:
    with pytest.raises(ValueFitError, match=r"linear\.x"):
        serialize(TWIST, {"linear": {"x": "fast"}})
    with pytest.raises(UnknownTypeError, match="geometry_msgs/msg/Twst"):
        serialize("geometry_msgs/msg/Twst", {})
    other = deserialize("std_msgs/msg/Bool", serialize("std_msgs/msg/Bool", {"data": True}))
    with pytest.raises(TypeError, match="not a geometry_msgs/msg/Twist"):
        serialize(TWIST, other)
