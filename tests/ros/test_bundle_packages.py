"""Every package the bundle ships resolves from the wire and encodes, with no ROS around.

The hash tests prove each type's definition; these prove the rest of the path a tool takes:
a DDS type name seen on the graph (`tf2_msgs::msg::dds_::TFMessage_` on `/tf_static`)
finds its bundle type, the codec builds a DDS type for every type the bundle defines
(derived service, action and event types included), and a sample of one type per package
goes through our CDR encoder, equals the reference encoder's bytes and decodes back.
"""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rcan_rtps.ros.graph import ros_type_of
from rcan_rtps.ros.names import EndpointKind, demangle
from rcan_rtps.ros.typesys.ddstypes import DdsTypes
from rcan_rtps.ros.typesys.store import TypeStore
from rcan_rtps.ros.typesys.values import MessageValues, str_to_wide, wide_to_str

from .cdr_reference import encode
from .offline_data import TEST_IDL, load
from .strategies import values_for

pytestmark = pytest.mark.offline

STORE = TypeStore([TEST_IDL], distro="jazzy")  # + the test_msgs types the vectors name
CODEC = MessageValues(DdsTypes(STORE))
# every type name with an official hash (tests/data/README.md): the whole bundle
ALL_TYPES = sorted({**load("rihs01_jazzy.json")["hashes"],
                    **load("rihs01_official_jazzy.json")["hashes"]})
ONE_PER_PACKAGE = [
    "visualization_msgs/msg/Marker",
    "shape_msgs/msg/SolidPrimitive",
    "stereo_msgs/msg/DisparityImage",
    "actionlib_msgs/msg/GoalStatusArray",
    "tf2_msgs/msg/TFMessage",
    "control_msgs/action/FollowJointTrajectory_Goal",
    "nav2_msgs/msg/Costmap",
    "example_interfaces/srv/AddTwoInts_Request",
    "example_interfaces/msg/WString",
    "vision_msgs/msg/Detection3DArray",
    "ackermann_msgs/msg/AckermannDriveStamped",
    "geographic_msgs/msg/GeoPoseStamped",
    "statistics_msgs/msg/MetricsMessage",
]


def test_tf_static_resolves_to_tf2_msgs_tfmessage() -> None:
    seen = demangle("rt/tf_static")
    assert seen is not None and seen.kind is EndpointKind.TOPIC
    ros_type = ros_type_of("tf2_msgs::msg::dds_::TFMessage_", seen.kind)
    assert ros_type == "tf2_msgs/msg/TFMessage"
    fields = [(f.name, f.type.nested) for f in STORE.message(ros_type).fields]
    assert fields == [("transforms", "geometry_msgs/msg/TransformStamped")]


def test_a_tf_message_round_trips() -> None:
    stamp = {"sec": 7, "nanosec": 250}
    transform = {
        "header": {"stamp": stamp, "frame_id": "base_link"},
        "child_frame_id": "laser",
        "transform": {"translation": {"x": 0.5, "y": 0.0, "z": 0.25},
                      "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
    }
    wire = CODEC.build("tf2_msgs/msg/TFMessage", {"transforms": [transform]}).serialize()
    decoded = CODEC.types.struct("tf2_msgs/msg/TFMessage").deserialize(wire)
    assert CODEC.to_plain("tf2_msgs/msg/TFMessage", decoded) == {"transforms": [transform]}


def test_every_bundle_type_resolves_from_its_dds_name_and_builds() -> None:
    assert len(ALL_TYPES) > 800
    for name in ALL_TYPES:
        pkg, kind, short = name.split("/")
        assert ros_type_of(f"{pkg}::{kind}::dds_::{short}_", EndpointKind.TOPIC) == name
        if kind == "msg" or short.endswith(("_Request", "_Response", "_Event", "_Goal",
                                             "_Result", "_Feedback", "_FeedbackMessage")):
            assert CODEC.types.struct(name) is not None, name


@pytest.mark.parametrize("type_name", ONE_PER_PACKAGE)
@settings(max_examples=10, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
def test_one_type_per_package_round_trips(type_name: str, data: st.DataObject) -> None:
    value = data.draw(values_for(STORE, type_name, max_items=2))
    wire = CODEC.build(type_name, value).serialize()
    reference, _ = encode(STORE, type_name, value)
    assert wire == bytes([0, 1, 0, 0]) + reference
    decoded = CODEC.types.struct(type_name).deserialize(wire)
    assert CODEC.to_plain(type_name, decoded) == value


def test_wstring_bytes_are_what_rmw_fastrtps_writes() -> None:
    """The bytes rclpy (Jazzy, Fast DDS) gives a wstring "a😀" (seen as the first field of
    test_msgs/msg/WStrings): a count of UTF-16 code units, then each unit as a 4-byte
    little-endian wchar_t, no terminator."""
    wire = CODEC.build("example_interfaces/msg/WString", {"data": "a😀"}).serialize()
    assert wire.hex(" ") == "00 01 00 00 03 00 00 00 61 00 00 00 3d d8 00 00 00 de 00 00"
    decoded = CODEC.types.struct("example_interfaces/msg/WString").deserialize(wire)
    assert CODEC.to_plain("example_interfaces/msg/WString", decoded) == {"data": "a😀"}


def test_a_peers_impossible_wstring_units_decode_to_replacement_characters() -> None:
    # a lone surrogate, a unit beyond UTF-16: no crash, U+FFFD in their place
    assert wide_to_str([0x61, 0xD83D, 0x62, 0x110000]) == "a\ufffdb\ufffd"
    assert wide_to_str(str_to_wide("ハロー😀")) == "ハロー😀"
