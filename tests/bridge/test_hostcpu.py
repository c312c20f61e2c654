"""STATUS's §20 `cpu_percent` (issue 24): the host's non-idle share between two readings of
/proc/stat, taken at most once per interval."""

from __future__ import annotations

from pathlib import Path

from rcan_rtps.bridge.hostcpu import CpuMeter


def _stat(path: Path, user: int, idle: int, iowait: int = 0) -> None:
    # cpu user nice system idle iowait irq softirq steal guest guest_nice
    path.write_text(f"cpu  {user} 0 0 {idle} {iowait} 0 0 0 7 0\ncpu0 1 2 3 4\n")


def test_the_share_of_busy_time_since_the_last_reading(tmp_path: Path) -> None:
    stat, now = tmp_path / "stat", [0.0]
    _stat(stat, user=100, idle=100)
    meter = CpuMeter(path=stat, min_interval_s=1.0, monotonic=lambda: now[0])
    assert meter.percent() is None  # one reading: no figure yet
    _stat(stat, user=130, idle=160, iowait=10)  # +30 busy, +70 idle and iowait
    assert meter.percent() is None  # not a second later
    now[0] = 1.0
    assert meter.percent() == 30.0
    _stat(stat, user=230, idle=160, iowait=10)
    now[0] = 1.5
    assert meter.percent() == 30.0  # the last figure until the interval has passed
    now[0] = 2.0
    assert meter.percent() == 100.0


def test_no_proc_stat_no_figure(tmp_path: Path) -> None:
    now = [0.0]
    meter = CpuMeter(path=tmp_path / "none", monotonic=lambda: now[0])
    now[0] = 5.0
    assert meter.percent() is None


def test_on_this_machine_a_figure_in_range() -> None:
    now = [0.0]
    meter = CpuMeter(monotonic=lambda: now[0])
    now[0] = 1.0
    value = meter.percent()
    assert value is None or 0.0 <= value <= 100.0
