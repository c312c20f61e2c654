"""ROS names: every rcl validity rule rejects, expansion, mangle/demangle round trips."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from rcan_rtps.ros.errors import InvalidNameError
from rcan_rtps.ros.names import (
    EndpointKind,
    action_names,
    action_of,
    demangle,
    expand_topic_name,
    mangle_service,
    mangle_topic,
    normalize_namespace,
    validate_full_name,
    validate_namespace,
    validate_node_name,
    validate_topic_name,
)

TOKEN = st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,8}", fullmatch=True)
FULL_NAME = st.lists(TOKEN, min_size=1, max_size=5).map(lambda ts: "/" + "/".join(ts))


@given(FULL_NAME)
def test_topic_mangling_round_trips(name: str) -> None:
    back = demangle(mangle_topic(name))
    assert back is not None and back.kind is EndpointKind.TOPIC and back.name == name


@given(FULL_NAME)
def test_service_mangling_round_trips(name: str) -> None:
    request, reply = mangle_service(name)
    assert request == f"rq{name}Request" and reply == f"rr{name}Reply"
    assert demangle(request) == demangle(request) and demangle(request).name == name  # type: ignore[union-attr]
    assert demangle(reply).kind is EndpointKind.REPLY and demangle(reply).name == name  # type: ignore[union-attr]


@given(FULL_NAME)
def test_action_names_round_trip(name: str) -> None:
    for part, member in action_names(name).items():
        assert action_of(member) == (name, part)


@pytest.mark.parametrize(("name", "rule"), [
    ("", "must not be empty"),
    ("/a b", "only letters, digits"),
    ("/a-b", "only letters, digits"),
    ("/a//b", "repeated '/'"),
    ("/a/", "must not end with '/'"),
    ("/1abc", "must not start with a digit"),
    ("/a/2b", "must not start with a digit"),
    ("a/~b", "'~' is allowed only at the start"),
    ("~ab", "'~' must be followed by '/'"),  # rcl checks it from three characters on
    ("~_x", "'~' must be followed by '/'"),
    ("~{node}", "'~' must be followed by '/'"),
    ("/a{b", "substitutions must be balanced"),
    ("/", "must not be just '/'"),
])
def test_topic_rules_reject(name: str, rule: str) -> None:
    with pytest.raises(InvalidNameError, match=rule.replace("(", r"\(")):
        validate_topic_name(name)


def test_full_name_rules() -> None:
    with pytest.raises(InvalidNameError, match="must start with '/'"):
        validate_full_name("a/b")
    with pytest.raises(InvalidNameError, match="longer than"):
        validate_full_name("/" + "a" * 300)


@pytest.mark.parametrize(("name", "rule"), [
    ("", "must not be empty"), ("a/b", "only letters"), ("9node", "start with a digit"),
    ("n" * 256, "at most"),
])
def test_node_name_rules(name: str, rule: str) -> None:
    with pytest.raises(InvalidNameError, match=rule):
        validate_node_name(name)


@pytest.mark.parametrize(("ns", "rule"), [
    ("", "must not be empty"), ("robot", "absolute"), ("/robot/", "end with '/'"),
    ("/a//b", "repeated"), ("/1a", "digit"), ("/a b", "only letters"),
])
def test_namespace_rules(ns: str, rule: str) -> None:
    with pytest.raises(InvalidNameError, match=rule):
        validate_namespace(ns)


@pytest.mark.parametrize(("name", "expected"), [
    ("cmd_vel", "/robot1/cmd_vel"),
    ("/cmd_vel", "/cmd_vel"),
    ("~/status", "/robot1/rcan_bridge/status"),
    ("~", "/robot1/rcan_bridge"),
    ("~/a/b", "/robot1/rcan_bridge/a/b"),
    ("~x", "/robot1/rcan_bridgex"),  # what rcl makes of a two-character `~x`
    ("~_", "/robot1/rcan_bridge_"),
    ("{node}/x", "/robot1/rcan_bridge/x"),
    ("a/b", "/robot1/a/b"),
])
def test_expansion_like_rcl(name: str, expected: str) -> None:
    assert expand_topic_name(name, "rcan_bridge", "/robot1") == expected


def test_expansion_in_root_namespace() -> None:
    assert expand_topic_name("cmd_vel", "n", "/") == "/cmd_vel"
    assert expand_topic_name("~/x", "n", "/") == "/n/x"
    assert expand_topic_name("~", "n", "/") == "/n"
    assert expand_topic_name("~1", "n", "/") == "/n1"


def test_unknown_substitution_is_named() -> None:
    with pytest.raises(InvalidNameError, match="unknown substitution"):
        expand_topic_name("{nope}/x", "n", "/")


def test_namespace_normalization() -> None:
    assert normalize_namespace("robot1") == "/robot1"
    assert normalize_namespace("") == "/"
    assert normalize_namespace("/robot1/") == "/robot1"


def test_non_ros_topics_do_not_demangle() -> None:
    assert demangle("ros_discovery_info") is None
    assert demangle("DCPSParticipant") is None
