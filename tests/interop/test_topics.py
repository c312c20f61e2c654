"""Topics both ways between our node and a real rclpy Jazzy node, and graph presence (on Fast
DDS and on Cyclone DDS)."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path

import pytest
from oracle.client import OracleEnv, RclpyOracle, both_rmws
from waiting import eventually, take

from rcan_rtps.ros import qos
from rcan_rtps.ros.participant import RosNode

TWIST = {"linear": {"x": 0.5, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": -0.25}}


@pytest.fixture
def oracle(jazzy_oracle: OracleEnv, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_oracle, "oracle_node", "/lab", domain_id=domain_id) as agent:
        yield agent


@pytest.fixture
def node(domain_id: int) -> Iterator[RosNode]:
    with RosNode("rcan_bridge", "/robot1", domain_id=domain_id, distro="jazzy") as n:
        yield n


@both_rmws
async def test_we_publish_twist_rclpy_receives(oracle: RclpyOracle, node: RosNode) -> None:
    await oracle.acall("subscribe", topic="/robot1/cmd_vel", type="geometry_msgs/msg/Twist")
    pub = node.create_publisher("cmd_vel", "geometry_msgs/msg/Twist")
    await pub.wait_for_subscribers(1, timeout=15)
    pub.publish(TWIST)
    got = await take(oracle, "/robot1/cmd_vel")
    assert got == [TWIST]


@both_rmws
async def test_rclpy_publishes_we_receive(oracle: RclpyOracle, node: RosNode) -> None:
    sub = node.create_subscription("/lab/chatter", "std_msgs/msg/String")
    await oracle.acall("publisher", topic="/lab/chatter", type="std_msgs/msg/String")
    await sub.wait_for_publishers(1, timeout=15)
    assert await oracle.acall("wait_subscribers", topic="/lab/chatter") >= 1
    await oracle.acall("publish", topic="/lab/chatter", type="std_msgs/msg/String",
                       value={"data": "héllo"})
    msg = await sub.get(timeout=10)
    assert msg.data == "héllo"


@both_rmws
async def test_sensor_data_qos_both_ways(oracle: RclpyOracle, node: RosNode) -> None:
    scan = {"angle_min": -1.0, "angle_max": 1.0, "ranges": [1.0, 2.0, 3.5],
            "header": {"frame_id": "laser", "stamp": {"sec": 3, "nanosec": 4}}}
    await oracle.acall("subscribe", topic="/scan_out", type="sensor_msgs/msg/LaserScan",
                       qos="sensor")
    await oracle.acall("publisher", topic="/scan_in", type="sensor_msgs/msg/LaserScan",
                       qos="sensor")
    pub = node.create_publisher("/scan_out", "sensor_msgs/msg/LaserScan", qos.SENSOR_DATA)
    sub = node.create_subscription("/scan_in", "sensor_msgs/msg/LaserScan", qos.SENSOR_DATA)
    await pub.wait_for_subscribers(1, timeout=15)
    await sub.wait_for_publishers(1, timeout=15)
    await oracle.acall("publish", topic="/scan_in", type="sensor_msgs/msg/LaserScan", value=scan,
                       count=5)
    got = await sub.get(timeout=10)
    assert list(got.ranges) == [1.0, 2.0, 3.5] and got.header.frame_id == "laser"
    for _ in range(5):  # best effort: a sample may be lost, so send a few
        pub.publish(scan)
        await asyncio.sleep(0.05)
    received = await take(oracle, "/scan_out")
    assert received and received[0]["ranges"] == [1.0, 2.0, 3.5]


@both_rmws
async def test_image_640x480_both_ways(oracle: RclpyOracle, node: RosNode) -> None:
    data = bytes(range(256)) * (640 * 480 * 3 // 256)
    image = {"height": 480, "width": 640, "encoding": "rgb8", "step": 1920, "data": data}
    await oracle.acall("subscribe", topic="/camera/image_raw", type="sensor_msgs/msg/Image")
    pub = node.create_publisher("/camera/image_raw", "sensor_msgs/msg/Image")
    await pub.wait_for_subscribers(1, timeout=15)
    pub.publish(image)
    got = await take(oracle, "/camera/image_raw")
    assert got[0]["width"] == 640 and bytes(got[0]["data"]) == data

    # rclpy → us, streamed like a camera: Cyclone's volatile reader may drop the one
    # fragmented sample still in flight when it first syncs with Fast DDS's writer.
    sub = node.create_subscription("/camera/back", "sensor_msgs/msg/Image")
    await oracle.acall("publisher", topic="/camera/back", type="sensor_msgs/msg/Image")
    await sub.wait_for_publishers(1, timeout=15)
    assert await oracle.acall("wait_subscribers", topic="/camera/back") >= 1
    await oracle.acall("publish", topic="/camera/back", type="sensor_msgs/msg/Image",
                       value={**image, "data": list(data)}, count=3, period=0.2, timeout=60)
    back = await sub.get(timeout=20)
    assert back.encoding == "rgb8" and bytes(back.data) == data


@both_rmws
async def test_transient_local_reaches_late_joiner(oracle: RclpyOracle, node: RosNode) -> None:
    pub = node.create_publisher("/map_meta", "std_msgs/msg/String", qos.TF_STATIC)
    pub.publish({"data": "latched"})
    await oracle.acall("subscribe", topic="/map_meta", type="std_msgs/msg/String",
                       qos="transient_local")
    got = await take(oracle, "/map_meta")
    assert got == [{"data": "latched"}]

    await oracle.acall("publisher", topic="/latched_back", type="std_msgs/msg/String",
                       qos="transient_local")
    await oracle.acall("publish", topic="/latched_back", type="std_msgs/msg/String",
                       value={"data": "from rclpy"})
    await asyncio.sleep(0.5)  # it was published before we exist; that is the point
    sub = node.create_subscription("/latched_back", "std_msgs/msg/String", qos.TF_STATIC)
    assert (await sub.get(timeout=15)).data == "from rclpy"


@both_rmws
async def test_rclpy_lists_our_node_and_type_hash(oracle: RclpyOracle, node: RosNode) -> None:
    pub = node.create_publisher("cmd_vel", "geometry_msgs/msg/Twist")
    await oracle.acall("subscribe", topic="/robot1/cmd_vel", type="geometry_msgs/msg/Twist")
    await pub.wait_for_subscribers(1, timeout=15)
    async def listed() -> bool:
        return ["rcan_bridge", "/robot1"] in await oracle.acall("node_names")

    await eventually(listed)
    infos = await oracle.acall("publishers_info", topic="/robot1/cmd_vel")
    ours = [i for i in infos if i["node_name"] == "rcan_bridge"]
    assert ours, infos
    assert ours[0]["node_namespace"] == "/robot1"
    assert ours[0]["topic_type"] == "geometry_msgs/msg/Twist"
    assert node.store.hash_of("geometry_msgs/msg/Twist") in ours[0]["type_hash"]


@both_rmws
async def test_incompatible_qos_is_reported(oracle: RclpyOracle, node: RosNode) -> None:
    """A reliable reader never matches a best-effort writer; we say so instead of hanging."""
    await oracle.acall("publisher", topic="/lossy", type="std_msgs/msg/String", qos="sensor")
    sub = node.create_subscription("/lossy", "std_msgs/msg/String", qos.DEFAULT)
    await eventually(lambda: sub.incompatible_qos_events >= 1)
    assert sub.matched_count() == 0
    assert qos.incompatibilities(qos.SENSOR_DATA, qos.DEFAULT) == [
        "reader requests RELIABLE but the writer offers BEST_EFFORT"]
    assert qos.incompatibilities(qos.DEFAULT, qos.SENSOR_DATA) == []
    assert qos.incompatibilities(qos.DEFAULT, qos.TF_STATIC) == [
        "reader requests TRANSIENT_LOCAL but the writer offers VOLATILE"]


# -- full fidelity (issue 12) -------------------------------------------------------------
LATCHED_5 = qos.DEFAULT.with_(depth=5, durability=qos.Durability.TRANSIENT_LOCAL)


@both_rmws
async def test_late_rclpy_subscriber_gets_our_whole_transient_local_history(
        oracle: RclpyOracle, node: RosNode) -> None:
    pub = node.create_publisher("/robot1/history", "std_msgs/msg/Int32", LATCHED_5)
    for i in range(5):
        pub.publish({"data": i})
    await oracle.acall("subscribe", topic="/robot1/history", type="std_msgs/msg/Int32",
                       qos="transient_local:5")
    got = await take(oracle, "/robot1/history", until=lambda got: len(got) >= 5)
    assert [m["data"] for m in got] == [0, 1, 2, 3, 4]


@both_rmws
async def test_we_join_late_and_get_rclpy_transient_local_history(
        oracle: RclpyOracle, node: RosNode) -> None:
    await oracle.acall("publisher", topic="/lab/history", type="std_msgs/msg/Int32",
                       qos="transient_local:5")
    for i in range(5):
        await oracle.acall("publish", topic="/lab/history", type="std_msgs/msg/Int32",
                           value={"data": i}, period=0.0)
    sub = node.create_subscription("/lab/history", "std_msgs/msg/Int32", LATCHED_5)
    got = [(await sub.get(timeout=15)).data for _ in range(5)]  # type: ignore[attr-defined]
    assert got == [0, 1, 2, 3, 4]


@both_rmws
async def test_our_best_effort_publisher_reports_a_reliable_rclpy_subscriber(
        oracle: RclpyOracle, node: RosNode, caplog: pytest.LogCaptureFixture) -> None:
    await oracle.acall("subscribe", topic="/robot1/strict", type="std_msgs/msg/String")
    pub = node.create_publisher("strict", "std_msgs/msg/String", qos.SENSOR_DATA)
    await eventually(lambda: pub.incompatible_qos_events >= 1, timeout=20)
    assert pub.matched_count() == 0
    # The warning is logged from the listener's thread just after the count goes up.
    await eventually(lambda: any(
        "publisher /robot1/strict" in r.getMessage()
        and "RELIABILITY_QOS_POLICY" in r.getMessage() for r in caplog.records),
        timeout=5, what="the incompatible-QoS warning")


@both_rmws
async def test_bounded_string_counts_characters_like_rclpy(
        oracle: RclpyOracle, domain_id: int, jazzy_share: Path) -> None:
    # string<=22 holding 22 two-byte characters (44 bytes): rclpy bounds characters, and
    # rclpy → rclpy carries it; so must we, both ways.
    value = {"bounded_string_value": "é" * 22}
    with RosNode("strings", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as strings:
        await oracle.acall("subscribe", topic="/to_rclpy", type="test_msgs/msg/Strings")
        await oracle.acall("publisher", topic="/to_us", type="test_msgs/msg/Strings")
        pub = strings.create_publisher("/to_rclpy", "test_msgs/msg/Strings")
        sub = strings.create_subscription("/to_us", "test_msgs/msg/Strings")
        await pub.wait_for_subscribers(1, timeout=15)
        await sub.wait_for_publishers(1, timeout=15)
        assert await oracle.acall("wait_matched", topic="/to_rclpy") >= 1
        # (our reader saw their writer; their writer must have matched our reader too, or its
        # one volatile sample goes to nobody: CI lost it once on a busy machine)
        assert await oracle.acall("wait_subscribers_matched", topic="/to_us") >= 1
        pub.publish(value)
        await oracle.acall("publish", topic="/to_us", type="test_msgs/msg/Strings", value=value)
        (theirs,) = await take(oracle, "/to_rclpy")
        ours = await sub.get(timeout=10)
    assert theirs["bounded_string_value"] == value["bounded_string_value"]
    assert ours.bounded_string_value == value["bounded_string_value"]  # type: ignore[attr-defined]
