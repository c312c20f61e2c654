"""One process of the concurrent-clients test: a fresh node calls /echo `calls` times, one
after another (the processes run side by side), and prints a JSON tally (each reply must echo
its own request). One call at a time per process, as a ROS tool makes them: a burst of many
would overflow the server's request queue (KEEP_LAST 10), which loses requests by design.
A call that fails with AmbiguousReply (a reply without a readable identity while other clients
are there) is tallied as such: a clear refusal, neither lost nor wrong."""

from __future__ import annotations

import asyncio
import json
import sys

from rcan_rtps.ros.errors import AmbiguousReply, ServiceTimeout
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.services import ServiceClient

ECHO = "test_msgs/srv/BasicTypes"


async def main(tag: str, calls: int, domain_id: int, share: str) -> None:
    lost: list[int] = []
    wrong: list[str] = []
    ambiguous: list[int] = []
    with RosNode(f"caller_{tag}", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[share]) as node:
        client = ServiceClient(node, "/echo", ECHO)
        await client.wait_for_service(timeout=30)

        async def one(i: int) -> None:
            request = {"string_value": f"{tag}:{i}", "int64_value": i}
            try:
                reply = await client.call(request, timeout=15)
            except ServiceTimeout:
                lost.append(i)
                return
            except AmbiguousReply:
                ambiguous.append(i)
                return
            if (reply.string_value, reply.int64_value) != (f"{tag}:{i}", i):
                wrong.append(f"{tag}:{i} got {reply.string_value}")

        print("ready", flush=True)
        sys.stdin.readline()  # every process starts calling at the same moment
        for i in range(calls):
            await one(i)
        client.close()
    print(json.dumps({"lost": lost, "wrong": wrong, "ambiguous": ambiguous}), flush=True)


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]))
