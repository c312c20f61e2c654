"""Our CDR bytes (the generated codecs) equal rclpy's `serialize_message` for random values,
and decode back; and we decode rclpy's bytes, for every bundled type the oracle also ships.

Fast CDR leaves alignment padding uninitialised, so rclpy's padding bytes are garbage, and
rmw_fastrtps sizes its buffer from a conservative estimate (it aligns after empty
sequences), so its buffer may run past the message end. A reference encoder marks where
padding is. We require: our bytes equal the reference encoder's exactly (padding zero);
rclpy's buffer starts with the same bytes everywhere but in padding; and rclpy decodes ours.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from oracle.client import RclpyOracle

from rcan_rtps.ros.typesys.cdr import CdrCodecs
from rcan_rtps.ros.typesys.ddstypes import DdsTypes
from rcan_rtps.ros.typesys.store import TypeStore
from rcan_rtps.ros.typesys.values import MessageValues

from .cdr_reference import encode, equal_ignoring_padding
from .offline_data import load
from .strategies import LISTED_TYPES, values_for

pytestmark = pytest.mark.interop

TYPES = [*LISTED_TYPES, "test_msgs/msg/Arrays", "test_msgs/msg/BoundedSequences",
         "visualization_msgs/msg/Marker", "stereo_msgs/msg/DisparityImage",
         "test_msgs/msg/WStrings"]
# The packages of the bundle that the oracle environment installs too (scripts/test.sh). The
# others have no ros-jazzy-* wheel on the package index: test_generated_codec.py holds them to
# cyclonedds and the reference encoder instead.
NOT_ON_THE_INDEX = ["ackermann_msgs", "control_msgs", "example_interfaces", "geographic_msgs",
                    "nav2_msgs", "statistics_msgs", "tf2_msgs", "vision_msgs"]
ORACLE_PACKAGES = ["action_msgs", "actionlib_msgs", "builtin_interfaces", "diagnostic_msgs",
                   "geometry_msgs", "lifecycle_msgs", "nav_msgs", "rcl_interfaces",
                   "rmw_dds_common", "rosgraph_msgs",
                   "sensor_msgs", "service_msgs", "shape_msgs", "std_msgs", "std_srvs",
                   "stereo_msgs", "test_msgs", "trajectory_msgs", "type_description_interfaces",
                   "unique_identifier_msgs", "visualization_msgs"]
# Structs only: rclpy cannot instantiate the service and action types themselves.
STRUCT_SUFFIXES = ("_Request", "_Response", "_Event", "_Goal", "_Result", "_Feedback",
                   "_FeedbackMessage")
BUNDLED = sorted(t for t in {**load("rihs01_jazzy.json")["hashes"],
                             **load("rihs01_official_jazzy.json")["hashes"]}
                 if "/msg/" in t or t.endswith(STRUCT_SUFFIXES))


@pytest.fixture(scope="module")
def store(jazzy_share: Path) -> TypeStore:
    # the bundle first; the oracle's own test_msgs only for the extra coverage types
    return TypeStore([jazzy_share / "test_msgs"], distro="jazzy")


@pytest.fixture(scope="module")
def values(store: TypeStore) -> MessageValues:
    return MessageValues(DdsTypes(store))


def examples(n: int) -> settings:
    return settings(max_examples=n, deadline=None, suppress_health_check=[
        HealthCheck.too_slow, HealthCheck.function_scoped_fixture, HealthCheck.data_too_large])


def test_every_bundled_package_is_compared_with_rclpy_or_said_not_to_be() -> None:
    packages = {t.split("/")[0] for t in BUNDLED}
    assert packages == set(ORACLE_PACKAGES) | set(NOT_ON_THE_INDEX)


@pytest.fixture(scope="module")
def codecs(values: MessageValues) -> CdrCodecs:
    return CdrCodecs(values.types, values)


@pytest.fixture(scope="module")
def oracle(jazzy_python: Path) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_python, "codec_oracle") as agent:
        yield agent


@pytest.mark.parametrize("type_name", TYPES)
@examples(25)
@given(data=st.data())
def test_bytes_equal_rclpy(oracle: RclpyOracle, store: TypeStore, codecs: CdrCodecs,
                           type_name: str, data: st.DataObject) -> None:
    value = data.draw(values_for(store, type_name))
    ours = codecs.of(type_name).encode_plain(value)[4:]
    theirs = bytes.fromhex(oracle.call("serialize", type=type_name, value=value))[4:]
    reference, padding = encode(store, type_name, value)
    assert ours == reference, f"{type_name}: differs from the reference encoder"
    assert len(theirs) >= len(ours)
    assert equal_ignoring_padding(ours, theirs[: len(ours)], padding), f"{type_name}: differs"
    header = bytes([0, 1, 0, 0])
    assert oracle.call("deserialize", type=type_name, hex=(header + ours).hex()) == \
        oracle.call("roundtrip", type=type_name, value=value)


@pytest.mark.parametrize("type_name", TYPES)
@examples(10)
@given(data=st.data())
def test_we_decode_rclpy_bytes(oracle: RclpyOracle, store: TypeStore, values: MessageValues,
                               codecs: CdrCodecs, type_name: str, data: st.DataObject) -> None:
    value = data.draw(values_for(store, type_name))
    theirs = bytes.fromhex(oracle.call("serialize", type=type_name, value=value))
    expected = oracle.call("roundtrip", type=type_name, value=value)
    codec = codecs.of(type_name)
    assert codec.decode_plain(theirs) == expected
    assert values.to_plain(type_name, codec.decode(theirs)) == expected


@pytest.mark.parametrize("package", ORACLE_PACKAGES)
@examples(30)
@given(data=st.data())
def test_every_shared_type_both_ways(oracle: RclpyOracle, store: TypeStore, codecs: CdrCodecs,
                                     package: str, data: st.DataObject) -> None:
    """Any bundled type of the package: rclpy decodes our bytes to the values, we decode its."""
    type_name = data.draw(st.sampled_from([t for t in BUNDLED if t.startswith(package + "/")]))
    value = data.draw(values_for(store, type_name))
    codec = codecs.of(type_name)
    expected = oracle.call("roundtrip", type=type_name, value=value)
    assert oracle.call("deserialize", type=type_name,
                       hex=codec.encode_plain(value).hex()) == expected
    theirs = bytes.fromhex(oracle.call("serialize", type=type_name, value=value))
    assert codec.decode_plain(theirs) == expected
