"""Our node on a secured graph, run by tests/interop/test_sros2.py in the interpreter of a
Cyclone DDS built with security (scripts/cyclonedds-secure), SROS2 set by the environment
(ROS_SECURITY_*). One JSON object a line on stdout, in this order:

    {"secured": true}                          the participant is up, secured
    {"published": N}                           a subscriber matched /from_us, N samples sent
    {"received": "..."}                        the first sample on /from_rclpy
    {"called": {...}}                          /rclpy_trigger's reply
    {"action": {...}}                          a Fibonacci goal on rclpy's /fib: state, result
    {"serving": true}                          /our_trigger is served until stdin closes
    {"heard": [...]}                           every /from_rclpy text, at the end

An error ends it with {"error": "..."} (exit 1).
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
from typing import Any

from sros2_peer_io import run_peer, say

from rcan_rtps.ros.actions import ActionClient
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.services import ServiceClient, ServiceServer

STRING, TRIGGER = "std_msgs/msg/String", "std_srvs/srv/Trigger"
FIB = "test_msgs/action/Fibonacci"


async def run(domain_id: int) -> None:
    loop = asyncio.get_running_loop()
    with RosNode("secure_peer", "/", domain_id=domain_id, distro="jazzy") as node:
        say(secured=node.secured)
        heard: list[str] = []
        sub = node.create_subscription("/from_rclpy", STRING)
        pub = node.create_publisher("/from_us", STRING)
        await pub.wait_for_subscribers(1, timeout=30)
        for i in range(5):
            pub.publish({"data": f"secured hello {i}"})
            await asyncio.sleep(0.1)
        say(published=5)
        first = await sub.get(timeout=30)
        heard.append(first.data)
        say(received=first.data)
        client = ServiceClient(node, "/rclpy_trigger", TRIGGER)
        await client.wait_for_service(30)
        reply = await client.call({}, timeout=15)
        say(called={"success": bool(reply.success), "message": reply.message})
        goal = await ActionClient(node, "/fib", FIB).send_goal({"order": 5}, timeout=30)
        outcome = await goal.result(timeout=30)
        sequence = list(outcome.result.sequence) if outcome.result is not None else None
        say(action={"state": outcome.state.name, "sequence": sequence})

        async def trigger(request: Any) -> dict[str, Any]:
            return {"success": True, "message": "served by rcan-rtps"}

        server = ServiceServer(node, "/our_trigger", TRIGGER, trigger)
        say(serving=True)
        stdin_closed = loop.run_in_executor(None, sys.stdin.read)
        while not stdin_closed.done():
            with contextlib.suppress(asyncio.TimeoutError):
                heard.append((await sub.get(timeout=0.2)).data)
        await server.close()
        say(heard=heard)


if __name__ == "__main__":
    sys.exit(run_peer(run))
