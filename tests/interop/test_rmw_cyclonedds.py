"""Against rclpy Jazzy on rmw_cyclonedds_cpp (issue 12): rclpy clients on Cyclone use our
servers, and a Cyclone node's log stays clean of warnings about our endpoints.

The cases shared with Fast DDS (topics, our clients against rclpy servers, node lists) are
parametrized over both RMWs in their own modules; here is what only Cyclone can do: a Fast
DDS client cannot use our servers at all (see test_services.py).
"""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication
from oracle.client import OracleEnv, RclpyOracle, fibonacci
from waiting import eventually, eventually_sync

from rcan_rtps.ros.actions import ActionServer, ServerGoal
from rcan_rtps.ros.participant import DISCOVERY_TOPIC, DISCOVERY_TYPE, RosNode
from rcan_rtps.ros.qos import user_data_of
from rcan_rtps.ros.services import ServiceServer

FIB = "test_msgs/action/Fibonacci"
TYPE_HASH_WARNING = "Failed to parse type hash"


@pytest.fixture
def cyclone(jazzy_cyclone_python: Path) -> OracleEnv:
    return OracleEnv(jazzy_cyclone_python, "cyclonedds")


@pytest.fixture
def oracle(cyclone: OracleEnv, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(cyclone, "cyclone_peer", "/", domain_id=domain_id) as agent:
        assert agent.call("rmw") == "rmw_cyclonedds_cpp"
        yield agent


@pytest.fixture
async def node(domain_id: int, jazzy_share: Path) -> AsyncIterator[RosNode]:
    with RosNode("rcan_server", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as n:
        yield n


async def test_rclpy_client_on_cyclone_calls_our_trigger_and_setbool(
        oracle: RclpyOracle, node: RosNode) -> None:
    served: list[Any] = []

    async def trigger(request: Any) -> dict[str, Any]:
        served.append("trigger")
        return {"success": True, "message": f"ours #{len(served)}"}

    async def set_bool(request: Any) -> dict[str, Any]:
        served.append(bool(request.data))
        return {"success": bool(request.data), "message": f"set {request.data}"}

    servers = [ServiceServer(node, "/trigger", "std_srvs/srv/Trigger", trigger),
               ServiceServer(node, "/enable", "std_srvs/srv/SetBool", set_bool)]
    try:
        first = await oracle.acall("service_call", name="/trigger",
                                   type="std_srvs/srv/Trigger", value={}, wait=15.0)
        on = await oracle.acall("service_call", name="/enable", type="std_srvs/srv/SetBool",
                                value={"data": True}, wait=15.0)
        off = await oracle.acall("service_call", name="/enable", type="std_srvs/srv/SetBool",
                                 value={"data": False}, wait=15.0)
    finally:
        for server in servers:
            await server.close()
    assert first == {"success": True, "message": "ours #1"}
    assert on == {"success": True, "message": "set True"}
    assert off == {"success": False, "message": "set False"}
    assert served == ["trigger", True, False]


async def fibonacci_execute(goal: ServerGoal) -> dict[str, Any]:
    order = int(goal.goal.order)  # type: ignore[attr-defined]
    seq = [0, 1]
    for i in range(1, order):
        seq.append(seq[i] + seq[i - 1])
        goal.publish_feedback({"sequence": seq})
        await asyncio.sleep(0.05)
    return {"sequence": seq}


async def test_rclpy_action_client_on_cyclone_uses_our_action_server(
        oracle: RclpyOracle, node: RosNode) -> None:
    async def accept(goal: Any) -> bool:
        return int(goal.order) < 20  # a long goal is refused

    server = ActionServer(node, "/fib", FIB, fibonacci_execute, accept=accept)
    try:
        await oracle.acall("action_send_goal", name="/fib", key="ok", order=6)
        done = await oracle.acall("action_goal", key="ok", timeout=30)
        await oracle.acall("action_send_goal", name="/fib", key="long", order=25)
        refused = await oracle.acall("action_goal", key="long", timeout=30)
    finally:
        await server.close()
    assert done["accepted"] is True
    assert done["result"] == {"status": 4, "sequence": fibonacci(6)}  # SUCCEEDED
    assert done["feedback"] and done["feedback"][-1] == fibonacci(6)
    assert refused["accepted"] is False and refused["result"] is None


def cli(domain_id: int, jazzy_share: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    return subprocess.run([sys.executable, "-m", "rcan_rtps", "--idl-path", str(jazzy_share),
                           *args], capture_output=True, text=True, env=env, timeout=90)


def test_cyclone_node_log_has_no_type_hash_warning(cyclone: OracleEnv, domain_id: int,
                                                    jazzy_share: Path) -> None:
    """Every endpoint we create, ros_discovery_info's included, carries `typehash=` in
    USER_DATA as rmw does; rmw_cyclonedds warns about each one that does not."""
    with RclpyOracle(cyclone, "clean_log", "/", domain_id=domain_id) as peer:
        peer.call("publisher", topic="/chatter", type="std_msgs/msg/String")
        peer.call("subscribe", topic="/cmd", type="std_msgs/msg/String")
        peer.call("service_server", name="/trigger", type="std_srvs/srv/Trigger")
        peer.call("action_server", name="/fib")
        steps = [
            ("node", "list"),
            ("topic", "pub", "--once", "/cmd", "std_msgs/msg/String", "{data: hi}"),
            ("service", "call", "/trigger", "std_srvs/srv/Trigger"),
            ("action", "send_goal", "/fib", FIB, "{order: 3}"),
        ]
        failed = [(step, done.stderr[-300:]) for step in steps
                  if (done := cli(domain_id, jazzy_share, *step)).returncode != 0]
        echo = subprocess.Popen(
            [sys.executable, "-m", "rcan_rtps", "topic", "echo", "/chatter", "--once",
             "--timeout", "30"], env={**os.environ, "ROS_DOMAIN_ID": str(domain_id)},
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            eventually_sync(lambda: peer.call("publish", topic="/chatter",
                                              type="std_msgs/msg/String",
                                              value={"data": "x"}) and echo.poll() is not None,
                            timeout=30, what="topic echo got a message")
        finally:
            echo.kill()
            echo.wait()
        heard = peer.call("take", topic="/cmd")
        served = peer.call("service_requests", name="/trigger")
    assert failed == [] and echo.returncode == 0
    assert heard == [{"data": "hi"}] and served == [{}]  # every command did reach the node
    warnings = [line for line in peer.stderr().splitlines() if TYPE_HASH_WARNING in line]
    assert warnings == []


async def test_our_discovery_endpoints_carry_the_hash_rmw_cyclonedds_uses(
        oracle: RclpyOracle, node: RosNode) -> None:
    """rmw_cyclonedds' own ros_discovery_info writer says which hash it expects there."""
    publications = BuiltinDataReader(node.participant, BuiltinTopicDcpsPublication)
    ours = node.participant.guid.bytes

    def theirs() -> set[str]:
        return {user_data_of(s.qos).get("typehash", "") for s in publications.read(N=1000)
                if s.topic_name == DISCOVERY_TOPIC and s.participant_key.bytes != ours}

    hashes = await eventually(theirs, what="rmw_cyclonedds' ros_discovery_info writer")
    assert hashes == {node.store.hash_of(DISCOVERY_TYPE)}
    assert node.endpoint_user_data(DISCOVERY_TYPE) == f"typehash={hashes.pop()};".encode()
