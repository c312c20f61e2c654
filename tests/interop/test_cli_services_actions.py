"""`rcan-rtps service …` and `action …` as subprocesses against a real rclpy Jazzy graph (on
Fast DDS and on Cyclone DDS)."""

from __future__ import annotations

import asyncio
import os
import selectors
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from dropping import SMALL_BUFFERS, flood_process
from oracle.client import OracleEnv, RclpyOracle, both_rmws
from waiting import SPIN

from rcan_rtps.ros.actions import ActionServer, ServerGoal
from rcan_rtps.ros.participant import RosNode


def cli(domain_id: int, *args: str, timeout: float = 90) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    return subprocess.run([sys.executable, "-m", "rcan_rtps", *args], capture_output=True,
                          text=True, env=env, timeout=timeout)


@pytest.fixture
def oracle(jazzy_oracle: OracleEnv, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_oracle, "cli_peer", "/demo", domain_id=domain_id) as agent:
        yield agent


@both_rmws
def test_service_list_and_call(oracle: RclpyOracle, domain_id: int) -> None:
    oracle.call("service_server", name="/demo/trigger", type="std_srvs/srv/Trigger")
    oracle.call("service_server", name="/demo/enable", type="std_srvs/srv/SetBool")
    listing = cli(domain_id, "service", "list", "-t", *SPIN)
    assert listing.returncode == 0, listing.stderr
    assert "/demo/trigger [std_srvs/srv/Trigger]" in listing.stdout.splitlines()
    assert "/demo/enable [std_srvs/srv/SetBool]" in listing.stdout.splitlines()

    done = cli(domain_id, "service", "call", "/demo/enable", "std_srvs/srv/SetBool",
               "{data: true}")
    assert done.returncode == 0, done.stderr
    assert "success: true" in done.stdout and "message: set to True (#1)" in done.stdout
    assert oracle.call("service_requests", name="/demo/enable") == [{"data": True}]


def test_service_call_with_another_type_than_the_servers_says_so(oracle: RclpyOracle,
                                                                 domain_id: int) -> None:
    """A wrong TYPE for a served service waited 10 s and said 'no server': the two types'
    endpoints never match, as `topic pub` with a wrong type already says at once."""
    oracle.call("service_server", name="/demo/enable", type="std_srvs/srv/SetBool")
    done = cli(domain_id, "service", "call", "/demo/enable", "std_srvs/srv/Trigger")
    assert done.returncode == 1 and "requester:" not in done.stdout
    assert done.stderr.strip() == ("rcan-rtps: error: type mismatch: /demo/enable has "
                                   "std_srvs/srv/SetBool, you asked for std_srvs/srv/Trigger")
    assert oracle.call("service_requests", name="/demo/enable") == []


def test_service_call_failures_are_messages(domain_id: int) -> None:
    done = cli(domain_id, "service", "call", "/nobody", "std_srvs/srv/Trigger", "--timeout", "1")
    assert done.returncode != 0
    assert "no server for service /nobody" in done.stderr and "Traceback" not in done.stderr
    done = cli(domain_id, "service", "call", "/x", "std_srvs/srv/SetBool", "{data: 7}")
    assert done.returncode != 0
    assert "data: expected true or false" in done.stderr and "Traceback" not in done.stderr


@both_rmws
def test_action_list_info_and_send_goal(oracle: RclpyOracle, domain_id: int,
                                        jazzy_share: Path) -> None:
    oracle.call("action_server", name="/demo/fibonacci")
    listing = cli(domain_id, "action", "list", "-t", *SPIN)
    assert listing.returncode == 0, listing.stderr
    assert "/demo/fibonacci [test_msgs/action/Fibonacci]" in listing.stdout.splitlines()
    info = cli(domain_id, "action", "info", "/demo/fibonacci", *SPIN)
    assert info.returncode == 0, info.stderr
    assert "Action servers: 1\n    /demo/cli_peer" in info.stdout

    done = cli(domain_id, "--idl-path", str(jazzy_share), "action", "send_goal",
               "/demo/fibonacci", "test_msgs/action/Fibonacci", "{order: 5}", "--feedback")
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert "Goal accepted with ID:" in out and "Feedback:" in out
    assert "Result:\n  sequence:\n  - 0\n  - 1\n  - 1\n  - 2\n  - 3\n  - 5" in out
    assert out.rstrip().endswith("Goal finished with status: SUCCEEDED")


# SIGTERM and SIGHUP (its terminal closed) used to kill the command and leave the goal running.
@both_rmws
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP],
                         ids=lambda s: s.name)
def test_send_goal_ended_by_a_signal_cancels_the_goal(oracle: RclpyOracle, domain_id: int,
                                                      jazzy_share: Path,
                                                      sig: signal.Signals) -> None:
    oracle.call("action_server", name="/demo/fibonacci", mode="slow")
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "rcan_rtps", "--idl-path", str(jazzy_share), "action",
         "send_goal", "/demo/fibonacci", "test_msgs/action/Fibonacci", "{order: 100}", "-f"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stdout is not None
        seen = ""
        with selectors.DefaultSelector() as sel:
            sel.register(proc.stdout, selectors.EVENT_READ)
            deadline = time.monotonic() + 60
            while "Feedback:" not in seen and time.monotonic() < deadline:
                if sel.select(1.0):
                    seen += proc.stdout.readline()
        assert "Feedback:" in seen, seen
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 128 + sig, err
    assert "Goal canceled." in out and "Goal finished with status: CANCELED" in out
    assert "Traceback" not in err


NAV = "nav2_msgs/action/NavigateToPose"
# The command with a repair window that cannot end before the test does: what it prints
# before its server leaves is printed before the window ends.
LONG_REPAIR = ("import sys; from rcan_rtps.ros import action_goals; "
               "action_goals.REPAIR_S = {m: 600.0 for m in action_goals.REPAIR_S}; "
               "from rcan_rtps.cli.main import main; sys.exit(main(sys.argv[1:]))")


async def _line_with(stream: asyncio.StreamReader, text: str, seen: list[str]) -> None:
    while not seen or text not in seen[-1]:
        line = await stream.readline()
        assert line, f"the command ended before printing {text!r}: {''.join(seen)}"
        seen.append(line.decode())


async def test_send_goal_prints_the_result_before_the_repair_window_ends(
        domain_id: int) -> None:
    """After a datagram was dropped at its sockets, `send_goal -f` waits, once the goal has
    ended, for as long as the server's repair of a dropped feedback can take (REPAIR_S); it
    printed the result only after that. The result comes as soon as it is in, feedback the
    window brings after it, and the status line last."""
    with RosNode("robot_sim", "/", domain_id=domain_id) as server_node:
        go = asyncio.Event()
        goals: list[ServerGoal] = []

        async def execute(goal: ServerGoal) -> dict[str, Any]:
            goals.append(goal)
            goal.publish_feedback({"distance_remaining": 2.0})
            await go.wait()
            goal.publish_feedback({"distance_remaining": 1.0})
            return {"error_code": 0, "error_msg": "arrived"}

        server = ActionServer(server_node, "/nav", NAV, execute)
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-c", LONG_REPAIR, "action", "send_goal", "/nav", NAV, "{}", "-f",
            "--timeout", "30", stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
            env={**os.environ, "ROS_DOMAIN_ID": str(domain_id),
                 "CYCLONEDDS_URI": SMALL_BUFFERS.format(size="3kB")})
        try:
            assert proc.stdout is not None
            seen: list[str] = []
            await asyncio.wait_for(_line_with(proc.stdout, "Goal accepted", seen), 60)
            await asyncio.to_thread(flood_process, proc.pid)  # after the goal was sent
            go.set()
            await asyncio.wait_for(_line_with(proc.stdout, "Result:", seen), 60)
            assert proc.returncode is None  # in the repair window, still
            goals[0].publish_feedback({"distance_remaining": 0.5})  # as a repair brings it
            await asyncio.wait_for(_line_with(proc.stdout, "distance_remaining: 0.5", seen), 60)
            assert proc.returncode is None
            await server.close()  # its server gone, nothing more can come: the command ends
            server_node.close()
            rest, err = await asyncio.wait_for(proc.communicate(), 60)
        finally:
            if proc.returncode is None:
                proc.kill()
    out = "".join(seen) + rest.decode()
    assert proc.returncode == 0, err.decode()
    assert out.index("distance_remaining: 1.0") < out.index("Result:\n  error_code: 0") \
        < out.index("distance_remaining: 0.5")
    assert out.rstrip().endswith("Goal finished with status: SUCCEEDED")
