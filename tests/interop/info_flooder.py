"""A peer in its own process writing `count` ros_discovery_info samples of `size` bytes each
for made-up participants, every one acknowledged by the readers matched before the next is
written (so each is in the victim's reader, not overwritten in ours). Prints "ready" once
matched by a reader, waits for "go", writes, prints "done". (test_discovery_info_memory.py)"""

from __future__ import annotations

import sys
import time
import uuid
from pathlib import Path

from rcan_rtps.ros import qos, raw_cdr
from rcan_rtps.ros.participant import DISCOVERY_TOPIC, DISCOVERY_TYPE, RosNode


def info(codec: object, size: int) -> bytes:
    """One info naming a made-up participant's node with enough made-up writer gids to be
    about `size` bytes."""
    gids = [{"data": uuid.uuid4().bytes} for _ in range(max(1, size // 16))]
    value = {"gid": {"data": uuid.uuid4().bytes}, "node_entities_info_seq": [
        {"node_namespace": "/", "node_name": "flood", "writer_gid_seq": gids}]}
    return bytes(codec.encode_value(value))  # type: ignore[attr-defined]


def main() -> None:
    count, size, domain_id, share = (int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]),
                                     Path(sys.argv[4]))
    with RosNode("flooder", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[share]) as node:
        writer = node.create_writer(DISCOVERY_TOPIC, DISCOVERY_TYPE, qos.DISCOVERY_INFO)
        codec = node.codecs.of(DISCOVERY_TYPE)
        sample = info(codec, size)
        while writer.get_publication_matched_status().current_count < 1:
            time.sleep(0.1)
        print("ready", flush=True)
        sys.stdin.readline()
        for _ in range(count):
            fresh = bytearray(sample)
            fresh[4:20] = uuid.uuid4().bytes  # another made-up participant each time
            raw_cdr.write(writer, bytes(fresh))
            writer.wait_for_acks(30 * 10**9)
        print("done", flush=True)
        sys.stdin.readline()


if __name__ == "__main__":
    main()
