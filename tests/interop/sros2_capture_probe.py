"""Run by tests/interop/test_sros2.py in the secure interpreter, SROS2 set by the environment:
whether a plain call (the Fast DDS mapping) of our secured node has the packet capture keep
its reply. Prints one JSON object: {"secured": ..., "capture": ..., "kept": [...]}.

The call's reply writer is a DataWriter of our own on the client's reply topic (a secured
Fast DDS server is not at hand: the oracle's Fast DDS has no security); nobody answers, the
call times out. What matters is what the call asked of the capture before its request went
out (`expect_reply`)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import sys
from typing import Any

from cyclonedds.pub import DataWriter

from rcan_rtps.ros.handshake import matched_writers
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.services import RequestMapping, ServiceClient, ServiceTimeout

TRIGGER = "std_srvs/srv/Trigger"


def watch_reply_capture(node: RosNode) -> list[bool]:
    """What each call's request to the capture to keep its reply answers, from now on."""
    kept: list[bool] = []
    capture = node.identities
    if capture is not None:
        expect = capture.expect_reply

        def expect_reply(identity: Any, writers: Any) -> bool:
            kept.append(expect(identity, writers))
            return kept[-1]
        capture.expect_reply = expect_reply  # type: ignore[method-assign]
    return kept


async def run(domain_id: int) -> dict[str, Any]:
    loop = asyncio.get_running_loop()
    with RosNode("capture_probe", "/", domain_id=domain_id, distro="jazzy") as node:
        kept = watch_reply_capture(node)
        client = ServiceClient(node, "/plain_probe", TRIGGER, mapping=RequestMapping.FASTDDS)
        pair = client._pair(RequestMapping.FASTDDS)
        writer = DataWriter(node.participant, pair.reader.topic)
        deadline = loop.time() + 10
        while not matched_writers(pair.reader) and loop.time() < deadline:
            await asyncio.sleep(0.05)
        request = node.values.build(client.request_type, {})
        with contextlib.suppress(ServiceTimeout):
            await client._send_plain(pair, request, loop.time() + 0.3, None, False)
        client.close()
        del writer
        return {"secured": node.secured, "capture": node.identities is not None,
                "kept": kept}


def main() -> int:
    try:
        print(json.dumps(asyncio.run(run(int(sys.argv[1])))), flush=True)
    except Exception as e:  # the test reads the reason
        print(json.dumps({"error": f"{type(e).__name__}: {e}"}), flush=True)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
