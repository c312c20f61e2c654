"""`commands.Halted.result`: what a stop answers, from what its halt reached."""

from __future__ import annotations

from rcan_rtps.bridge.commands import Halted
from rcan_rtps.governance import ArmsHeld

NOT_HELD = ArmsHeld(not_held=("the arm on /arm was not held: joint_states for 'elbow' "
                              "last heard 0.76 s ago",))


def test_a_stop_that_could_not_hold_a_moving_arm_fails_naming_it() -> None:
    result = Halted(reached=True, cancelled=1, arms=NOT_HELD).result("/cmd_vel")
    assert not result.ok and result.detail == NOT_HELD.not_held[0]


def test_an_estop_the_robot_was_told_of_stands_though_an_arm_was_not_held() -> None:
    # The robot's own e-stop stops its arm; the bridge's hold is its second measure.
    assert Halted(reached=True, cancelled=0, arms=NOT_HELD).result("/estop", told=True).ok
    untold = Halted(reached=True, cancelled=0, arms=NOT_HELD).result("/estop", told=False)
    assert not untold.ok and "not held" in (untold.detail or "")


def test_a_stop_that_reached_nothing_fails() -> None:
    result = Halted(reached=False, cancelled=0, arms=ArmsHeld()).result("/cmd_vel")
    assert (result.ok, result.detail) == (False, "no subscriber on /cmd_vel")
    assert Halted(reached=False, cancelled=0, arms=ArmsHeld(held=("/arm",))).result("/c").ok
