"""`topic bw`, `topic delay` and the `topic echo` flags against rclpy Jazzy publishers."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from oracle.client import RclpyOracle

ODOM = "nav_msgs/msg/Odometry"
ODOM_VALUE = {"header": {"frame_id": "odom"}, "child_frame_id": "base_link",
              "pose": {"pose": {"position": {"x": 1.5, "y": -2.0}}}}


def cli(domain_id: int, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    return subprocess.run([sys.executable, "-m", "rcan_rtps", *args], capture_output=True,
                          text=True, env=env, timeout=timeout)


@pytest.fixture
def oracle(jazzy_python: Path, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_python, "talker", "/demo", domain_id=domain_id) as agent:
        yield agent


@pytest.fixture
def odom(oracle: RclpyOracle) -> Iterator[float]:
    """/odom published at 20 Hz, stamped with the publisher's clock; gives the wall-clock
    time (this host's, as the stamps are) just before the first stamp."""
    oracle.call("publisher", topic="/odom", type=ODOM, qos="sensor")
    since = time.time()
    oracle.call("publish_periodic", topic="/odom", type=ODOM, value=ODOM_VALUE, rate=20.0,
                stamp=True)
    yield since
    oracle.call("stop_periodic", topic="/odom")


def test_bw_reports_the_serialized_size_rclpy_sends(oracle: RclpyOracle,
                                                    domain_id: int) -> None:
    value = {"data": "x" * 1000}
    size = len(oracle.call("serialize", type="std_msgs/msg/String", value=value)) // 2
    oracle.call("publisher", topic="/big", type="std_msgs/msg/String")
    oracle.call("publish_periodic", topic="/big", type="std_msgs/msg/String", value=value,
                rate=20.0)
    try:
        done = cli(domain_id, "topic", "bw", "/big", "-w", "50", "--duration", "4")
    finally:
        oracle.call("stop_periodic", topic="/big")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("Subscribed to [/big]\n")
    last = re.findall(r"([\d.]+) KB/s from (\d+) messages\n\tMessage size mean: ([\d.]+) KB "
                      r"min: ([\d.]+) KB max: ([\d.]+) KB", done.stdout)[-1]
    rate, count, mean, low, high = float(last[0]), int(last[1]), *map(float, last[2:])
    # The rate's arithmetic is checked with a clock of our own (tests/cli/test_measure.py);
    # here: rclpy's messages were counted, and at their size on the wire.
    assert rate > 0.0 and 2 <= count <= 50
    assert mean == low == high == round(size / 1000, 2)


def test_delay_measures_header_stamps(odom: float, domain_id: int) -> None:
    done = cli(domain_id, "topic", "delay", "/odom", "--duration", "4")
    ended = time.time()
    assert done.returncode == 0, done.stderr
    found = re.findall(r"average delay: ([\d.-]+)\n\tmin: ([\d.-]+)s max: ([\d.-]+)s "
                       r"std dev: ([\d.]+)s window: (\d+)", done.stdout)
    assert found, done.stdout
    average, low, high, _, window = found[-1]
    # Stamps of this host's clock: no delay is negative, and none is longer than /odom has
    # been published (one from another clock or epoch would be; no speed is assumed).
    assert 0.0 <= float(low) <= float(average) <= float(high) <= ended - odom
    assert int(window) >= 10


def test_delay_refuses_a_type_without_header(oracle: RclpyOracle, domain_id: int) -> None:
    done = cli(domain_id, "topic", "delay", "/x", "std_msgs/msg/String", "--duration", "1")
    assert done.returncode != 0
    assert "no 'header' field" in done.stderr and "Traceback" not in done.stderr


def test_echo_field_csv_and_no_arr(odom: float, domain_id: int) -> None:
    position = cli(domain_id, "topic", "echo", "/odom", "--once", "--timeout", "20",
                   "--field", "pose.pose.position", "--csv")
    assert position.returncode == 0, position.stderr
    assert position.stdout == "1.5,-2.0,0.0\n"

    frame = cli(domain_id, "topic", "echo", "/odom", "--once", "--timeout", "20",
                "--field", "child_frame_id")
    assert frame.stdout == "base_link\n---\n", frame.stderr

    whole = cli(domain_id, "topic", "echo", "/odom", "--once", "--timeout", "20", "--no-arr")
    assert whole.returncode == 0, whole.stderr
    assert "covariance: '<array type: double[36]>'" in whole.stdout
    assert "child_frame_id: base_link" in whole.stdout

    row = cli(domain_id, "topic", "echo", "/odom", "--once", "--timeout", "20", "--csv",
              "--no-arr").stdout.strip().split(",")
    # header (sec, nanosec, frame_id), child_frame_id, position, orientation, covariance …
    assert row[2:7] == ["odom", "base_link", "1.5", "-2.0", "0.0"]
    assert "<array type: double[36]>" in row


def test_echo_bad_field_fails_before_listening(odom: RclpyOracle, domain_id: int) -> None:
    done = cli(domain_id, "topic", "echo", "/odom", "--once", "--field", "pose.nope")
    assert done.returncode != 0
    assert "has no field 'nope'" in done.stderr and "Traceback" not in done.stderr


def test_echo_qos_flags_choose_the_subscription_qos(odom: RclpyOracle, domain_id: int) -> None:
    fits = cli(domain_id, "topic", "echo", "/odom", "--once", "--timeout", "20", "--field",
               "header.frame_id", "--qos-reliability", "best_effort", "--qos-durability",
               "volatile", "--qos-depth", "5", "--qos-history", "keep_last")
    assert fits.stdout == "odom\n---\n", fits.stderr
    profile = cli(domain_id, "topic", "echo", "/odom", "--once", "--timeout", "20", "--field",
                  "header.frame_id", "--qos-profile", "sensor_data")
    assert profile.stdout == "odom\n---\n", profile.stderr
    # A reliable reader never matches the best-effort publisher: nothing arrives.
    strict = cli(domain_id, "topic", "echo", "/odom", "--once", "--timeout", "3",
                 "--qos-reliability", "reliable")
    assert strict.returncode != 0 and strict.stdout == ""
