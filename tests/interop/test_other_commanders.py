"""Another publisher on a topic the bridge commands the robot on (bridge/commanders.py).

The robot obeys a second node on its cmd_vel or trajectory topic between the bridge's samples,
and an e-stop cannot hold it against one. The bridge cannot stop such a peer: it must show it
(STATUS), say so once in its log when it appears and once when it goes, and audit both.
"""

from __future__ import annotations

import json
import logging
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.topic import Topic
from oracle.client import OracleEnv, RclpyOracle, both_rmws
from waiting import eventually

from rcan_rtps.bridge.commanders import KEY_BURST
from rcan_rtps.bridge.telemetry import ESTOP_NOT_HOLDING, FOREIGN_PUBLISHER
from rcan_rtps.rcan import ForeignPublisher, Status
from rcan_rtps.ros import qos
from rcan_rtps.ros.participant import RosNode

from .bridge_rig import VIEWER, Rig, bridge_config, close_rig, make_rig
from .test_demo import Demo, call, wait_status

TWIST = "geometry_msgs/msg/Twist"
TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"
CMD_VEL = "/robot1/cmd_vel"
ARM = "/robot1/joint_trajectory_controller/joint_trajectory"


@pytest.fixture
async def rig(tmp_path: Path, jazzy_oracle: OracleEnv, domain_id: int) -> AsyncIterator[Rig]:
    r = await make_rig(bridge_config(tmp_path, domain_id), jazzy_oracle, domain_id, watch_s=0.2)
    yield r
    await close_rig(r)


def status(rig: Rig) -> Status:
    return rig.telemetry.status(pending_auth=0)


def listed(rig: Rig) -> list[ForeignPublisher]:
    return status(rig).foreign_publishers


def warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.name == "rcan_rtps.bridge.commanders" and r.levelno == logging.WARNING]


def entries(rig: Rig, event: str) -> list[dict[str, Any]]:
    return [e for e in rig.entries() if e["event"] == event]


@both_rmws
async def test_a_second_publisher_on_cmd_vel_is_shown_logged_and_audited(
        rig: Rig, jazzy_oracle: OracleEnv, domain_id: int,
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="rcan_rtps.bridge.commanders")
    # The robot's own subscription, and the bridge's own writers, are nobody's business.
    await rig.oracle.acall("subscribe", topic=CMD_VEL, type=TWIST)
    assert await rig.oracle.acall("wait_matched", topic=CMD_VEL) >= 1
    assert listed(rig) == []
    with RclpyOracle(jazzy_oracle, "teleop", "/", domain_id=domain_id) as teleop:
        teleop.call("publisher", topic=CMD_VEL, type=TWIST)
        await eventually(lambda: [p.node for p in listed(rig)] == ["/teleop"],
                         what="the teleop node listed by name")
        (shown,) = listed(rig)
        assert (shown.topic, shown.type, shown.writers) == (CMD_VEL, TWIST, 1)
        assert len(shown.participant.split(".")) == 12
        faults = {f.name: f for f in status(rig).faults}
        assert faults[f"{FOREIGN_PUBLISHER}:{CMD_VEL}"].level == "WARN"
        assert "/teleop" in faults[f"{FOREIGN_PUBLISHER}:{CMD_VEL}"].message
        assert status(rig).state != "fault"  # shown, not a fault of the robot's

        # Latched, the e-stop cannot hold the robot against it: the first fault says so.
        assert (await rig.command(VIEWER, {"action": "estop"})).http_status == 200
        first = status(rig).faults[0]
        assert (first.name, first.level) == (ESTOP_NOT_HOLDING, "ERROR")
        assert CMD_VEL in first.message and "/teleop" in first.message
        assert status(rig).state == "estop"

        await eventually(lambda: entries(rig, "FOREIGN_PUBLISHER"))
        (seen,) = entries(rig, "FOREIGN_PUBLISHER")
        assert seen["ros2_topic"] == CMD_VEL
        assert seen["params"]["node"] == "/teleop" and seen["params"]["type"] == TWIST
        teleop.call("unpublish", topic=CMD_VEL)
        await eventually(lambda: listed(rig) == [], what="the teleop node gone from STATUS")
        assert not any(f.name == ESTOP_NOT_HOLDING for f in status(rig).faults)
        await eventually(lambda: entries(rig, "FOREIGN_PUBLISHER_GONE"))
        (left,) = entries(rig, "FOREIGN_PUBLISHER_GONE")
        assert left["params"]["participant"] == seen["params"]["participant"]
    said = warnings(caplog)
    assert len(said) == 2, said
    assert "/teleop" in said[0] and "cannot hold" in said[0] and "no longer" in said[1]
    assert len(entries(rig, "FOREIGN_PUBLISHER")) == 1  # once, though polled many times


ODOM = "nav_msgs/msg/Odometry"
EXPECTED = """\
foreign_publishers:
  poll_s: 0.2
  expected: {cmd_vel: [/robot1/controller_server]}
"""


def odometry(linear_x: float) -> dict[str, Any]:
    return {"header": {"frame_id": "odom"}, "twist": {"twist": {"linear": {"x": linear_x}}}}


def faults_of(rig: Rig) -> dict[str, tuple[str, str]]:
    return {f.name: (f.level, f.message) for f in status(rig).faults}


@both_rmws
async def test_an_expected_publisher_is_listed_and_audited_and_the_estop_fault_stays(
        tmp_path: Path, jazzy_oracle: OracleEnv, domain_id: int,
        caplog: pytest.LogCaptureFixture) -> None:
    """nav2's controller_server on cmd_vel, declared in the config: listed (expected), audited,
    no WARN fault. Latched, the e-stop still cannot hold the robot against it: a WARN while
    the robot's odometry says it is still, an ERROR while it does not (or says nothing)."""
    caplog.set_level(logging.INFO, logger="rcan_rtps.bridge.commanders")
    config = bridge_config(tmp_path, domain_id, extra_ros2=EXPECTED)
    rig = await make_rig(config, jazzy_oracle, domain_id, watch=True)
    try:
        assert rig.commanders is not None and rig.commanders.interval == 0.2  # the config's
        await rig.oracle.acall("subscribe", topic=CMD_VEL, type=TWIST)  # the robot
        assert await rig.oracle.acall("wait_matched", topic=CMD_VEL) >= 1
        with RclpyOracle(jazzy_oracle, "controller_server", "/robot1",
                         domain_id=domain_id) as nav2:
            nav2.call("publisher", topic=CMD_VEL, type=TWIST)
            await eventually(lambda: [(p.node, p.expected) for p in listed(rig)] == [
                ("/robot1/controller_server", True)], what="the controller listed, expected")
            assert faults_of(rig) == {} and status(rig).state != "fault"
            await eventually(lambda: entries(rig, "FOREIGN_PUBLISHER"))
            (seen,) = entries(rig, "FOREIGN_PUBLISHER")
            assert seen["params"]["node"] == "/robot1/controller_server"
            assert seen["params"]["expected"] is True
            assert warnings(caplog) == []  # the robot's design, told at INFO
            assert any("/robot1/controller_server (expected)" in r.getMessage()
                       for r in caplog.records if r.levelno == logging.INFO)

            assert (await rig.command(VIEWER, {"action": "estop"})).http_status == 200
            # No odometry yet: the robot is not seen still.
            level, message = faults_of(rig)[ESTOP_NOT_HOLDING]
            assert level == "ERROR" and "not seen still" in message
            assert status(rig).faults[0].name == ESTOP_NOT_HOLDING
            await rig.oracle.acall("publisher", topic="/robot1/odom", type=ODOM)
            await rig.oracle.acall("publish_periodic", topic="/robot1/odom", type=ODOM,
                                   value=odometry(0.0), rate=20.0)
            await eventually(lambda: faults_of(rig)[ESTOP_NOT_HOLDING][0] == "WARN",
                             what="a WARN once the robot is seen still")
            level, message = faults_of(rig)[ESTOP_NOT_HOLDING]
            assert "cannot hold" in message and "/robot1/controller_server (expected)" in message
            assert status(rig).state == "estop"
            await rig.oracle.acall("stop_periodic", topic="/robot1/odom")
            await rig.oracle.acall("publish_periodic", topic="/robot1/odom", type=ODOM,
                                   value=odometry(0.4), rate=20.0)
            await eventually(lambda: faults_of(rig)[ESTOP_NOT_HOLDING][0] == "ERROR",
                             what="an ERROR again while the robot moves")

            # A publisher whose node cannot be learned never matches the list.
            participant = DomainParticipant(domain_id)
            topic = Topic(participant, "rt/robot1/cmd_vel", rig.node.types.struct(TWIST))
            writer = DataWriter(participant, topic)
            try:
                await eventually(lambda: len(listed(rig)) == 2)
                unnamed = next(p for p in listed(rig) if p.node is None)
                assert not unnamed.expected
                assert faults_of(rig)[f"{FOREIGN_PUBLISHER}:{CMD_VEL}"][0] == "WARN"
            finally:
                del writer, topic, participant
            await rig.oracle.acall("stop_periodic", topic="/robot1/odom")
            nav2.call("unpublish", topic=CMD_VEL)
            await eventually(lambda: listed(rig) == [])
            assert ESTOP_NOT_HOLDING not in faults_of(rig)
            await eventually(lambda: [e["params"]["expected"] for e in entries(
                rig, "FOREIGN_PUBLISHER_GONE") if e["params"]["node"]] == [True])
    finally:
        await close_rig(rig)


@pytest.fixture
def hostile(domain_id: int, jazzy_share: Path) -> Iterator[RosNode]:
    with RosNode("hostile", "/robot1", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as node:
        yield node


async def test_the_arm_topic_is_watched_too(rig: Rig, hostile: RosNode) -> None:
    """Every topic the registry's actions publish to, not only the velocity."""
    arm = hostile.create_publisher(ARM, TRAJECTORY, qos.DEFAULT)
    await eventually(lambda: [(p.topic, p.node) for p in listed(rig)] == [
        (ARM, "/robot1/hostile")])
    await rig.command(VIEWER, {"action": "estop"})  # no robot here to tell: latched still
    assert rig.governor.latch.latched
    assert status(rig).faults[0].name == ESTOP_NOT_HOLDING
    assert ARM in status(rig).faults[0].message
    arm.close()
    await eventually(lambda: listed(rig) == [])


async def test_a_publisher_that_names_no_node_is_shown_by_its_participant(
        rig: Rig, domain_id: int, caplog: pytest.LogCaptureFixture) -> None:
    """A plain DDS participant (no ros_discovery_info) writing the mangled topic: named by
    its GUID prefix; its two writers count as one publisher."""
    caplog.set_level(logging.WARNING, logger="rcan_rtps.bridge.commanders")
    participant = DomainParticipant(domain_id)
    topic = Topic(participant, "rt/robot1/cmd_vel", rig.node.types.struct(TWIST))
    writers = [DataWriter(participant, topic), DataWriter(participant, topic)]
    try:
        await eventually(lambda: [p.writers for p in listed(rig)] == [2])
        (shown,) = listed(rig)
        assert shown.node is None
        assert shown.participant == ".".join(f"{b:02x}" for b in participant.guid.bytes[:12])
        # Logged and audited once no name came for the grace period, unnamed.
        await eventually(lambda: entries(rig, "FOREIGN_PUBLISHER"), timeout=15)
        assert entries(rig, "FOREIGN_PUBLISHER")[0]["params"]["node"] is None
        assert "an unnamed node" in warnings(caplog)[0]
    finally:
        del writers, topic, participant


@pytest.fixture
async def http() -> AsyncIterator[aiohttp.ClientSession]:
    async with aiohttp.ClientSession() as session:
        yield session


async def test_the_running_bridge_shows_it_in_api_status(
        sim: Demo, http: aiohttp.ClientSession, jazzy_oracle: OracleEnv) -> None:
    """`rcan-rtps run --sim` as a user starts it: GET /api/status lists the other publisher,
    and its audit log has both entries (the demo's own sim robot publishes none)."""
    _, quiet = await call(http, sim, sim.user, "GET", "/api/status")
    assert quiet["foreign_publishers"] == [] and quiet["foreign_publishers_count"] == 0
    with RclpyOracle(jazzy_oracle, "teleop", "/robot1", domain_id=sim.domain_id,
                     env={"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}) as teleop:
        teleop.call("publisher", topic=CMD_VEL, type=TWIST)
        status = await wait_status(http, sim, lambda s: [
            p["node"] for p in s["foreign_publishers"]] == ["/robot1/teleop"])
        assert status["foreign_publishers"][0]["topic"] == CMD_VEL
        assert status["foreign_publishers_count"] == 1
        teleop.call("unpublish", topic=CMD_VEL)
        await wait_status(http, sim, lambda s: not s["foreign_publishers"])
    events = [json.loads(line)["event"] for line in sim.audit.read_text().splitlines()]
    assert events.count("FOREIGN_PUBLISHER") == 1
    assert events.count("FOREIGN_PUBLISHER_GONE") == 1


async def test_a_flapping_publisher_does_not_flood_the_audit(
        rig: Rig, hostile: RosNode, caplog: pytest.LogCaptureFixture) -> None:
    """A real peer whose cmd_vel writer comes and goes, every change seen by the watch
    (polling every 0.1 s): STATUS follows each, while the audit and the log hold at its
    budget (one entry per change, for ever, before: any DDS peer could fill the disk)."""
    caplog.set_level(logging.INFO, logger="rcan_rtps.bridge.commanders")
    cycles = 10
    for _ in range(cycles):
        publisher = hostile.create_publisher(CMD_VEL, TWIST, qos.DEFAULT)
        await eventually(lambda: [p.node for p in listed(rig)] == ["/robot1/hostile"],
                         what="the flapping writer listed")
        publisher.close()
        await eventually(lambda: listed(rig) == [], what="the flapping writer gone")
    publisher = hostile.create_publisher(CMD_VEL, TWIST, qos.DEFAULT)
    await eventually(lambda: [p.node for p in listed(rig)] == ["/robot1/hostile"])
    told = [e for e in rig.entries()
            if e["event"] in ("FOREIGN_PUBLISHER", "FOREIGN_PUBLISHER_GONE")]
    assert len(told) <= KEY_BURST < 2 * cycles, told  # was one per change: 21
    assert [e["event"] for e in told] == ["FOREIGN_PUBLISHER", "FOREIGN_PUBLISHER_GONE"] * 2
    said = [r for r in caplog.records if r.name == "rcan_rtps.bridge.commanders"]
    assert len(said) <= KEY_BURST
    # Latched, the e-stop's fault says what is there now, budget or not.
    await rig.command(VIEWER, {"action": "estop"})  # no robot here to tell: latched still
    assert rig.governor.latch.latched
    first = status(rig).faults[0]
    assert (first.name, first.level) == (ESTOP_NOT_HOLDING, "ERROR")
    assert "/robot1/hostile" in first.message
    publisher.close()
