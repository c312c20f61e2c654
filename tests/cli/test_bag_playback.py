"""`bag play` timing, decided without a clock: when each message is due."""

from __future__ import annotations

import pytest

from rcan_rtps.cli.bag_cmd import playback
from rcan_rtps.ros.bag import BagMessage

S = 1_000_000_000


def _bag(*seconds: float) -> list[BagMessage]:
    return [BagMessage("/t", "std_msgs/msg/String", round(s * S), b"") for s in seconds]


def test_recorded_gaps_are_kept() -> None:
    due = [offset for offset, _ in playback(_bag(10.0, 10.25, 10.35, 10.8), 10 * S, None, 1.0)]
    assert due == pytest.approx([0.0, 0.25, 0.35, 0.8])


def test_rate_divides_the_gaps() -> None:
    due = [offset for offset, _ in playback(_bag(0.0, 0.5, 1.3), 0, None, 2.0)]
    assert due == pytest.approx([0.0, 0.25, 0.65])
    slow = [offset for offset, _ in playback(_bag(0.0, 0.5), 0, None, 0.5)]
    assert slow == pytest.approx([0.0, 1.0])


def test_the_window_skips_before_and_stops_after() -> None:
    played = list(playback(_bag(0.0, 1.0, 2.0, 3.0, 4.0), 1 * S, 3 * S, 1.0))
    assert [(offset, m.log_time_ns // S) for offset, m in played] == [(0.0, 1), (1.0, 2),
                                                                      (2.0, 3)]
