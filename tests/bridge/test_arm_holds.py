"""`bridge.arm_holds` alone: where a stop holds an arm, and when it does not (a manual clock;
the wire is tests/interop/test_arms.py)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import pytest

from rcan_rtps.bridge.arm_holds import (
    MAX_AGE_S,
    MAX_JOINT_NAME,
    MAX_KEPT,
    MAX_LEAD,
    SETTLING_S,
    ArmHolds,
    JointPositions,
)


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class Topic:
    def __init__(self, topic: str, fail: bool = False) -> None:
        self.topic, self.fail = topic, fail
        self.sent: list[Any] = []

    def publish(self, message: Any) -> None:
        if self.fail:
            raise RuntimeError("writer closed")
        self.sent.append(message)


def hold(joints: Sequence[str], where: Sequence[float]) -> Any:
    return (list(joints), list(where))


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def positions(clock: Clock) -> JointPositions:
    return JointPositions(clock)


def test_joints_are_kept_from_any_joint_state_before_any_trajectory(
        positions: JointPositions, clock: Clock) -> None:
    # Heard before its first trajectory: a stop right after it (before the next JointState)
    # finds where the arm is.
    positions.heard(["a", "b"], [1.0, 2.0], [])
    assert positions.now(["a", "b"], 1.0) == [1.0, 2.0]
    # Two publishers, each with part of the arm (a gripper's node, the arm's broadcaster).
    positions.heard(["a", "x"], [1.05, 5.0], [0.0, 0.0])
    positions.heard(["b"], [2.05], [])
    assert positions.now(["a", "b", "x"], 1.0) == [1.05, 2.05, 5.0]
    assert positions.now(["y"], 1.0) == "no joint_states heard for 'y'"


def test_a_joint_state_s_size_is_bounded_but_not_for_watched_joints(
        positions: JointPositions) -> None:
    long_name = "j" * (MAX_JOINT_NAME + 1)
    positions.heard([long_name], [1.0], [])  # no command can name it
    assert positions.now([long_name], 1.0) == f"no joint_states heard for {long_name!r}"
    junk = [f"junk{i}" for i in range(MAX_KEPT + 10)]
    positions.heard(junk, [0.0] * len(junk), [])
    positions.heard(["elbow"], [0.5], [])
    assert positions.now(["elbow"], 1.0) == "no joint_states heard for 'elbow'"
    positions.watch("/arm", ["elbow"])  # its trajectory: kept from the next JointState
    positions.heard(["elbow"], [0.5], [])
    assert positions.now(["elbow"], 1.0) == [0.5]


def test_a_sender_s_inconsistent_lists_are_read_as_far_as_they_go(
        positions: JointPositions) -> None:
    positions.heard(["a", "b", "c", "a"], [1.0, 2.0], [0.0])  # short lists, a name twice
    assert positions.now(["a", "b"], 1.0) == [1.0, 2.0]
    assert positions.now(["c"], 1.0) == "no joint_states heard for 'c'"


def test_a_position_is_carried_forward_by_its_velocity_by_at_most_max_lead(
        positions: JointPositions, clock: Clock) -> None:
    positions.heard(["a", "b", "c"], [1.0, 1.0, 1.0], [0.5, 1e300, -math.inf])
    clock.t += 0.1
    a, b, c = positions.now(["a", "b", "c"], 1.0)
    assert a == pytest.approx(1.05)
    assert b == 1.0 + MAX_LEAD  # a wrong velocity does not make the hold a long move
    assert c == 1.0  # not a velocity at all: not carried


def test_old_or_not_finite_positions_hold_nothing(positions: JointPositions,
                                                  clock: Clock) -> None:
    positions.heard(["a", "b"], [1.0, math.nan], [])
    assert "position nan" in str(positions.now(["b"], 1.0))
    clock.t += 0.6
    assert positions.now(["a"], 0.5) == "joint_states for 'a' last heard 0.60 s ago"


def test_a_stop_holds_each_running_trajectory_once(positions: JointPositions,
                                                   clock: Clock) -> None:
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    left, right = Topic("/left"), Topic("/right")
    arms.sent(left, "m1", ["a"], 5.0, hold)
    arms.sent(right, "m2", ["b"], 5.0, hold)
    positions.heard(["a", "b"], [0.1, 0.2], [])
    assert arms.hold_all() == (("/left", "/right"), ())
    assert left.sent == [(["a"], [0.1])] and right.sent == [(["b"], [0.2])]
    assert arms.running() == [] and arms.hold_all() == ((), ())


def test_a_trajectory_the_next_on_its_topic_may_not_have_replaced_is_held_too(
        positions: JointPositions, clock: Clock) -> None:
    # joint_trajectory_controller refuses m2 (only some of its joints, without
    # allow_partial_joints_goal), and the topic says nothing: m1 may run on. Each joint set
    # still due is held, oldest first (a hold of a set the controller refuses is refused).
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    left = Topic("/left")
    arms.sent(left, "m1", ["a", "b"], 60.0, hold)
    arms.sent(left, "m2", ["b"], 0.5, hold)
    positions.heard(["a", "b"], [0.1, 0.2], [])
    assert arms.running() == ["m1", "m2"]
    assert arms.hold_all() == (("/left",), ())
    assert left.sent == [(["a", "b"], [0.1, 0.2]), (["b"], [0.2])]
    assert arms.running() == []


def test_a_trajectory_of_the_same_joints_replaces_the_last_and_an_ended_one_is_not_held(
        positions: JointPositions, clock: Clock) -> None:
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    left = Topic("/left")
    arms.sent(left, "m1", ["a", "b"], 60.0, hold)
    arms.sent(left, "m2", ["b", "a"], 0.5, hold)  # the controller takes it as it took m1
    positions.heard(["a", "b"], [0.1, 0.2], [])
    assert arms.running() == ["m2"]
    clock.t += 0.5 + SETTLING_S + 0.01  # m2 has ended, settled included
    assert arms.running() == []
    assert arms.hold_all() == ((), ()) and left.sent == []


def test_a_stop_of_one_principal_holds_only_its_trajectories(positions: JointPositions,
                                                             clock: Clock) -> None:
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    left, right = Topic("/left"), Topic("/right")
    arms.sent(left, "mine", ["a"], 5.0, hold)
    arms.sent(right, "theirs", ["b"], 5.0, hold)
    positions.heard(["a", "b"], [0.1, 0.2], [])
    assert arms.hold({"mine", "unknown"}) == (("/left",), ())
    assert right.sent == [] and arms.running() == ["theirs"]


def test_an_arm_that_cannot_be_held_is_named_and_kept_for_the_next_stop(
        positions: JointPositions, clock: Clock) -> None:
    arms = ArmHolds(positions, max_age_s=10.0, monotonic=clock)  # bounded by MAX_AGE_S
    left, right = Topic("/left"), Topic("/right", fail=True)
    arms.sent(left, "m1", ["a"], 5.0, hold)
    arms.sent(right, "m2", ["b"], 5.0, hold)
    positions.heard(["a", "b"], [0.1, 0.2], [])
    clock.t += MAX_AGE_S + 0.01
    held = arms.hold_all()
    assert held.held == () and len(held.not_held) == 2
    assert "the arm on /left was not held: joint_states for 'a' last heard" in held.not_held[0]
    positions.heard(["a", "b"], [0.3, 0.4], [])
    held = arms.hold_all()  # the faulty writer does not keep the other arm moving
    assert held.held == ("/left",) and left.sent == [(["a"], [0.3])]
    assert held.not_held == ("the arm on /right was not held: RuntimeError('writer closed')",)
    assert arms.running() == ["m2"]


def test_a_joint_whose_joint_states_senders_disagree_is_not_held(
        positions: JointPositions, clock: Clock) -> None:
    # The robot's broadcaster (1) and a joint_state_publisher left running (2, its zeros): a
    # hold at whichever came last may be a step across the arm's reach.
    positions.heard(["a", "b"], [0.25, -0.5], [0.0, 0.0], sender=1)
    clock.t += 0.02
    positions.heard(["a", "b"], [0.0, 0.0], [], sender=2)
    assert positions.now(["a", "b"], 1.0) == (
        "joint_states senders disagree on 'a': 0.250 and 0.000, 0.00 s ago")
    clock.t += 0.02
    positions.heard(["a", "b"], [0.25, -0.5], [0.0, 0.0], sender=1)
    assert isinstance(positions.now(["a", "b"], 1.0), str)
    # One sender again: held once the disagreement is MAX_AGE_S old.
    for _ in range(round(MAX_AGE_S / 0.02) + 1):
        clock.t += 0.02
        positions.heard(["a", "b"], [0.25, -0.5], [0.0, 0.0], sender=1)
    assert positions.now(["a", "b"], MAX_AGE_S) == [0.25, -0.5]


def test_one_sender_never_disagrees_with_itself_nor_senders_that_agree(
        positions: JointPositions, clock: Clock) -> None:
    # No velocities given, 10 Hz, 3 rad/s: 0.3 rad between two samples of one sender.
    positions.heard(["fast", "wrap"], [0.0, math.pi - 0.01], [], sender=1)
    clock.t += 0.1
    positions.heard(["fast", "wrap"], [0.3, math.pi - 0.01], [], sender=1)
    # Another sender (a driver restarted): where the first left it, or a turn around.
    clock.t += 0.1
    positions.heard(["fast", "wrap"], [0.35, -math.pi + 0.02], [0.5, 0.0], sender=3)
    clock.t += 2.0  # the first again, after long: the joint may be anywhere now
    positions.heard(["fast"], [1.5], [0.0], sender=1)
    assert isinstance(positions.now(["fast", "wrap"], 10.0, resting_holds=True), list)


def test_a_joint_heard_at_rest_holds_longer_while_nothing_of_ours_moves_it(
        positions: JointPositions, clock: Clock) -> None:
    # A busy computer delays joint_states (1.7 s measured under CPU load): an arm heard at
    # rest, its velocity given, is where it was — until a trajectory of ours moves it.
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    positions.heard(["rest", "unsaid", "slow"], [0.4, 0.5, 0.6], [0.0, math.nan, 0.3])
    clock.t += 1.5
    assert arms.cannot_hold(["rest"]) is None  # MAX_AGE_S passed, at rest: still known
    assert "last heard 1.50 s ago" in str(arms.cannot_hold(["unsaid"]))  # no velocity given
    assert "last heard 1.50 s ago" in str(arms.cannot_hold(["slow"]))  # it was moving
    left = Topic("/left")
    arms.sent(left, "m1", ["rest"], 30.0, hold)  # ours moves it now
    assert "last heard 1.50 s ago" in str(arms.cannot_hold(["rest"]))
    assert arms.hold_all().not_held  # nor is it held where it was heard
    clock.t += 1.0
    assert "last heard 2.50 s ago" in str(positions.now(["rest"], 2.0, resting_holds=True))
