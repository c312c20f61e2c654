"""`~` in a configured topic: rcl wants it followed by '/' (or alone). `~cmd_vel` resolved to
`/robot1/rcan_bridgecmd_vel` — the node's name run into the topic's — and was taken: it is
refused, naming the key and its line; `~/cmd_vel` is a topic inside the bridge's node."""

from __future__ import annotations

import itertools
import textwrap

import pytest

from rcan_rtps.config import ConfigError, loads_config
from rcan_rtps.config._model import _ros_name_problem
from rcan_rtps.ros.errors import InvalidNameError
from rcan_rtps.ros.names import expand_topic_name

HEAD = """\
robot: {ruri: rcan://registry.local/acme/rover/unit-0001}
bridge:
  api: {auth_token_env: RCAN_BRIDGE_TOKEN}
  safety: {max_linear_vel: 1.0, max_angular_vel: 1.0}
  ros2:
"""
BASE = HEAD + "    namespace: /robot1\n"


def issues(ros2: str) -> list[tuple[str, int | None, str]]:
    with pytest.raises(ConfigError) as info:
        loads_config(BASE + textwrap.indent(textwrap.dedent(ros2), "    "), env={})
    text = str(info.value)
    found = [(i.path, i.line, i.message) for i in info.value.issues]
    for path, line, _ in found:  # what the operator reads names the key and the line
        assert f"line {line}: {path}:" in text
    return found


@pytest.mark.parametrize(("ros2", "path"), [
    ("cmd_vel_topic: ~cmd_vel", "cmd_vel_topic"),
    ("odom_topic: ~o", "odom_topic"),  # rcl passes a two-character `~x`; the same mistake
    ("nav_action: ~nav/x", "nav_action"),
    ("arms: {left: {topic: ~left/joint_trajectory}}", "arms.left.topic"),
    ("images: {front: {topic: ~camera}}", "images.front.topic"),
    ("foreign_publishers: {expected: {~cmd_vel: [/teleop]}}",
     "foreign_publishers.expected.~cmd_vel"),
])
def test_a_tilde_not_followed_by_a_slash_is_refused_at_its_key_and_line(
        ros2: str, path: str) -> None:
    [(got, line, message)] = issues(ros2)
    assert (got, line) == (f"$.bridge.ros2.{path}", 7)
    assert "'~' must be followed by '/'" in message and "'~/" in message


def test_a_namespace_has_no_tilde() -> None:
    with pytest.raises(ConfigError) as info:
        loads_config(HEAD + "    namespace: ~/robot1\n", env={})
    [(got, line, message)] = [(i.path, i.line, i.message) for i in info.value.issues]
    assert (got, line) == ("$.bridge.ros2.namespace", 6)
    assert "no '~'" in message


def test_a_tilde_slash_topic_is_inside_the_node() -> None:
    ros2 = loads_config(BASE + "    cmd_vel_topic: ~/cmd_vel\n", env={}).bridge.ros2
    assert ros2.resolve(ros2.cmd_vel_topic) == "/robot1/rcan_bridge/cmd_vel"
    assert "/robot1/rcan_bridge/cmd_vel" in ros2.command_topics()


NAMES = ["".join(p) for n in range(1, 6) for p in itertools.product("~/a_", repeat=n)]


def test_what_the_config_takes_the_node_resolves_the_same() -> None:
    """The config's check is no looser than names.py (checked against rcl by
    tests/interop/test_names_vs_rcl.py), and its resolution is the node's: every name of up
    to five of `~/a_` (one test, not 1,364: each would cost the parallel phase its overhead)."""
    wrong = []
    for name in NAMES:
        if _ros_name_problem(name) is not None:
            continue
        loaded = loads_config(BASE + f"    odom_topic: '{name}'\n", env={}).bridge.ros2
        try:
            expanded = expand_topic_name(name, "rcan_bridge", "/robot1")
        except InvalidNameError as exc:
            wrong.append(f"the config takes {name!r}, which rcl refuses: {exc}")
            continue
        if loaded.resolve(name) != expanded:
            wrong.append(f"{name!r}: the config resolves {loaded.resolve(name)!r}, "
                         f"the node {expanded!r}")
    assert wrong == []
