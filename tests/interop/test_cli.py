"""The ros2cli-shaped commands as subprocesses against a real rclpy Jazzy graph (on Fast DDS;
the graph views and topic pub/echo on Cyclone DDS too)."""

from __future__ import annotations

import asyncio
import json
import math
import os
import re
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from oracle.client import OracleEnv, RclpyOracle, both_rmws
from waiting import SPIN, eventually_sync


def cli(domain_id: int, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    return subprocess.run([sys.executable, "-m", "rcan_rtps", *args], capture_output=True,
                          text=True, env=env, timeout=timeout)


def cli_start(domain_id: int, *args: str) -> subprocess.Popen[str]:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    return subprocess.Popen([sys.executable, "-m", "rcan_rtps", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


@pytest.fixture
def oracle(jazzy_oracle: OracleEnv, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_oracle, "talker", "/demo", domain_id=domain_id) as agent:
        yield agent


VENDOR_OF_RMW = {"fastrtps": "eProsima Fast DDS", "cyclonedds": "Eclipse Cyclone DDS"}


@both_rmws
def test_topic_list_node_list_and_info_show_the_rclpy_graph(oracle: RclpyOracle,
                                                           domain_id: int) -> None:
    oracle.call("publisher", topic="/demo/chatter", type="std_msgs/msg/String")
    oracle.call("subscribe", topic="/demo/odom", type="nav_msgs/msg/Odometry", qos="sensor")
    listing = cli(domain_id, "topic", "list", "-t", *SPIN)
    assert listing.returncode == 0, listing.stderr
    assert "/demo/chatter [std_msgs/msg/String]" in listing.stdout.splitlines()
    assert "/demo/odom [nav_msgs/msg/Odometry]" in listing.stdout.splitlines()

    nodes = cli(domain_id, "node", "list", *SPIN)
    assert "/demo/talker" in nodes.stdout.splitlines()
    assert not any("_rcan_rtps_cli" in line for line in nodes.stdout.splitlines())

    info = cli(domain_id, "topic", "info", "/demo/odom", "-v", *SPIN)
    assert info.returncode == 0, info.stderr
    out = info.stdout
    assert "Type: nav_msgs/msg/Odometry" in out
    assert "Subscription count: 1" in out
    assert "Node name: talker" in out and "Node namespace: /demo" in out
    assert f"DDS vendor: {VENDOR_OF_RMW[oracle.rmw]}" in out
    assert "Reliability: BEST_EFFORT" in out
    assert "RIHS01_" in out


@both_rmws
def test_topic_pub_reaches_rclpy(oracle: RclpyOracle, domain_id: int) -> None:
    oracle.call("subscribe", topic="/cmd_vel", type="geometry_msgs/msg/Twist")
    done = cli(domain_id, "topic", "pub", "--once", "/cmd_vel", "geometry_msgs/msg/Twist",
               "{linear: {x: 0.2}, angular: {z: -0.1}}")
    assert done.returncode == 0, done.stderr
    got = eventually_sync(lambda: oracle.call("take", topic="/cmd_vel"),
                          what="a Twist on /cmd_vel")
    assert got and got[0]["linear"]["x"] == 0.2 and got[0]["angular"]["z"] == -0.1


@both_rmws
def test_topic_echo_resolves_the_type_from_the_graph(oracle: RclpyOracle,
                                                     domain_id: int) -> None:
    oracle.call("publisher", topic="/demo/status", type="std_msgs/msg/String")
    echo = cli_start(domain_id, "topic", "echo", "/demo/status", "--count", "2", "--json",
                     "--timeout", "30")
    try:
        deadline = time.monotonic() + 30
        while echo.poll() is None and time.monotonic() < deadline:
            oracle.call("publish", topic="/demo/status", type="std_msgs/msg/String",
                        value={"data": "ok"}, count=2, period=0.1)
        out, err = echo.communicate(timeout=30)
    finally:
        echo.kill()
    assert echo.returncode == 0, err
    assert out.splitlines()[:2] == ['{"data": "ok"}', '{"data": "ok"}']


def test_topic_echo_json_is_strict_json_for_non_finite_floats(oracle: RclpyOracle,
                                                               domain_id: int) -> None:
    oracle.call("publisher", topic="/demo/odd", type="geometry_msgs/msg/Vector3")
    echo = cli_start(domain_id, "topic", "echo", "/demo/odd", "--once", "--json",
                     "--timeout", "30")
    try:
        deadline = time.monotonic() + 30
        while echo.poll() is None and time.monotonic() < deadline:
            oracle.call("publish", topic="/demo/odd", type="geometry_msgs/msg/Vector3",
                        value={"x": math.nan, "y": math.inf, "z": -math.inf}, count=2,
                        period=0.1)
        out, err = echo.communicate(timeout=30)
    finally:
        echo.kill()
    assert echo.returncode == 0, err

    def refuse(constant: str) -> None:
        raise AssertionError(f"bare {constant} is not JSON")

    assert json.loads(out.splitlines()[0], parse_constant=refuse) == {
        "x": "NaN", "y": "Infinity", "z": "-Infinity"}


def test_topic_hz_measures_a_rate(oracle: RclpyOracle, domain_id: int) -> None:
    oracle.call("publisher", topic="/tick", type="std_msgs/msg/Empty")
    hz = cli_start(domain_id, "topic", "hz", "/tick", "std_msgs/msg/Empty", "--duration", "4")
    try:
        # Through all of hz's 4 s, which start once it subscribed: on a busy machine that can
        # be after a fixed burst of messages has long been sent.
        deadline, published = time.monotonic() + 60, 0
        while hz.poll() is None and time.monotonic() < deadline:
            oracle.call("publish", topic="/tick", type="std_msgs/msg/Empty", value={}, count=10,
                        period=0.05, timeout=60)
            published += 10
        out, err = hz.communicate(timeout=30)
    finally:
        hz.kill()
    assert hz.returncode == 0, err
    # The rate's arithmetic is checked on stamps of our own (tests/cli/test_measure.py); here:
    # rclpy's messages were received and reported, whatever this machine's speed.
    reports = re.findall(r"average rate: ([\d.]+)\n\tmin: [\d.]+s max: [\d.]+s "
                         r"std dev: [\d.]+s window: (\d+)", out)
    assert reports and all(float(rate) > 0 for rate, _ in reports)
    # Never more in a window than rclpy sent (the count, not this machine's speed, bounds it).
    assert 2 <= max(int(window) for _, window in reports) <= published, (published, out)


def test_bad_values_name_the_field_path(domain_id: int) -> None:
    done = cli(domain_id, "topic", "pub", "--once", "-w", "0", "/x", "geometry_msgs/msg/Twist",
               "{linear: {x: fast}}")
    assert done.returncode != 0
    assert "linear.x" in done.stderr and "Traceback" not in done.stderr
    done = cli(domain_id, "topic", "pub", "--once", "-w", "0", "/x", "sensor_msgs/msg/JointState",
               "{name: [a, 3]}")
    assert done.returncode != 0 and "name[1]" in done.stderr
    done = cli(domain_id, "topic", "pub", "--once", "-w", "0", "/x", "geometry_msgs/msg/Twist",
               "{linear: [}")
    assert done.returncode != 0 and "YAML" in done.stderr and "Traceback" not in done.stderr


def test_unknown_type_suggests_and_fails(domain_id: int) -> None:
    done = cli(domain_id, "interface", "show", "sensor_msgs/msg/JointStat")
    assert done.returncode != 0
    assert "sensor_msgs/msg/JointState" in done.stderr and "Traceback" not in done.stderr


def test_interface_hash_prints_exactly_the_hash(domain_id: int) -> None:
    done = cli(domain_id, "interface", "hash", "std_msgs/msg/String")
    assert done.stdout == \
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18\n"


def test_malformed_idl_on_the_path_names_file_and_line(tmp_path: Path, domain_id: int) -> None:
    bad = tmp_path / "my_msgs" / "msg"
    bad.mkdir(parents=True)
    (bad / "Broken.idl").write_text("module my_msgs {\n  module msg {\n"
                                    "    struct Broken {\n      double x\n    };\n  };\n};\n")
    done = cli(domain_id, "--idl-path", str(tmp_path), "interface", "show", "my_msgs/msg/Broken")
    assert done.returncode != 0
    assert "Broken.idl:5" in done.stderr and "expected ';'" in done.stderr
    assert "Traceback" not in done.stderr


async def test_cli_does_not_hang_without_a_graph(domain_id: int) -> None:
    done = await asyncio.to_thread(cli, domain_id, "topic", "echo", "/nothing", "--timeout", "1")
    assert done.returncode != 0 and "no publisher" in done.stderr
