"""Property: for generated values, encode → decode is the identity, and our bytes equal the
test-only reference encoder's (tests/ros/cdr_reference.py), with no ROS around."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rcan_rtps.ros.errors import ValueFitError
from rcan_rtps.ros.typesys.ddstypes import DdsTypes
from rcan_rtps.ros.typesys.store import TypeStore
from rcan_rtps.ros.typesys.values import MessageValues

from .cdr_reference import encode
from .offline_data import TEST_IDL
from .strategies import LISTED_TYPES, values_for

pytestmark = pytest.mark.offline

TYPES = [
    *LISTED_TYPES,
    "test_msgs/msg/BasicTypes",
    "test_msgs/msg/Strings",
    "test_msgs/msg/WStrings",
    "rmw_dds_common/msg/ParticipantEntitiesInfo",
    "rcl_interfaces/msg/ParameterDescriptor",
    "rcl_interfaces/srv/SetParameters_Request",
    "test_msgs/action/Fibonacci_SendGoal_Request",
    "action_msgs/msg/GoalStatusArray",
]
STORE = TypeStore([TEST_IDL], distro="jazzy")
CODEC = MessageValues(DdsTypes(STORE))


@pytest.mark.parametrize("type_name", TYPES)
@settings(
    max_examples=20,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(data=st.data())
def test_encode_decode_identity(type_name: str, data: st.DataObject) -> None:
    value = data.draw(values_for(STORE, type_name))
    wire = CODEC.build(type_name, value).serialize()
    reference, _ = encode(STORE, type_name, value)
    assert wire == bytes([0, 1, 0, 0]) + reference
    decoded = CODEC.types.struct(type_name).deserialize(wire)
    assert CODEC.to_plain(type_name, decoded) == value


def test_bounded_string_counts_characters_like_rclpy() -> None:
    # string<=22: rclpy's setter checks len(value), so 22 'é' (44 UTF-8 bytes) fit, 23 do not.
    text = "é" * 22
    wire = CODEC.build("test_msgs/msg/Strings", {"bounded_string_value": text}).serialize()
    decoded = CODEC.types.struct("test_msgs/msg/Strings").deserialize(wire)
    assert CODEC.to_plain("test_msgs/msg/Strings", decoded)["bounded_string_value"] == text
    with pytest.raises(ValueFitError, match="bound of 22 characters"):
        CODEC.build("test_msgs/msg/Strings", {"bounded_string_value": "é" * 23})
