"""Which other publishers on the command topics are expected (commanders.foreign_publishers),
and what they mean for STATUS's faults (telemetry): no DDS, the graph's endpoints made here."""

from __future__ import annotations

from rcan_rtps.bridge.commanders import MAX_NODE_NAME, foreign_publishers
from rcan_rtps.bridge.telemetry import (
    ESTOP_NOT_HOLDING,
    FOREIGN_PUBLISHER,
    _commander_faults,
    _Stillness,
)
from rcan_rtps.rcan import Fault, ForeignPublisher, Joints, Telemetry, Velocity
from rcan_rtps.ros import qos
from rcan_rtps.ros.graph import Direction, Endpoint, bound_node_name
from rcan_rtps.ros.names import EndpointKind

CMD_VEL = "/robot1/cmd_vel"
ARM = "/robot1/arm/joint_trajectory"
OWN = bytes(16)
EXPECTED = {CMD_VEL: frozenset({"/controller_server", "/robot1/velocity_smoother"})}


def writer(topic: str, participant: int, node: str | None, n: int = 0) -> Endpoint:
    namespace, _, name = (node or "").rpartition("/")
    named = {} if node is None else {"node_name": name, "node_namespace": namespace or "/"}
    return Endpoint(Direction.PUBLISHER, EndpointKind.TOPIC, topic, "geometry_msgs/msg/Twist",
                    "rt" + topic, "geometry_msgs::msg::dds_::Twist_", bytes([participant, n]) * 8,
                    bytes([participant]) * 12 + bytes(4), qos.DEFAULT, "", "test", **named)


def classify(*endpoints: Endpoint) -> dict[tuple[str, str | None], bool]:
    found = foreign_publishers(list(endpoints), OWN, EXPECTED)
    return {(p.topic, p.node): p.expected for p in found.values()}


def test_a_declared_node_is_expected_on_its_topic_only() -> None:
    assert classify(writer(CMD_VEL, 1, "/controller_server"),
                    writer(ARM, 1, "/controller_server", 1),
                    writer(CMD_VEL, 2, "/robot1/velocity_smoother"),
                    writer(CMD_VEL, 3, "/teleop")) == {
        (CMD_VEL, "/controller_server"): True, (ARM, "/controller_server"): False,
        (CMD_VEL, "/robot1/velocity_smoother"): True, (CMD_VEL, "/teleop"): False}


def test_names_match_exactly_fully_qualified() -> None:
    assert classify(writer(CMD_VEL, 1, "/robot1/controller_server"),
                    writer(CMD_VEL, 2, "/velocity_smoother")) == {
        (CMD_VEL, "/robot1/controller_server"): False, (CMD_VEL, "/velocity_smoother"): False}


def test_a_publisher_whose_node_is_not_known_never_matches() -> None:
    assert classify(writer(CMD_VEL, 1, None)) == {(CMD_VEL, None): False}
    assert foreign_publishers([writer(CMD_VEL, 1, None)], OWN, None)  # listed all the same


def test_one_writer_of_another_node_in_the_participant_makes_it_unexpected() -> None:
    """A component container holds several nodes in one participant: it is expected only if
    every writer it has on the topic is of a declared node, and it is named by the other."""
    for second in ("/teleop", None):
        (publisher,) = foreign_publishers([writer(CMD_VEL, 1, "/controller_server"),
                                           writer(CMD_VEL, 1, second, 1)], OWN, EXPECTED).values()
        assert publisher.writers == 2 and not publisher.expected
        assert publisher.node == (second or "/controller_server")
    (both,) = foreign_publishers([writer(CMD_VEL, 1, "/controller_server"),
                                  writer(CMD_VEL, 1, "/robot1/velocity_smoother", 1)],
                                 OWN, EXPECTED).values()
    assert both.expected and both.writers == 2


def test_the_bridge_itself_is_never_listed() -> None:
    assert foreign_publishers([writer(CMD_VEL, 0, "/robot1/rcan_bridge")], OWN, EXPECTED) == {}


# -- what STATUS's faults say --------------------------------------------------------------

STILL = Telemetry(velocity=Velocity(0.0, 0.0))
MOVING = Telemetry(velocity=Velocity(0.3, 0.0))


def publisher(topic: str, node: str, expected: bool) -> ForeignPublisher:
    return ForeignPublisher(topic=topic, type="t", participant="01", node=node, expected=expected)


def faults(estop: bool, foreign: list[ForeignPublisher], telemetry: Telemetry = STILL,
           stale: bool = False, arm_joints: frozenset[str] = frozenset()) -> list[Fault]:
    motion = sorted({f.topic for f in foreign if f.topic in (CMD_VEL, ARM)})
    return _commander_faults(estop, foreign, motion, _Stillness(
        stale, stale, telemetry, CMD_VEL, {ARM: arm_joints}))


def levels(found: list[Fault]) -> dict[str, str]:
    return {f.name: f.level for f in found}


def test_an_expected_publisher_raises_no_warning_an_unexpected_one_does() -> None:
    controller = publisher(CMD_VEL, "/controller_server", True)
    assert faults(False, [controller]) == []
    teleop = publisher(CMD_VEL, "/teleop", False)
    (warn,) = faults(False, [controller, teleop])
    assert (warn.name, warn.level) == (f"{FOREIGN_PUBLISHER}:{CMD_VEL}", "WARN")
    assert "/teleop" in warn.message and "/controller_server" not in warn.message


def test_latched_with_an_expected_publisher_and_the_robot_still_it_is_a_warning() -> None:
    """Never hidden: the fault is there, first, saying the e-stop cannot hold the robot."""
    found = faults(True, [publisher(CMD_VEL, "/controller_server", True)])
    assert levels(found) == {ESTOP_NOT_HOLDING: "WARN"}
    message = found[0].message
    assert "cannot hold" in message and "/controller_server (expected)" in message
    assert CMD_VEL in message


def test_latched_it_is_an_error_while_the_robot_is_not_seen_still() -> None:
    controller = publisher(CMD_VEL, "/controller_server", True)
    for telemetry, stale in ((MOVING, False), (STILL, True), (Telemetry(), False),
                             (Telemetry(velocity=Velocity(float("nan"), 0.0)), False)):
        found = faults(True, [controller], telemetry, stale)
        assert levels(found) == {ESTOP_NOT_HOLDING: "ERROR"}, (telemetry, stale)
        assert "not seen still" in found[0].message


def test_latched_any_unexpected_publisher_on_a_motion_topic_is_an_error() -> None:
    found = faults(True, [publisher(CMD_VEL, "/controller_server", True),
                          publisher(ARM, "/teleop", False)])
    assert found[0].name == ESTOP_NOT_HOLDING and found[0].level == "ERROR"
    assert levels(found)[f"{FOREIGN_PUBLISHER}:{ARM}"] == "WARN"
    assert f"{FOREIGN_PUBLISHER}:{CMD_VEL}" not in levels(found)


def test_an_expected_trajectory_publisher_needs_the_joints_seen_still() -> None:
    moveit = [publisher(ARM, "/move_group", True)]
    assert levels(faults(True, moveit)) == {ESTOP_NOT_HOLDING: "ERROR"}  # no JointState
    resting = Joints(["elbow", "wrist"], [0.1, 0.2], [0.0, 0.0])
    assert levels(faults(True, moveit, Telemetry(velocity=Velocity(0, 0), joints=resting))) == {
        ESTOP_NOT_HOLDING: "WARN"}
    for joints in (Joints(["elbow", "wrist"], [0.1, 0.2], [0.0, 0.4]),
                   Joints(["elbow", "wrist"], [0.1, 0.2], [])):  # velocities not reported
        telemetry = Telemetry(velocity=Velocity(0, 0), joints=joints)
        assert levels(faults(True, moveit, telemetry)) == {ESTOP_NOT_HOLDING: "ERROR"}


def test_an_arm_is_seen_still_only_by_its_own_joints() -> None:
    """A JointState that does not list the arm's configured joints (only the wheels', the
    arm's own coming on another topic) says nothing of the arm; nor does one cut short when
    the arm's joints are not configured (any joint may be the arm's)."""
    moveit = [publisher(ARM, "/move_group", True)]
    arm = frozenset({"shoulder", "elbow"})
    wheels = Joints(["wheel_left", "wheel_right"], [0.0, 0.0], [0.0, 0.0])
    assert levels(faults(True, moveit, Telemetry(velocity=Velocity(0, 0), joints=wheels),
                         arm_joints=arm)) == {ESTOP_NOT_HOLDING: "ERROR"}
    both = Joints(["wheel_left", "shoulder", "elbow"], [0.0] * 3, [0.0] * 3)
    assert levels(faults(True, moveit, Telemetry(velocity=Velocity(0, 0), joints=both),
                         arm_joints=arm)) == {ESTOP_NOT_HOLDING: "WARN"}
    cut = Joints([f"j{i}" for i in range(64)], [0.0] * 64, [0.0] * 64, count=100)
    assert levels(faults(True, moveit, Telemetry(velocity=Velocity(0, 0), joints=cut))) == {
        ESTOP_NOT_HOLDING: "ERROR"}
    assert levels(faults(True, moveit, Telemetry(velocity=Velocity(0, 0), joints=cut),
                         arm_joints=frozenset({"j3"}))) == {ESTOP_NOT_HOLDING: "WARN"}


def test_a_node_name_cut_at_the_idl_bound_is_never_expected() -> None:
    """ros_discovery_info's names are bounded (256 characters each) by its IDL, not by what
    a peer writes: the graph cuts them where it reads them (bound_node_name; a real peer in
    test_hostile_peers), and a cut name — the declared one and more — is never expected."""
    declared = "/" + "n" * 300
    cut = "/" + bound_node_name("n" * 300)
    (publisher,) = foreign_publishers([writer(CMD_VEL, 1, cut)], OWN,
                                      {CMD_VEL: frozenset({declared})}).values()
    assert publisher.node == cut and len(cut) <= MAX_NODE_NAME and not publisher.expected
    # The config takes no declared name with the cut's mark (test_foreign_publishers_config).
    assert publisher.node.startswith("/nnn") and "…" in publisher.node
