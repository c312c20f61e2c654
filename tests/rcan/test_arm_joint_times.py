"""`arm_joint`'s point times as the controller gets them: whole nanoseconds.

A time is sent as builtin_interfaces/Duration (sec, nanosec). Rounding only the fraction once
sent 0.9999999999 s as 0 s — a point meant to be reached after a second was due at once, and
1.9999999999 s as 1 s. Times that round to the same nanosecond are one instant to the
controller: refused, so the bridge's model of a trajectory (a stop's hold) is what it runs.
"""

from __future__ import annotations

import math

import msgspec
import pytest
from hypothesis import given
from hypothesis import strategies as st

from rcan_rtps.rcan.actions.arm_joint import ArmJointParams, trajectory
from rcan_rtps.ros.rostime import duration_msg


def _sent(seconds: float) -> dict[str, int]:
    params = ArmJointParams(joints=["elbow"], positions=[0.5], duration_s=seconds)
    (point,) = trajectory(params, kit=None)["points"]  # type: ignore[arg-type]
    time: dict[str, int] = point["time_from_start"]
    return time


@pytest.mark.parametrize(("seconds", "sent"), [
    (0.9999999999, {"sec": 1, "nanosec": 0}),
    (1.9999999999, {"sec": 2, "nanosec": 0}),
    (2.5, {"sec": 2, "nanosec": 500_000_000}),
    (1e-9, {"sec": 0, "nanosec": 1}),
    (3600.0, {"sec": 3600, "nanosec": 0}),
])
def test_a_time_is_sent_as_its_nearest_nanosecond(seconds: float,
                                                  sent: dict[str, int]) -> None:
    assert _sent(seconds) == sent
    assert duration_msg(seconds) == sent  # the simulator's durations alike


@given(st.floats(min_value=1e-9, max_value=3600.0))
def test_a_sent_time_is_never_more_than_half_a_nanosecond_off(seconds: float) -> None:
    sent = _sent(seconds)
    assert 0 <= sent["nanosec"] < 1_000_000_000
    assert math.isclose(sent["sec"] + sent["nanosec"] / 1e9, seconds, rel_tol=0,
                        abs_tol=0.5e-9 + seconds * 1e-15)


@pytest.mark.parametrize("times", [[4e-10], [1.0, 1.0000000001], [5e-324, 1.0]])
def test_times_one_instant_when_sent_are_refused(times: list[float]) -> None:
    points = [{"positions": [0.1], "time_from_start_s": t} for t in times]
    with pytest.raises(msgspec.ValidationError, match="at least 1 ns"):
        msgspec.convert({"joints": ["elbow"], "points": points}, ArmJointParams)
