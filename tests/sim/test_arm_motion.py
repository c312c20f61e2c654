"""The simulated arm follows every point of a trajectory, each at its time."""

from __future__ import annotations

import pytest

from rcan_rtps.sim.robot import _ArmMotion


def test_the_arm_passes_each_point_at_its_time() -> None:
    motion = _ArmMotion([(0.0, [0.0]), (1.0, [1.0]), (3.0, [0.0])], began=0.0)
    assert motion.at(0.5) == ([0.5], [1.0], False)
    assert motion.at(1.0)[0] == [1.0]
    positions, velocities, finished = motion.at(2.0)
    assert positions == [pytest.approx(0.5)] and velocities == [-0.5] and not finished
    assert motion.at(3.0) == ([0.0], [0.0], True)
    assert motion.at(99.0) == ([0.0], [0.0], True)
