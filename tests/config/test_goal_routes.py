"""Goal routes are checked when the registry and the config load (issue 23, item 4).

Each (config key, action type) of the registry's SendGoal routes is a server of its own: a
config whose keys name one server for two action types, a route whose key the config model
does not have, and a registry key declared with two types are refused, naming what clashes.
"""

from __future__ import annotations

from typing import Any

import pytest

from rcan_rtps.config import ConfigError, Ros2Config, loads_config
from rcan_rtps.config._model import goal_routes_problem
from rcan_rtps.rcan import Role
from rcan_rtps.rcan.actions import (
    ACTIONS,
    ActionSpec,
    Effect,
    GoalRoute,
    Invariant,
    NavigateParams,
    SendGoal,
    goal_routes,
)
from rcan_rtps.rcan.actions._registry import collect_goal_routes
from rcan_rtps.ros.names import expand_topic_name

NAV = "nav2_msgs/action/NavigateToPose"
DOCK = "nav2_msgs/action/DockRobot"
BASE = """\
robot: {{ruri: rcan://registry.local/acme/rover/unit-0001}}
bridge:
  ros2:
    namespace: /robot1
{ros2}
  api: {{auth_token_env: RCAN_BRIDGE_TOKEN}}
  safety: {{max_linear_vel: 1.0, max_angular_vel: 1.0}}
"""
ENV = {"RCAN_BRIDGE_TOKEN": "t" * 32}


def load(ros2: str) -> Any:
    return loads_config(BASE.format(ros2=ros2), env=ENV)


def test_the_registry_declares_a_route_per_goal_action() -> None:
    routes = {(r.action_key, r.type_name): r.actions for r in goal_routes()}
    assert routes == {("nav_action", NAV): ("navigate",), ("dock_action", DOCK): ("dock",)}
    assert {a for r in goal_routes() for a in r.actions} == {
        name for name, spec in ACTIONS.items() if spec.starts_goal}


def test_a_goal_server_set_to_null_is_no_server() -> None:
    """A robot without nav2 or a dock says so (issue 27: then no action client is made)."""
    ros2 = load("    nav_action: null\n    dock_action: null").bridge.ros2
    assert (ros2.nav_action, ros2.dock_action) == (None, None)
    assert goal_routes_problem(ros2, goal_routes()) is None
    # The text "null", quoted, is still a name.
    assert load("    nav_action: 'null'").bridge.ros2.nav_action == "null"


def test_the_default_config_gives_each_goal_action_its_own_server() -> None:
    ros2 = load("").bridge.ros2
    assert (ros2.resolve(ros2.nav_action), ros2.resolve(ros2.dock_action)) == (
        "/robot1/navigate_to_pose", "/robot1/dock_robot")


@pytest.mark.parametrize("ros2", [
    "    dock_action: navigate_to_pose",  # the same relative name
    "    nav_action: /robot1/base/go\n    dock_action: base/go",  # absolute vs relative
    "    nav_action: /robot1/rcan_bridge/go\n    dock_action: ~/go",  # private vs absolute
])
def test_two_goal_types_on_one_server_are_refused_naming_both(ros2: str) -> None:
    with pytest.raises(ConfigError) as err:
        load(ros2)
    text = str(err.value)
    for named in ("`nav_action`", "`dock_action`", NAV, DOCK, "(navigate)", "(dock)"):
        assert named in text, text
    assert "bridge.ros2" in text  # reported at the section holding both keys


def test_names_that_only_look_alike_are_two_servers() -> None:
    ros2 = load("    nav_action: /fleet/go\n    dock_action: go").bridge.ros2  # /robot1/go
    assert ros2.resolve(ros2.nav_action) != ros2.resolve(ros2.dock_action)


@pytest.mark.parametrize(("name", "namespace"), [
    ("go", "/robot1"), ("/abs/go", "/robot1"), ("~/go", "/robot1"), ("~", "/robot1"),
    ("go", ""), ("~/go", ""), ("a/b", "/x/y")])
def test_the_config_resolves_names_as_the_node_does(name: str, namespace: str) -> None:
    ros2 = Ros2Config(namespace=namespace, node_name="bridge")
    assert ros2.resolve(name) == expand_topic_name(name, "bridge", namespace or "/")


def test_a_route_to_a_key_the_config_does_not_have_is_refused() -> None:
    route = GoalRoute("arm_action", "control_msgs/action/FollowJointTrajectory",
                      ("arm_goal",))
    problem = goal_routes_problem(Ros2Config(), (*goal_routes(), route))
    assert problem is not None
    assert "`arm_action`" in problem and "arm_goal" in problem, problem
    # a key that exists but is no action name is no better
    odd = GoalRoute("domain_id", NAV, ("odd",))
    assert "`domain_id`" in (goal_routes_problem(Ros2Config(), (odd,)) or "")


def _goal_spec(name: str, key: str, type_name: str) -> ActionSpec[Any]:
    return ActionSpec(name=name, summary="", params=NavigateParams, effect=Effect.MOTION,
                      default_role=Role.USER, starts_goal=True,
                      ros=SendGoal(action_key=key, type_name=type_name,
                                   build=lambda p, k: {}),
                      invariants=(Invariant.ESTOP_GUARD, Invariant.FINITE))


def test_a_registry_key_declared_with_two_types_is_refused() -> None:
    same = collect_goal_routes([_goal_spec("a", "nav_action", NAV),
                                _goal_spec("b", "nav_action", NAV)])
    assert same == (GoalRoute("nav_action", NAV, ("a", "b")),)  # one server, two actions
    with pytest.raises(ValueError, match=r"`nav_action`.*NavigateToPose \(a\).*DockRobot \(b\)"):
        collect_goal_routes([_goal_spec("a", "nav_action", NAV),
                             _goal_spec("b", "nav_action", DOCK)])


def test_a_goal_is_started_exactly_by_a_send_goal_route() -> None:
    with pytest.raises(ValueError, match="SendGoal"):
        ActionSpec(name="x", summary="", params=NavigateParams, effect=Effect.MOTION,
                   default_role=Role.USER, ros=ACTIONS["move"].ros, starts_goal=True,
                   invariants=(Invariant.ESTOP_GUARD, Invariant.FINITE))
    with pytest.raises(ValueError, match="SendGoal"):
        ActionSpec(name="x", summary="", params=NavigateParams, effect=Effect.MOTION,
                   default_role=Role.USER, ros=ACTIONS["navigate"].ros,
                   invariants=(Invariant.ESTOP_GUARD, Invariant.FINITE))
