"""`rcan-rtps param …` against an rclpy Jazzy node's rcl_interfaces parameter services."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from oracle.client import RclpyOracle
from waiting import SPIN


def cli(domain_id: int, *args: str, timeout: float = 90) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    return subprocess.run([sys.executable, "-m", "rcan_rtps", *args], capture_output=True,
                          text=True, env=env, timeout=timeout)


@pytest.fixture
def oracle(jazzy_python: Path, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_python, "tuned", "/demo", domain_id=domain_id) as agent:
        agent.call("declare_parameter", name="max_speed", value=0.5)
        agent.call("declare_parameter", name="robot.name", value="rover")
        agent.call("declare_parameter", name="wheels", value=[1, 2, 3, 4])
        agent.call("declare_parameter", name="enabled", value=True)
        yield agent


def test_param_list_get_set_dump(oracle: RclpyOracle, domain_id: int) -> None:
    listing = cli(domain_id, "param", "list", "/demo/tuned")
    assert listing.returncode == 0, listing.stderr
    names = listing.stdout.splitlines()
    for name in ("max_speed", "robot.name", "wheels", "enabled", "use_sim_time"):
        assert f"  {name}" in names

    got = cli(domain_id, "param", "get", "/demo/tuned", "max_speed")
    assert got.returncode == 0, got.stderr
    assert got.stdout.strip() == "Double value is: 0.5"
    assert cli(domain_id, "param", "get", "/demo/tuned", "enabled").stdout.strip() == \
        "Boolean value is: True"
    assert cli(domain_id, "param", "get", "/demo/tuned", "robot.name", "--hide-type") \
        .stdout.strip() == "rover"

    done = cli(domain_id, "param", "set", "/demo/tuned", "max_speed", "1.25")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "Set parameter successful"
    assert oracle.call("get_parameter", name="max_speed") == 1.25

    refused = cli(domain_id, "param", "set", "/demo/tuned", "max_speed", "fast")
    assert refused.returncode == 1
    assert refused.stdout.startswith("Setting parameter failed")
    assert oracle.call("get_parameter", name="max_speed") == 1.25

    dump = cli(domain_id, "param", "dump", "/demo/tuned")
    assert dump.returncode == 0, dump.stderr
    params = yaml.safe_load(dump.stdout)["/demo/tuned"]["ros__parameters"]
    assert params["max_speed"] == 1.25 and params["robot"] == {"name": "rover"}
    assert params["wheels"] == [1, 2, 3, 4] and params["enabled"] is True


def test_node_list_warns_of_two_nodes_with_one_name(jazzy_python: Path, domain_id: int) -> None:
    """A second process started under a name already taken (a second sim, a robot's node
    launched twice) is the mistake `ros2 node list` warns of: one line would hide it."""
    with RclpyOracle(jazzy_python, "twin", "/demo", domain_id=domain_id), \
            RclpyOracle(jazzy_python, "twin", "/demo", domain_id=domain_id), \
            RclpyOracle(jazzy_python, "single", "/demo", domain_id=domain_id):
        nodes = cli(domain_id, "node", "list", *SPIN)
    assert nodes.returncode == 0, nodes.stderr
    assert {"/demo/twin", "/demo/single"} <= set(nodes.stdout.splitlines())
    warnings = [line for line in nodes.stderr.splitlines() if "share" in line]
    assert len(warnings) == 1 and "/demo/twin" in warnings[0] and "single" not in warnings[0]


@pytest.mark.parametrize("verb", [["get", "/demo/tuned_typo", "max_speed"],
                                  ["list", "/demo/tuned_typo"], ["dump", "demo/tuned_typo"]])
def test_param_on_a_node_not_there_names_the_node(oracle: RclpyOracle, domain_id: int,
                                                  verb: list[str]) -> None:
    """A typo'd node name said 'no server for service …/get_parameters (rcl_interfaces/srv/
    GetParameters) within 10 s': the user named a node, not a service."""
    done = cli(domain_id, "param", *verb)
    assert done.returncode == 1 and done.stdout == ""
    assert done.stderr.strip() == (
        "rcan-rtps: error: no node /demo/tuned_typo serves parameters within 3 s; "
        "`rcan-rtps node list` shows the nodes there are")


def parse_node_info(text: str) -> dict[str, dict[str, list[str]]]:
    sections: dict[str, dict[str, list[str]]] = {}
    current = ""
    for line in text.splitlines()[1:]:
        if line.startswith("    "):
            name, types = line.strip().split(": ", 1)
            sections[current][name] = types.split(", ")
        elif line.startswith("  "):
            current = line.strip().rstrip(":")
            sections[current] = {}
    return sections


def test_node_info_lists_what_rclpy_reports(oracle: RclpyOracle, domain_id: int) -> None:
    oracle.call("publisher", topic="/demo/chatter", type="std_msgs/msg/String")
    oracle.call("subscribe", topic="/demo/cmd_vel", type="geometry_msgs/msg/Twist")
    oracle.call("service_server", name="/demo/trigger", type="std_srvs/srv/Trigger")
    oracle.call("action_server", name="/demo/fibonacci")
    info = cli(domain_id, "node", "info", "/demo/tuned", *SPIN)
    assert info.returncode == 0, info.stderr
    assert info.stdout.splitlines()[0] == "/demo/tuned"
    ours = parse_node_info(info.stdout)
    theirs = oracle.call("node_info", name="tuned", namespace="/demo")
    for section, entries in theirs.items():
        visible = {name: sorted(types) for name, types in entries
                   if not any(t.startswith("_") for t in name.split("/") if t)}
        assert {n: sorted(t) for n, t in ours[section].items()} == visible, section
    assert "/demo/chatter" in ours["Publishers"] and "/demo/fibonacci" in ours["Action Servers"]
    assert ours["Service Servers"]["/demo/tuned/get_parameters"] == \
        ["rcl_interfaces/srv/GetParameters"]


def test_topic_and_service_type_and_find(oracle: RclpyOracle, domain_id: int) -> None:
    oracle.call("publisher", topic="/demo/chatter", type="std_msgs/msg/String")
    oracle.call("service_server", name="/demo/trigger", type="std_srvs/srv/Trigger")
    assert cli(domain_id, "topic", "type", "/demo/chatter", *SPIN).stdout.splitlines() == \
        ["std_msgs/msg/String"]
    assert "/demo/chatter" in cli(domain_id, "topic", "find", "std_msgs/msg/String", *SPIN) \
        .stdout.splitlines()
    assert cli(domain_id, "service", "type", "/demo/trigger", *SPIN).stdout.splitlines() == \
        ["std_srvs/srv/Trigger"]
    assert cli(domain_id, "service", "find", "std_srvs/srv/Trigger", *SPIN).stdout.splitlines() == \
        ["/demo/trigger"]
    assert cli(domain_id, "topic", "type", "/demo/nothing").returncode == 1
