"""The command line pointed at the wrong thing, against a real rclpy Jazzy graph (and a
Cyclone peer where rclpy's cannot show it): a topic of another type, a pipe closed early, a
service called without its type or with no server."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from oracle.client import OracleEnv, RclpyOracle, both_rmws
from waiting import eventually_sync

from rcan_rtps.ros.graph import Direction, RosGraph
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.typesys.store import TypeStore

HASH = r"RIHS01 [0-9a-f]{12}…"


def cli(domain_id: int, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    return subprocess.run([sys.executable, "-m", "rcan_rtps", *args], capture_output=True,
                          text=True, env=env, timeout=timeout)


@pytest.fixture
def oracle(jazzy_oracle: OracleEnv, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_oracle, "peer", "/wrong", domain_id=domain_id) as agent:
        yield agent


def _error_line(done: subprocess.CompletedProcess[str]) -> str:
    assert "Traceback" not in done.stderr, done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("rcan-rtps: error:")]
    assert len(errors) == 1, done.stderr
    return errors[0]


@both_rmws
def test_echo_with_another_type_says_type_mismatch(oracle: RclpyOracle,
                                                   domain_id: int) -> None:
    oracle.call("publisher", topic="/wrong/chatter", type="std_msgs/msg/String")
    done = cli(domain_id, "topic", "echo", "/wrong/chatter", "std_msgs/msg/Int32", "--once")
    assert done.returncode == 1
    assert re.fullmatch(
        rf"rcan-rtps: error: type mismatch: /wrong/chatter has std_msgs/msg/String \({HASH}\), "
        rf"you asked for std_msgs/msg/Int32 \({HASH}\)", _error_line(done)), done.stderr
    assert "UNKNOWN(24)" not in done.stderr


@both_rmws
def test_pub_with_another_type_says_type_mismatch(oracle: RclpyOracle, domain_id: int) -> None:
    oracle.call("subscribe", topic="/wrong/cmd_vel", type="geometry_msgs/msg/Twist")
    done = cli(domain_id, "topic", "pub", "--once", "/wrong/cmd_vel", "std_msgs/msg/String",
               "{data: hi}")
    assert done.returncode == 1
    assert "publishing anyway" not in done.stderr and "publishing #" not in done.stdout
    assert re.fullmatch(
        rf"rcan-rtps: error: type mismatch: /wrong/cmd_vel has geometry_msgs/msg/Twist "
        rf"\({HASH}\), you asked for std_msgs/msg/String \({HASH}\)", _error_line(done))
    assert oracle.call("take", topic="/wrong/cmd_vel") == []


@pytest.fixture
def cyclone_peer(domain_id: int) -> Iterator[RosNode]:
    """A peer that sends XTypes type information, as this bridge and `rcan-rtps sim` do
    (rmw_cyclonedds sends none): Cyclone in the CLI then reports the other type itself, as
    an incompatible TYPE_CONSISTENCY status, besides the graph showing it."""
    with RosNode("typed_peer", "/wrong", domain_id=domain_id) as node:
        yield node


@pytest.mark.parametrize("mode", [["--once"], ["--rate", "10"]], ids=["once", "loop"])
def test_pub_with_another_type_than_a_cyclone_peer_says_it_once(
        cyclone_peer: RosNode, domain_id: int, mode: list[str]) -> None:
    cyclone_peer.create_subscription("/wrong/cmd_vel", "geometry_msgs/msg/Twist",
                                     callback=lambda message: None)
    done = cli(domain_id, "topic", "pub", *mode, "/wrong/cmd_vel", "std_msgs/msg/String",
               "{data: hi}")
    assert done.returncode == 1
    # exactly one line: ours, with both names and hashes (no participant warning before it)
    assert re.fullmatch(
        rf"rcan-rtps: error: type mismatch: /wrong/cmd_vel has geometry_msgs/msg/Twist "
        rf"\({HASH}\), you asked for std_msgs/msg/String \({HASH}\)\n", done.stderr), done.stderr


def test_echo_with_a_cyclone_publisher_of_another_type_coming_later_says_it_once(
        cyclone_peer: RosNode, domain_id: int) -> None:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    echo = subprocess.Popen([sys.executable, "-m", "rcan_rtps", "topic", "echo",
                             "/wrong/chatter", "std_msgs/msg/Int32", "--once"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        graph = RosGraph(cyclone_peer)

        def echo_subscribed() -> bool:
            graph.refresh()
            return any(e.direction is Direction.SUBSCRIPTION
                       for e in graph.topic_endpoints("/wrong/chatter"))

        eventually_sync(echo_subscribed, timeout=30)
        # after echo's subscription: its own participant hears of this one's type first
        cyclone_peer.create_publisher("/wrong/chatter", "std_msgs/msg/String")
        _, stderr = echo.communicate(timeout=60)
    finally:
        echo.kill()
        echo.wait()
    assert echo.returncode == 1
    assert re.fullmatch(
        rf"rcan-rtps: error: type mismatch: /wrong/chatter has std_msgs/msg/String \({HASH}\), "
        rf"you asked for std_msgs/msg/Int32 \({HASH}\)\n", stderr), stderr


def test_pub_of_another_definition_under_the_same_name_on_humble_says_it_once(
        domain_id: int, tmp_path: Path) -> None:
    """Humble announces no type hash: the graph shows the same name on both sides, and only
    DDS (the peer's XTypes type information) sees the definitions differ. The one error says
    so (before: the participant's warning, then "publishing anyway" to nobody, exit 0)."""
    changed = tmp_path / "std_msgs" / "msg"
    changed.mkdir(parents=True)
    (changed / "String.idl").write_text(
        "module std_msgs { module msg {\n  struct String {\n    string data;\n"
        "    int32 extra;\n  };\n}; };\n")
    with RosNode("changed_peer", "/wrong", domain_id=domain_id,
                 store=TypeStore([tmp_path], "humble")) as peer:
        peer.create_subscription("/wrong/text", "std_msgs/msg/String",
                                 callback=lambda message: None)
        done = cli(domain_id, "--distro", "humble", "topic", "pub", "--once", "/wrong/text",
                   "std_msgs/msg/String", "{data: hi}")
    assert done.returncode == 1
    assert done.stderr == (
        "rcan-rtps: error: type mismatch: /wrong/text has an endpoint of another type than "
        "the std_msgs/msg/String (no type hash) you asked for, in name or definition (DDS "
        "reports it; the ROS graph cannot say which: no type hash to compare)\n"), done.stderr
    assert "publishing #" not in done.stdout


def test_echo_into_a_pipe_closed_early_ends_quietly(oracle: RclpyOracle, domain_id: int,
                                                    tmp_path: Path) -> None:
    oracle.call("publisher", topic="/wrong/chatter", type="std_msgs/msg/String")
    oracle.call("publish_periodic", topic="/wrong/chatter", type="std_msgs/msg/String",
                value={"data": "x" * 64}, rate=100.0)
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    # like `rcan-rtps topic echo /wrong/chatter | head -n 2`
    done = subprocess.run(
        f"{sys.executable} -m rcan_rtps topic echo /wrong/chatter --json 2>err.txt | head -n 2;"
        " echo \"status=${PIPESTATUS[0]}\"; cat err.txt",
        shell=True, executable="/bin/bash", capture_output=True, text=True, env=env,
        timeout=60, cwd=tmp_path)
    lines = done.stdout.splitlines()
    assert lines[:2] == ['{"data": "' + "x" * 64 + '"}'] * 2, done.stdout
    status = next(line for line in lines if line.startswith("status="))
    assert status in ("status=0", f"status={128 + 13}"), done.stdout  # 0 or SIGPIPE's
    assert "Broken pipe" not in done.stdout and "Traceback" not in done.stdout


@both_rmws
def test_service_call_takes_its_type_from_the_graph(oracle: RclpyOracle,
                                                    domain_id: int) -> None:
    oracle.call("service_server", name="/wrong/enable", type="std_srvs/srv/SetBool")
    done = cli(domain_id, "service", "call", "/wrong/enable", "{data: true}")
    assert done.returncode == 0, done.stderr
    assert "requester: making request: std_srvs/srv/SetBool_Request" in done.stdout
    assert "success: true" in done.stdout
    assert oracle.call("service_requests", name="/wrong/enable") == [{"data": True}]


def test_service_call_without_a_server_names_the_service(domain_id: int) -> None:
    done = cli(domain_id, "service", "call", "/wrong/nobody", "{data: true}")
    assert done.returncode == 1
    line = _error_line(done)
    assert "/wrong/nobody" in line and "rq/" not in line and "rr/" not in line
    assert "no server" in line
    typed = cli(domain_id, "service", "call", "/wrong/nobody", "std_srvs/srv/SetBool",
                "{data: true}", "--timeout", "1")
    line = _error_line(typed)
    assert "/wrong/nobody" in line and "rq/" not in line and "rr/" not in line
