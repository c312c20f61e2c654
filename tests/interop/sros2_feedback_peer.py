"""Our action client on a secured graph, run by tests/interop/test_sros2.py in the interpreter
of a Cyclone DDS built with security. Under DDS-Security a GUID carries no vendor id: the
feedback writer of rclpy's secured server (rmw_cyclonedds) must not be taken for one whose
first feedback cannot be held back (handshake.py, 4.). One JSON object on stdout:

    {"fresh_in_sync": ...,            a fresh client's reader, before any feedback was taken
     "open_after_end_settled": ...,   an order-1 goal (no feedback): feedback() still waiting
                                      for a repair once its end had settled
     "in_sync_after_a_feedback": ..., after a goal whose feedback came
     "own_server_in_sync": ...}       a fresh client of our own server in this process

An error ends it with {"error": "..."} (exit 1).
"""

from __future__ import annotations

import asyncio
import sys
from typing import Any

from sros2_peer_io import run_peer, say

from rcan_rtps.ros.actions import ActionClient, ActionServer, ClientGoal, ServerGoal
from rcan_rtps.ros.participant import RosNode

FIB = "test_msgs/action/Fibonacci"


async def open_after_end_settled(goal: ClientGoal) -> bool:
    """Whether `feedback()` is still waiting once it has said the goal's end settled (it
    returns in the same step as it says so when it sees no reason to wait)."""
    follow = asyncio.create_task(_all(goal))
    await goal.end_settled.wait()
    still = not follow.done()
    await follow
    return still


async def _all(goal: ClientGoal) -> list[Any]:
    return [f async for f in goal.feedback(timeout=60)]


async def run(domain_id: int) -> None:
    with RosNode("secure_client", "/", domain_id=domain_id, distro="jazzy") as node, \
            RosNode("secure_server", "/", domain_id=domain_id, distro="jazzy") as ours:
        assert node.secured and ours.secured, "not secured"
        client = ActionClient(node, "/fib", FIB)
        await client.wait_for_server(60)
        fresh = client.feedback_in_sync()
        goal = await client.send_goal({"order": 1}, timeout=30)  # ends with no feedback
        waited = await open_after_end_settled(goal)
        goal = await client.send_goal({"order": 3}, timeout=30)
        assert await _all(goal), "no feedback"
        after = client.feedback_in_sync()

        async def execute(goal: ServerGoal) -> dict[str, Any]:
            return {"sequence": [0, 1]}

        server = ActionServer(ours, "/our_fib", FIB, execute)
        own = ActionClient(node, "/our_fib", FIB)
        await own.wait_for_server(60)
        say(fresh_in_sync=fresh, open_after_end_settled=waited, in_sync_after_a_feedback=after,
            own_server_in_sync=own.feedback_in_sync())
        own.close()
        await server.close()


if __name__ == "__main__":
    sys.exit(run_peer(run))
