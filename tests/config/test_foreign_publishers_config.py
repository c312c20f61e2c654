"""`bridge.ros2.foreign_publishers`: the publishers expected on the command topics and how often
the graph is looked at, checked strictly (a typo would hide nothing, but would never match:
said at once, with its line)."""

from __future__ import annotations

import textwrap

import msgspec
import pytest

from rcan_rtps.config import ConfigError, RcanConfig, Ros2Config, loads_config

BASE = """\
robot: {ruri: rcan://registry.local/acme/rover/unit-0001}
bridge:
  api: {auth_token_env: RCAN_BRIDGE_TOKEN}
  safety: {max_linear_vel: 1.0, max_angular_vel: 1.0}
  ros2:
    namespace: /robot1
"""


def load(ros2: str) -> RcanConfig:
    return loads_config(BASE + textwrap.indent(textwrap.dedent(ros2), "    "), env={})


def only_issue(ros2: str) -> tuple[str, int | None, str]:
    with pytest.raises(ConfigError) as info:
        load(ros2)
    [issue] = info.value.issues
    return issue.path, issue.line, issue.message


def test_by_default_nothing_is_expected_and_the_graph_is_read_every_second() -> None:
    ros2 = load("").bridge.ros2
    assert ros2.foreign_publishers.poll_s == 1.0
    assert ros2.expected_publishers() == {}


def test_expected_publishers_resolve_like_the_topics_they_name() -> None:
    ros2 = load("""\
        arms:
          left: {topic: left_arm/joint_trajectory}
        foreign_publishers:
          poll_s: 0.25
          expected:
            cmd_vel: [/robot1/controller_server, /velocity_smoother]
            /robot1/left_arm/joint_trajectory: [/move_group]
        """).bridge.ros2
    assert ros2.foreign_publishers.poll_s == 0.25
    assert ros2.expected_publishers() == {
        "/robot1/cmd_vel": frozenset({"/robot1/controller_server", "/velocity_smoother"}),
        "/robot1/left_arm/joint_trajectory": frozenset({"/move_group"})}
    assert ros2.command_topics() == {"/robot1/cmd_vel", "/robot1/emergency_stop",
                                     "/robot1/left_arm/joint_trajectory"}


@pytest.mark.parametrize("poll_s", ["0.05", "0", "-1", "10.5", ".nan", "never"])
def test_the_poll_interval_is_bounded(poll_s: str) -> None:
    path, line, message = only_issue(f"foreign_publishers: {{poll_s: {poll_s}}}")
    assert path == "$.bridge.ros2.foreign_publishers.poll_s" and line == 7
    assert message.startswith("Expected")


@pytest.mark.parametrize("poll_s", ["0.1", "10"])
def test_the_poll_interval_bounds_are_inclusive(poll_s: str) -> None:
    assert load(f"foreign_publishers: {{poll_s: {poll_s}}}").bridge.ros2.foreign_publishers.poll_s \
        == float(poll_s)


@pytest.mark.parametrize(("nodes", "words"), [
    ("[controller_server]", "'controller_server' is not a fully qualified node name"),
    ("[/robot1/]", "'/robot1/' is not a fully qualified node name"),
    ("['/a b']", "is not a fully qualified node name"),
    ("['~/x']", "is not a fully qualified node name"),
    ("[/1node]", "is not a fully qualified node name"),
    ("[/a, /a]", "lists a node more than once"),
])
def test_a_node_must_be_named_as_ros2_node_list_prints_it(nodes: str, words: str) -> None:
    path, line, message = only_issue(f"foreign_publishers: {{expected: {{cmd_vel: {nodes}}}}}")
    assert path == "$.bridge.ros2.foreign_publishers.expected" and line == 7
    assert words in message and "cmd_vel" in message


@pytest.mark.parametrize(("expected", "path_end", "words"), [
    ("{cmd_vel: []}", ".expected.cmd_vel", "length >= 1"),
    ("{cmd_vel: /controller_server}", ".expected.cmd_vel", "Expected `array`, got `str`"),
    ("[/controller_server]", ".expected", "Expected `object`, got `array`"),
    ("{'bad topic': [/a]}", ".expected.bad topic", "not a valid ROS name"),
])
def test_the_shape_of_expected_is_checked(expected: str, path_end: str, words: str) -> None:
    path, _, message = only_issue(f"foreign_publishers: {{expected: {expected}}}")
    assert path == "$.bridge.ros2.foreign_publishers" + path_end
    assert words in message


def test_a_topic_the_bridge_does_not_command_is_refused_naming_those_it_does() -> None:
    path, _, message = only_issue("foreign_publishers: {expected: {cmd_vell: [/teleop]}}")
    assert path == "$.bridge.ros2"
    assert "'cmd_vell' (/robot1/cmd_vell)" in message
    assert "/robot1/cmd_vel, /robot1/emergency_stop" in message
    # With arms, the single trajectory topic is not one the bridge publishes to.
    path, _, message = only_issue("""\
        arms: {left: {topic: left/joint_trajectory}}
        foreign_publishers:
          expected: {joint_trajectory_controller/joint_trajectory: [/move_group]}
        """)
    assert "not a topic the bridge commands the robot on" in message


def test_one_topic_named_twice_is_refused() -> None:
    _, _, message = only_issue(
        "foreign_publishers: {expected: {cmd_vel: [/a], /robot1/cmd_vel: [/b]}}")
    assert "names /robot1/cmd_vel twice" in message


def test_unknown_keys_are_refused() -> None:
    path, _, message = only_issue("foreign_publishers: {expect: {cmd_vel: [/a]}}")
    assert path == "$.bridge.ros2.foreign_publishers.expect" and "unknown" in message.lower()


def test_the_checks_hold_outside_the_loader() -> None:
    with pytest.raises(msgspec.ValidationError, match="fully qualified"):
        msgspec.convert({"foreign_publishers": {"expected": {"cmd_vel": ["teleop"]}}},
                        Ros2Config)
    with pytest.raises(msgspec.ValidationError, match="not a topic the bridge commands"):
        msgspec.convert({"foreign_publishers": {"expected": {"odom": ["/teleop"]}}}, Ros2Config)
