"""arm_joint: parameter forms, and the JOINT_GROUP invariant (which arm, which joints)."""

from __future__ import annotations

from typing import Any

import pytest
from govhelpers import command

from rcan_rtps.config import ArmConfig
from rcan_rtps.governance import outcomes
from rcan_rtps.governance.invariants import JointGroups, Violation
from rcan_rtps.rcan import SchemaValidationError
from rcan_rtps.rcan.actions.arm_joint import trajectory

ONE = {"joints": ["elbow"], "positions": [0.5], "duration_s": 1.0}
ARMS = {"left": ArmConfig(topic="left/traj", joints=["l1", "l2"]),
        "right": ArmConfig(topic="right/traj", joints=["r1"])}


def _check(groups: JointGroups, params: dict[str, Any]) -> Any:
    cmd = command("arm_joint", params)
    return groups(cmd, cmd.params)


@pytest.mark.parametrize("params, message", [
    ({"joints": ["a"], "positions": [0.1]}, "needs `duration_s`"),
    ({"joints": ["a"]}, "either `positions` with `duration_s`, or `points`"),
    ({"joints": ["a"], "positions": [0.1], "duration_s": 1.0,
      "points": [{"positions": [0.1], "time_from_start_s": 1.0}]}, "either"),
    ({"joints": ["a"], "duration_s": 1.0,
      "points": [{"positions": [0.1], "time_from_start_s": 1.0}]}, "each point has its own"),
    ({"joints": ["a", "b"], "positions": [0.1], "duration_s": 1.0}, "one entry per joint"),
    ({"joints": ["a"], "points": [{"positions": [0.1], "velocities": [1, 2],
                                   "time_from_start_s": 1.0}]}, "`velocities` must have one"),
    ({"joints": ["a"], "points": [{"positions": [0.1], "time_from_start_s": 1.0},
                                  {"positions": [0.2], "time_from_start_s": 1.0}]}, "increase"),
    ({"joints": ["a", "a"], "positions": [0.1, 0.2], "duration_s": 1.0}, "repeat"),
    ({"joints": ["a"], "points": [{"positions": [0.1], "time_from_start_s": 0}]}, ">"),
    ({"joints": ["a"], "points": [{"positions": [1e12], "time_from_start_s": 1}]},
     "$.params.points[0].positions[0]"),
    ({"joints": ["a"], "points": [{"positions": [0.1], "time_from_start_s": 1, "x": 1}]},
     "unknown field"),
    ({"joints": ["a"], "group": "Left", "positions": [0.1], "duration_s": 1.0}, "group"),
])
def test_bad_trajectories_are_schema_errors(params: dict[str, Any], message: str) -> None:
    with pytest.raises(SchemaValidationError) as caught:
        command("arm_joint", params)
    assert message in str(caught.value)


def test_points_become_one_trajectory() -> None:
    cmd = command("arm_joint", {"joints": ["a", "b"], "points": [
        {"positions": [0, 1], "time_from_start_s": 0.25},
        {"positions": [2, 3], "velocities": [0.5, 0], "time_from_start_s": 3.5}]})
    msg = trajectory(cmd.params, None)  # type: ignore[arg-type]  # the builder needs no kit
    assert msg["joint_names"] == ["a", "b"]
    assert msg["points"] == [
        {"positions": [0, 1], "velocities": [], "time_from_start": {"sec": 0,
                                                                    "nanosec": 250_000_000}},
        {"positions": [2, 3], "velocities": [0.5, 0], "time_from_start": {"sec": 3,
                                                                          "nanosec": 500_000_000}}]


def test_no_arms_configured_keeps_the_single_topic() -> None:
    groups = JointGroups({})
    assert _check(groups, ONE).group is None
    with pytest.raises(Violation, match="no arm groups"):
        _check(groups, {**ONE, "group": "left"})


def test_the_only_arm_is_implied_and_recorded() -> None:
    groups = JointGroups({"arm": ArmConfig(topic="t", joints=[])})  # no list: any joint
    assert _check(groups, ONE).group == "arm"


@pytest.mark.parametrize("params, message", [
    (ONE, "name the arm in `group`: one of left, right"),
    ({**ONE, "group": "tail"}, "no arm 'tail' (arms: left, right)"),
    ({**ONE, "joints": ["l1", "r1"], "positions": [0, 0], "group": "left"},
     "arm 'left' has no joint r1"),
])
def test_joint_group_violations(params: dict[str, Any], message: str) -> None:
    with pytest.raises(Violation) as caught:
        _check(JointGroups(ARMS), params)
    assert caught.value.rejection == outcomes.JOINT_GROUP_VIOLATION
    assert message in str(caught.value)


def test_a_named_arm_with_its_own_joints_passes() -> None:
    applied = _check(JointGroups(ARMS), {**ONE, "joints": ["l2"], "group": "left"})
    assert applied.group == "left" and applied.joints == ["l2"]
