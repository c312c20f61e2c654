"""Our CDR bytes equal rclpy's, byte for byte, for fixed values, with no ROS around.

tests/data/cdr_vectors.json holds, per vector, a ROS type, the field values and the bytes
ROS 2 Jazzy's `rclpy.serialization.serialize_message` produced for them (alignment padding
zeroed, see tests/data/make_cdr_vectors.py). We encode the values and must produce exactly
those bytes; we decode the bytes and must get exactly those values.
"""

from __future__ import annotations

from typing import Any

import pytest

from rcan_rtps.ros.typesys.ddstypes import DdsTypes
from rcan_rtps.ros.typesys.store import TypeStore
from rcan_rtps.ros.typesys.values import MessageValues

from .cdr_reference import encode
from .offline_data import TEST_IDL, load

pytestmark = pytest.mark.offline

VECTORS: list[dict[str, Any]] = load("cdr_vectors.json")["vectors"]
IDS = [v["name"] for v in VECTORS]


@pytest.fixture(scope="module")
def store() -> TypeStore:
    return TypeStore([TEST_IDL], distro="jazzy")


@pytest.fixture(scope="module")
def codec(store: TypeStore) -> MessageValues:
    return MessageValues(DdsTypes(store))


def test_vectors_cover_the_listed_shapes() -> None:
    types = {v["type"] for v in VECTORS}
    for needed in (
        "geometry_msgs/msg/Twist",
        "std_msgs/msg/Header",
        "sensor_msgs/msg/JointState",
        "sensor_msgs/msg/Image",
        "nav_msgs/msg/Odometry",
        "test_msgs/msg/BasicTypes",
        "test_msgs/msg/Strings",
        "std_srvs/srv/SetBool_Request",
        "test_msgs/action/Fibonacci_SendGoal_Request",
    ):
        assert needed in types, needed
    assert len({v["name"] for v in VECTORS}) == len(VECTORS) >= 25


@pytest.mark.parametrize("vector", VECTORS, ids=IDS)
def test_encode_gives_rclpy_bytes(codec: MessageValues, vector: dict[str, Any]) -> None:
    ours = codec.build(vector["type"], vector["values"]).serialize()
    assert ours.hex() == vector["hex"]


@pytest.mark.parametrize("vector", VECTORS, ids=IDS)
def test_decode_gives_the_values(codec: MessageValues, vector: dict[str, Any]) -> None:
    cls = codec.types.struct(vector["type"])
    decoded = cls.deserialize(bytes.fromhex(vector["hex"]))
    assert codec.to_plain(vector["type"], decoded) == vector["values"]


@pytest.mark.parametrize(
    "vector",
    [v for v in VECTORS if "rclpy_hex" in v],
    ids=[v["name"] for v in VECTORS if "rclpy_hex" in v],
)
def test_decode_rclpy_bytes_as_sent(codec: MessageValues, vector: dict[str, Any]) -> None:
    """rclpy's own buffer (garbage padding, sometimes a longer tail) decodes the same."""
    cls = codec.types.struct(vector["type"])
    decoded = cls.deserialize(bytes.fromhex(vector["rclpy_hex"]))
    assert codec.to_plain(vector["type"], decoded) == vector["values"]


@pytest.mark.parametrize("vector", VECTORS, ids=IDS)
def test_reference_encoder_agrees(store: TypeStore, vector: dict[str, Any]) -> None:
    """The test-only reference encoder (used to mark padding) writes the same bytes."""
    body, _ = encode(store, vector["type"], vector["values"])
    assert "00010000" + body.hex() == vector["hex"]


def test_a_changed_byte_changes_the_decoded_values(codec: MessageValues) -> None:
    """The byte comparison has teeth: one flipped data byte decodes to other values."""
    vector = next(v for v in VECTORS if v["name"] == "basic_types")
    data = bytearray.fromhex(vector["hex"])
    data[-1] ^= 0x01  # last byte of uint64_value
    cls = codec.types.struct(vector["type"])
    decoded = codec.to_plain(vector["type"], cls.deserialize(bytes(data)))
    assert decoded != vector["values"]
    assert decoded["uint64_value"] == vector["values"]["uint64_value"] ^ (1 << 56)
