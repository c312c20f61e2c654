"""`topic bw` arithmetic with a clock the test moves."""

from __future__ import annotations

import pytest

from rcan_rtps.cli._measure import BandwidthWindow
from rcan_rtps.cli.topic_cmd import _report_rate


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_bandwidth_over_the_window_in_ros2_units() -> None:
    clock = Clock()
    window = BandwidthWindow(3, clock=clock)
    window.add_size(1000)
    assert window.report() is None  # one message says nothing about a rate
    for size in (1000, 3000, 2000):  # the first falls out of a window of 3
        clock.now += 0.5
        window.add_size(size)
    clock.now += 0.5
    # 6000 bytes since the oldest kept message arrived, 1.5 s ago
    assert window.report() == ("4.00 KB/s from 3 messages\n"
                               "\tMessage size mean: 2.00 KB min: 1.00 KB max: 3.00 KB")


def test_slow_topics_are_in_bytes() -> None:
    clock = Clock()
    window = BandwidthWindow(10, clock=clock)
    window.add_size(10)
    clock.now += 1.0
    window.add_size(30)
    clock.now += 1.0
    assert window.report() == ("20 B/s from 2 messages\n"
                               "\tMessage size mean: 20 B min: 10 B max: 30 B")


def test_hz_reports_the_mean_rate_and_gaps_of_its_stamps(
        capsys: pytest.CaptureFixture[str]) -> None:
    _report_rate([10.0, 10.05, 10.15, 10.2])  # gaps 0.05, 0.1, 0.05: mean 1/15 s
    assert capsys.readouterr().out == ("average rate: 15.000\n\tmin: 0.050s max: 0.100s "
                                       "std dev: 0.02357s window: 4\n")
    _report_rate([3.0])
    assert capsys.readouterr().out == "no new messages\n"
