"""One process of the related-sample-identity measurement (test_rpc_identity.py).

A fresh node, whose domain has Cyclone's packet capture on (rtps_capture.py), calls /echo (an
rclpy Fast DDS echo server) `calls` times, one after another, with plain requests as
rmw_fastrtps' clients send them. For every reply sample its reader gets (a Fast DDS server
sends each reply to every client's reply reader), it looks up the related sample identity
that the reply carried in its inline QoS and tallies:

    ours     identity = (our request writer, k) and the reply echoes our request k
    mixed    identity = ours but the reply echoes something else (the identity lies)
    foreign  identity names another writer, and the reply is not an echo of ours
    unknown  no related sample identity found for the reply (its datagram not in the
             capture, or it carried none)

A call waits for the reply whose identity is its own request's, so the tally also shows
whether identity alone gets every call its own answer. It prints a JSON tally.
"""

from __future__ import annotations

import asyncio
import json
import sys
from collections import Counter
from typing import Any

from rcan_rtps.ros import qos as qos_mod
from rcan_rtps.ros.handshake import hear_announcements
from rcan_rtps.ros.names import mangle_service
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.services import RequestMapping, _Pair

ECHO = "test_msgs/srv/BasicTypes"


async def main(tag: str, calls: int, domain_id: int, share: str) -> None:
    tally: Counter[str] = Counter()
    answered: dict[int, asyncio.Future[Any]] = {}
    lost: list[int] = []
    with RosNode(f"idcaller_{tag}", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[share]) as node:
        capture = node.identities  # the domain's packet capture (participant.py)
        assert capture is not None, "the packet capture is off (RCAN_RTPS_RPC_IDENTITY)"
        capture.use()  # parse, not only skip, what it records
        request_topic, reply_topic = mangle_service("/echo")
        srv = node.store.service(ECHO)

        def deliver(pair: _Pair, samples: list[Any]) -> None:
            mine = pair.writer.guid.bytes
            for sample in samples:
                info = sample.sample_info
                writer = pair.reader.get_matched_publication_data(info.publication_handle)
                guid = bytes(writer.key.bytes) if writer is not None else b""
                related = capture.lookup(guid, info.source_timestamp)
                if related is None:
                    tally["unknown"] += 1
                elif related.writer_guid == mine:
                    echoes = sample.string_value == f"{tag}:{related.seq}"
                    tally["ours" if echoes else "mixed"] += 1
                    future = answered.get(related.seq)
                    if echoes and future is not None and not future.done():
                        future.set_result(sample)
                else:
                    tally["foreign" if not sample.string_value.startswith(f"{tag}:")
                          else "mixed"] += 1

        pair = _Pair(node, RequestMapping.FASTDDS, (request_topic, srv.request.name),
                     (reply_topic, srv.response.name), qos_mod.SERVICES, "", deliver)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 30

        async def matched() -> None:
            while not pair.matched() and loop.time() < deadline:
                await asyncio.sleep(0.05)
            await asyncio.sleep(1.0)  # the server's reply writer matched our reader too

        async def renew() -> None:
            pair.renew_reader()
            await matched()

        await matched()
        # As the product's clients do (ServiceClient._await_announced): the first reply must
        # not be dropped as history because the writer's announcement to our reader was lost.
        _, unheard = await hear_announcements(capture, lambda: pair.reader, lambda: pair.since,
                                              renew, deadline)
        print("ready", flush=True)
        await loop.run_in_executor(None, sys.stdin.readline)
        for k in range(1, calls + 1):  # the writer's k-th sample has sequence number k
            answered[k] = loop.create_future()
            pair.write(node.values.build(srv.request.name,
                                         {"string_value": f"{tag}:{k}", "int64_value": k}))
            try:
                await asyncio.wait_for(answered[k], 15)
            except asyncio.TimeoutError:
                lost.append(k)
        await asyncio.sleep(0.5)  # late copies of others' replies still get tallied
        pair.close()
        capture.heard_heartbeat(bytes(16), bytes(16), 0)  # (reads the capture up to its end)
        # A lost reply whose DATA reached our socket was dropped by Cyclone, not the kernel.
        in_capture = [k for k in lost if any(
            i.writer_guid == pair.writer_guid and i.seq == k for i in capture._known.values())]
    stats = {"datagrams": capture.datagrams, "identified": capture.identified,
             "renewed": pair.renewed, "unannounced": len(unheard), "lost_in_capture": in_capture}
    print(json.dumps({"tally": dict(tally), "lost": lost, **stats}), flush=True)


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]))
