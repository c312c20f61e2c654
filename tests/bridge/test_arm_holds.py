"""`bridge.arm_holds` alone: where a stop holds an arm, and when it does not (a manual clock;
the wire is tests/interop/test_arms.py)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from rcan_rtps.bridge.arm_holds import SETTLING_S, TRACKING_SLACK_S, ArmHolds
from rcan_rtps.bridge.desired_path import DesiredPath
from rcan_rtps.bridge.joint_positions import (
    MAX_AGE_S,
    MAX_JOINT_NAME,
    MAX_KEPT,
    MAX_LEAD,
    JointPositions,
    Missing,
    Unknown,
)
from rcan_rtps.governance import ArmsHeld
from rcan_rtps.rcan.actions import PathPoint


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
    assert arms.hold_all() == ArmsHeld(("/left", "/right"))
    assert left.sent == [(["a"], [0.1])] and right.sent == [(["b"], [0.2])]
    assert arms.running() == [] and arms.hold_all() == ArmsHeld()


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
    assert arms.hold_all() == ArmsHeld(("/left",))
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
    assert arms.hold_all() == ArmsHeld() and left.sent == []


def test_a_stop_of_one_principal_holds_only_its_trajectories(positions: JointPositions,
                                                             clock: Clock) -> None:
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    left, right = Topic("/left"), Topic("/right")
    arms.sent(left, "mine", ["a"], 5.0, hold)
    arms.sent(right, "theirs", ["b"], 5.0, hold)
    positions.heard(["a", "b"], [0.1, 0.2], [])
    assert arms.hold({"mine", "unknown"}) == ArmsHeld(("/left",))
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


# -- joint_states late: a hold where the controller drives the arm (its trajectory, now) --
def line(*points: tuple[list[float], float]) -> list[PathPoint]:
    """Positions-only points (the controller interpolates straight lines between them)."""
    return [PathPoint(tuple(at), None, time_s) for at, time_s in points]


def test_the_first_segment_runs_straight_from_the_start_state() -> None:
    path = DesiredPath([0.0, 2.0], None, line(([1.0, 1.0], 2.0)))
    assert path.at(0.5) == pytest.approx([0.25, 1.75])
    assert path.at(-1.0) == [0.0, 2.0] and path.at(math.nan) == [0.0, 2.0]  # not started
    assert path.peak_speeds == pytest.approx([0.5, 0.5])


def test_points_without_velocities_are_joined_by_straight_lines() -> None:
    path = DesiredPath([0.0, 0.0], [0.0, 0.0],  # the start's velocities alone: still lines
                       line(([1.0, -1.0], 1.0), ([1.0, 1.0], 3.0), ([0.0, 0.0], 4.0)))
    assert path.at(0.5) == pytest.approx([0.5, -0.5])
    assert path.at(1.0) == pytest.approx([1.0, -1.0])
    assert path.at(2.0) == pytest.approx([1.0, 0.0])
    assert path.at(3.5) == pytest.approx([0.5, 0.5])
    assert path.peak_speeds == pytest.approx([1.0, 1.0])


def test_points_with_velocities_at_both_ends_are_joined_by_cubics() -> None:
    # Start at rest (its velocity measured), through 1 rad at 1 s moving 1 rad/s, on to 2 rad.
    points = [PathPoint((1.0,), (1.0,), 1.0), PathPoint((2.0,), (1.0,), 2.0)]
    path = DesiredPath([0.0], [0.0], points)
    # The cubic with p(0)=0, p'(0)=0, p(1)=1, p'(1)=1 is 2t² - t³.
    assert path.at(0.5)[0] == pytest.approx(2 * 0.25 - 0.125)
    assert path.at(1.5)[0] == pytest.approx(1.5)  # ends' velocities equal the slope: a line
    eps = 1e-6  # its velocities at the ends are the points' (a Hermite cubic)
    assert (path.at(eps)[0] - path.at(0.0)[0]) / eps == pytest.approx(0.0, abs=1e-5)
    assert (path.at(1.0)[0] - path.at(1.0 - eps)[0]) / eps == pytest.approx(1.0, rel=1e-4)
    assert path.peak_speeds == pytest.approx([4 / 3])  # p'(t) = 4t - 3t², highest at t = 2/3
    # Without the start's velocities (not in its joint_states): the first segment is a line.
    assert DesiredPath([0.0], None, points).at(0.5) == pytest.approx([0.5])


def test_past_its_last_point_the_trajectory_stays_there() -> None:
    path = DesiredPath([0.0], None, line(([1.0], 1.0), ([3.0], 2.0)))
    assert path.at(2.0) == [3.0] and path.at(1e9) == [3.0]


def stale_after(arms: ArmHolds, positions: JointPositions, clock: Clock, heard_at: float,
                heard: list[float], path: list[PathPoint], *, start: float = 0.0) -> Topic:
    """An arm heard at `start`, at rest, sent along `path`; heard at `heard` `heard_at` s
    later, then not again: now MAX_AGE_S (and a little) after that."""
    left = Topic("/left")
    positions.heard(["a"], [start], [0.0])
    arms.sent(left, "m1", ["a"], path[-1].time_s, hold, path=path)
    clock.t += heard_at
    positions.heard(["a"], heard, [0.0])
    clock.t += MAX_AGE_S + 0.1
    stale = positions.now(["a"], 10.0)
    assert isinstance(stale, Unknown) and stale.missing is Missing.STALE
    return left


def not_held(arms: ArmHolds, left: Topic) -> tuple[str, ...]:
    """A stop holds no arm and sends nothing on `left`: why, each arm it could not hold."""
    held = arms.hold_all()
    assert held.held == () and left.sent == [], left.sent
    return held.not_held


def test_a_late_arm_that_followed_its_trajectory_is_held_where_the_trajectory_has_it(
        positions: JointPositions, clock: Clock) -> None:
    # 0 → 1 rad over 2 s; heard 1 s in at 0.5 (where the trajectory had it, farther from
    # where it started than the tolerance: not an arm left standing), then late.
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    left = stale_after(arms, positions, clock, 1.0, [0.5], line(([1.0], 2.0)))
    assert arms.hold_all() == ArmsHeld(("/left",), (), ("/left",))
    ((joints, (at,)),) = left.sent
    assert joints == ["a"] and at == pytest.approx(0.5 * (1.0 + MAX_AGE_S + 0.1))
    assert arms.running() == []


def test_a_late_arm_that_was_not_following_its_trajectory_is_not_held(
        positions: JointPositions, clock: Clock) -> None:
    # Heard at 0.6 where the trajectory had 0.15: farther than MAX_LEAD + 0.5 rad/s × the
    # slack (the controller refused it, or something else drives the arm).
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    left = stale_after(arms, positions, clock, 0.3, [0.6], line(([1.0], 2.0)))
    (why,) = not_held(arms, left)
    assert arms.running() == ["m1"]
    assert why.startswith("the arm on /left was not held: joint_states for 'a' last heard 0.60")
    assert "'a' was last heard 0.450 from where its trajectory had it then" in why
    assert "the arm was not following it" in why


@pytest.mark.parametrize(("off", "held"), [(0.001, True), (-0.001, False)])
def test_a_late_sample_tracks_within_the_slack(off: float, held: bool) -> None:
    # A sample taken TRACKING_SLACK_S before it was heard (delivery under load), the arm
    # MAX_LEAD behind that (following error), still tracks: 0.5 rad/s, heard at 1.0 s.
    clock = Clock()
    positions = JointPositions(clock)
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    behind = 0.5 * (1.0 - TRACKING_SLACK_S) - MAX_LEAD
    stale_after(arms, positions, clock, 1.0, [behind + off], line(([1.0], 2.0)))
    assert arms.hold_all().at_desired == (("/left",) if held else ())


def test_a_late_arm_unheard_longer_than_the_robot_s_telemetry_may_be_is_not_held(
        positions: JointPositions, clock: Clock) -> None:
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    left = stale_after(arms, positions, clock, 0.3, [0.15], line(([1.0], 20.0)))
    clock.t += 2.0
    (why,) = arms.hold_all().not_held
    assert "unheard for longer than the robot's telemetry may be (2 s)" in why
    assert left.sent == []


def test_a_late_arm_two_trajectories_of_ours_may_drive_is_not_held(
        positions: JointPositions, clock: Clock) -> None:
    # m2 names 'a' alone: the controller may have refused it (m1 runs on) or taken it.
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    left = Topic("/left")
    positions.heard(["a", "b"], [0.0, 0.0], [0.0, 0.0])
    arms.sent(left, "m1", ["a", "b"], 10.0, hold, path=line(([1.0, 1.0], 10.0)))
    arms.sent(left, "m2", ["a"], 10.0, hold, path=line(([-1.0], 10.0)))
    clock.t += MAX_AGE_S + 0.1
    whys = not_held(arms, left)
    assert len(whys) == 2 and all("another trajectory of ours names 'a'" in why for why in whys)


def test_a_late_arm_another_trajectory_of_ours_went_to_is_not_held(
        positions: JointPositions, clock: Clock) -> None:
    # m2 names 'b' alone, on the same controller: one that takes partial goals holds 'a'
    # where it is then (m1 stops), one that does not refuses m2 (m1 runs on). Another arm
    # (its own topic and joints) has no rival.
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    left, right = Topic("/left"), Topic("/right")
    positions.heard(["a", "b", "c"], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    arms.sent(left, "m1", ["a"], 10.0, hold, path=line(([1.0], 10.0)))
    arms.sent(left, "m2", ["b"], 10.0, hold, path=line(([1.0], 10.0)))
    arms.sent(right, "m3", ["c"], 10.0, hold, path=line(([1.0], 10.0)))
    clock.t += MAX_AGE_S + 0.1
    held = arms.hold_all()
    assert held.held == ("/right",) and held.at_desired == ("/right",) and left.sent == []
    assert len(held.not_held) == 2
    assert all("another trajectory of ours went to /left" in why for why in held.not_held)


def test_a_trajectory_sent_without_its_points_is_held_only_where_measured(
        positions: JointPositions, clock: Clock) -> None:
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    left = Topic("/left")
    positions.heard(["a"], [0.0], [0.0])
    arms.sent(left, "m1", ["a"], 10.0, hold)
    clock.t += MAX_AGE_S + 0.1
    (why,) = arms.hold_all().not_held
    assert "no trajectory is known to tell where its controller drives it" in why


def test_only_age_is_worked_around(positions: JointPositions, clock: Clock) -> None:
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    left = Topic("/left")
    # Never heard: no start, nothing to follow.
    arms.sent(left, "m0", ["x"], 10.0, hold, path=line(([1.0], 10.0)))
    clock.t += MAX_AGE_S + 0.1
    unheard = positions.now(["x"], 2.0)
    assert isinstance(unheard, Unknown) and unheard.missing is Missing.UNHEARD
    assert arms.hold_all().not_held == (
        "the arm on /left was not held: no joint_states heard for 'x'",)
    # Not finite, and late too: the non-finite position is the reason.
    positions.heard(["n"], [0.0], [0.0])
    arms.sent(Topic("/n"), "m1", ["n"], 10.0, hold, path=line(([1.0], 10.0)))
    positions.heard(["n"], [math.nan], [0.0])
    clock.t += MAX_AGE_S + 0.1
    not_finite = positions.now(["n"], 2.0)
    assert isinstance(not_finite, Unknown) and not_finite.missing is Missing.NOT_FINITE
    assert "the arm on /n was not held: joint_states gave 'n' the position nan" in (
        arms.hold(["m1"]).not_held)


def test_a_late_arm_whose_senders_disagreed_before_they_went_quiet_is_not_held(
        positions: JointPositions, clock: Clock) -> None:
    # The robot's broadcaster and a joint_state_publisher (its zeros), then both silent: the
    # last sample is either's, so whether the arm followed the trajectory is not known.
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    left = Topic("/left")
    positions.heard(["a"], [0.25], [0.0], sender=1)
    arms.sent(left, "m1", ["a"], 10.0, hold, path=line(([0.25], 10.0)))
    clock.t += 0.02
    positions.heard(["a"], [0.0], [], sender=2)
    clock.t += MAX_AGE_S + 0.1
    disagree = positions.now(["a"], 2.0)
    assert isinstance(disagree, Unknown) and disagree.missing is Missing.DISAGREE
    (why,) = arms.hold_all().not_held
    assert "joint_states senders disagree on 'a': 0.250 and 0.000" in why
    assert left.sent == []


@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_a_hold_at_the_desired_state_lies_on_the_approved_path(data: st.DataObject) -> None:
    # Positions-only: each joint's hold is between its lowest and highest of the start and
    # the points, whenever the stop comes (before the start, between points, after the end),
    # the arm last heard where the trajectory had it some time before. Not held there only
    # when that sample could as well be of an arm standing where it started.
    clock = Clock()
    positions = JointPositions(clock)
    arms = ArmHolds(positions, max_age_s=3600.0, monotonic=clock)
    joints = data.draw(st.integers(1, 3))
    value = st.floats(-10.0, 10.0, allow_nan=False)
    start = data.draw(st.lists(value, min_size=joints, max_size=joints))
    gaps = data.draw(st.lists(st.floats(0.01, 5.0), min_size=1, max_size=5))
    times = [sum(gaps[:i + 1]) for i in range(len(gaps))]
    points = [PathPoint(tuple(data.draw(st.lists(value, min_size=joints, max_size=joints))),
                        None, t) for t in times]
    names = [f"j{i}" for i in range(joints)]
    positions.heard(names, start, [0.0] * joints)
    left = Topic("/left")
    arms.sent(left, "m1", names, times[-1], hold, path=points)
    stop_s = data.draw(st.floats(MAX_AGE_S + 0.01, times[-1] + SETTLING_S / 2))  # still due
    heard_s = data.draw(st.floats(0.0, stop_s - MAX_AGE_S - 0.01))
    clock.t += heard_s
    positions.heard(names, DesiredPath(start, None, points).at(heard_s), [])
    clock.t += stop_s - heard_s
    held = arms.hold_all()
    event("not held: the sample cannot tell" if held.not_held else "held where it has it")
    if held.not_held:
        (why,) = held.not_held
        assert "cannot tell it following its trajectory from standing where it was" in why
        return
    assert held.at_desired == ("/left",)
    ((_, where),) = left.sent
    for j, at in enumerate(where):
        along = [start[j], *(p.positions[j] for p in points)]
        assert min(along) - 1e-9 <= at <= max(along) + 1e-9, (where, start, points)


# -- what a late arm's last samples must show before it is held where its trajectory has it --
def test_a_late_arm_heard_where_it_stood_when_sent_is_not_held_where_its_trajectory_has_it(
        positions: JointPositions, clock: Clock) -> None:
    # 0 → 1 rad over 2 s (0.5 rad/s); heard 0.3 s in still at 0 — an arm standing where it
    # was (the controller refused the trajectory) and an arm following it look alike then:
    # the trajectory had moved it 0.15, less than the tracking tolerance. A hold at where
    # the trajectory has it now (0.45) would move an arm that never moved.
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    left = stale_after(arms, positions, clock, 0.3, [0.0], line(([1.0], 2.0)))
    (why,) = not_held(arms, left)
    assert arms.running() == ["m1"]
    assert "cannot tell it following its trajectory from standing where it was" in why


def test_a_late_arm_unheard_since_its_trajectory_went_out_is_not_held_where_it_has_it(
        positions: JointPositions, clock: Clock) -> None:
    # Heard at rest as it went out, then nothing: no sample says the controller runs it.
    arms = ArmHolds(positions, max_age_s=5.0, monotonic=clock)
    left = Topic("/left")
    positions.heard(["a"], [0.0], [0.0])
    arms.sent(left, "m1", ["a"], 2.0, hold, path=line(([1.0], 2.0)))
    clock.t += 1.5
    not_held(arms, left)


def test_a_large_velocity_does_not_make_any_late_sample_look_like_tracking(
        positions: JointPositions, clock: Clock) -> None:
    # A last point moving 1000 rad/s (jazzy's controller refuses it by default:
    # allow_nonzero_velocity_at_trajectory_end) makes the tracking tolerance 500 rad; the
    # arm heard standing at 0, 5.4 s in. Its cubic has the arm near -160 rad 6 s in.
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    points = [PathPoint((0.5,), (0.0,), 5.0), PathPoint((1.0,), (1000.0,), 10.0)]
    left = stale_after(arms, positions, clock, 5.4, [0.0], points)
    not_held(arms, left)


def test_a_late_hold_that_hardly_moves_the_arm_needs_no_more_evidence(
        positions: JointPositions, clock: Clock) -> None:
    # Where the trajectory has it now is within MAX_LEAD of where it was last heard: no
    # longer a move than a hold where measured may make.
    arms = ArmHolds(positions, max_age_s=2.0, monotonic=clock)
    left = stale_after(arms, positions, clock, 0.3, [0.0], line(([1.0], 20.0)))
    assert arms.hold_all().at_desired == ("/left",)
    ((_, (at,)),) = left.sent
    assert at == pytest.approx(0.05 * (0.3 + MAX_AGE_S + 0.1))


def test_a_trajectory_the_path_cannot_be_worked_out_for_does_not_break_a_stop(
        positions: JointPositions, clock: Clock) -> None:
    # A first point 5e-324 s in (valid: its time is > 0) with velocities, from a start whose
    # velocities were heard: its cubic's coefficients divide by the segment's time squared,
    # 0.0 in floats. With the arm's joint_states late the stop works that out; it must not
    # raise out of the stop, which would leave the other arm (and the goal cancels) undone,
    # nor log a traceback (it did: ZeroDivisionError): such a segment's speed is unbounded.
    arms = ArmHolds(positions, max_age_s=5.0, monotonic=clock)
    left, right = Topic("/left"), Topic("/right")
    positions.heard(["a"], [0.0], [0.0])
    arms.sent(left, "m1", ["a"], 10.0, hold,
              path=[PathPoint((1.0,), (0.0,), 5e-324), PathPoint((2.0,), None, 10.0)])
    clock.t += 1.0
    positions.heard(["b"], [0.5], [0.0])
    arms.sent(right, "m2", ["b"], 10.0, hold)
    held = arms.hold_all()
    assert held.held == ("/right",) and right.sent == [(["b"], [0.5])]
    (why,) = held.not_held
    assert why.startswith("the arm on /left was not held: ") and left.sent == []
    assert why.endswith("its trajectory's peak speed is not finite: where it has the arm "
                        "cannot be checked")
    assert arms.running() == ["m1"]  # the next stop tries again


def test_a_late_arm_whose_trajectory_may_have_been_refused_for_the_one_before_is_not_held(
        positions: JointPositions, clock: Clock) -> None:
    # m1: 0 → 2 rad over 4 s (0.5 rad/s). 1 s in, m2 for the same joint goes out: on at the
    # same speed to 1.5 at 2 s, then back to 0 — its last point still moving, which jazzy's
    # controller refuses: m1 runs on. The arm heard 1.8 s into m2 at 1.4 follows either.
    # Then late: 3.5 s into m2, m1 has it at 2.0, m2 at 0.28 — a hold there is a 1.7 rad
    # step back for an arm on its way to 2.0.
    arms = ArmHolds(positions, max_age_s=5.0, monotonic=clock)
    left = Topic("/left")
    positions.heard(["a"], [0.0], [0.0])
    arms.sent(left, "m1", ["a"], 4.0, hold, path=line(([2.0], 4.0)))
    clock.t += 1.0
    positions.heard(["a"], [0.5], [0.5])
    arms.sent(left, "m2", ["a"], 4.0, hold,
              path=[PathPoint((1.5,), (0.5,), 2.0), PathPoint((0.0,), (-0.01,), 4.0)])
    clock.t += 1.8
    positions.heard(["a"], [1.4], [0.5])
    clock.t += 1.7
    (why,) = not_held(arms, left)
    assert "cannot tell it from a trajectory of ours it replaced" in why


def test_a_late_arm_heard_following_the_trajectory_that_replaced_another_is_held_there(
        positions: JointPositions, clock: Clock) -> None:
    # m2 turns the arm back 1 s into m1; heard 1.5 s in on m2's way, far off m1's: the
    # controller took m2. Late, it is held where m2 has it (its end, -0.5).
    arms = ArmHolds(positions, max_age_s=5.0, monotonic=clock)
    left = Topic("/left")
    positions.heard(["a"], [0.0], [0.0])
    arms.sent(left, "m1", ["a"], 4.0, hold, path=line(([2.0], 4.0)))
    clock.t += 1.0
    positions.heard(["a"], [0.5], [0.5])
    arms.sent(left, "m2", ["a"], 2.0, hold, path=line(([-0.5], 2.0)))
    clock.t += 1.5
    positions.heard(["a"], [-0.25], [-0.5])
    clock.t += 0.6
    assert arms.hold_all().at_desired == ("/left",)
    assert left.sent == [(["a"], [-0.5])]


def test_a_hold_where_its_trajectory_has_the_arm_is_never_a_non_finite_position(
        positions: JointPositions, clock: Clock) -> None:
    # A joint_states sender gives the joint 1e308 rad/s as the trajectory goes out (finite:
    # taken), then positions along the cubic that starts that fast: 2 s in, the cubic has it
    # at inf. A measured hold is never made at a non-finite position; nor is this one.
    arms = ArmHolds(positions, max_age_s=5.0, monotonic=clock)
    left = Topic("/left")
    positions.heard(["a"], [0.0], [1e308])
    arms.sent(left, "m1", ["a"], 100.0, hold, path=[PathPoint((1.0,), (0.0,), 100.0)])
    clock.t += 1.0
    positions.heard(["a"], [9.801e307], [1e308])
    clock.t += 1.0
    (why,) = not_held(arms, left)
    assert "not finite" in why


def test_a_late_arm_standing_short_of_its_carried_forward_start_is_not_held_at_desired(
        positions: JointPositions, clock: Clock) -> None:
    # Heard at 0 moving 1 rad/s 0.2 s before the trajectory went out: its start is carried
    # forward to 0.1 (MAX_LEAD). The controller refused the trajectory (0.1 → -2 over 4 s)
    # and the arm stands at 0: 0.8 s in, the trajectory has it at -0.32, farther from its
    # start than the tolerance (0.3625), and 0 is within the tolerance of it. Standing
    # short of that start by up to MAX_LEAD is no sign of following it.
    arms = ArmHolds(positions, max_age_s=5.0, monotonic=clock)
    left = Topic("/left")
    positions.heard(["a"], [0.0], [1.0])
    clock.t += 0.2
    arms.sent(left, "m1", ["a"], 4.0, hold, path=line(([-2.0], 4.0)))
    clock.t += 0.8
    positions.heard(["a"], [0.0], [0.0])
    clock.t += MAX_AGE_S + 0.1
    not_held(arms, left)
