"""The issue-9 shape in process: a node writes a topic it also reads while a real remote
rclpy publisher floods the same topic. With a Cyclone listener this froze the process
for good (the GIL against Cyclone's reader lock); with the reader thread it must not.

A frozen process cannot fail a test by itself: faulthandler ends it (with every stack)
if the test has not finished in HANG_LIMIT s.
"""

from __future__ import annotations

import asyncio
import faulthandler
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from oracle.client import RclpyOracle
from waiting import eventually

from rcan_rtps.ros import qos
from rcan_rtps.ros.participant import RosNode

INT = "std_msgs/msg/Int32"
SECONDS = 15.0
HANG_LIMIT = 600.0


@pytest.fixture(autouse=True)
def _hang_is_a_failure() -> Iterator[None]:
    faulthandler.dump_traceback_later(HANG_LIMIT, exit=True, file=sys.stderr)
    yield
    faulthandler.cancel_dump_traceback_later()


async def test_own_writer_and_reader_with_a_remote_publisher_at_200hz(
        jazzy_python: Path, domain_id: int) -> None:
    node = RosNode("shared_io", "/", domain_id=domain_id)
    try:
        counts = {"mine": 0, "theirs": 0, "callbacks_on": set()}  # type: dict[str, Any]

        def on_sample(msg: Any) -> None:
            counts["callbacks_on"].add(threading.current_thread().name)
            counts["mine" if msg.data >= 0 else "theirs"] += 1

        sub = node.create_subscription("/shared", INT, qos.DEFAULT.with_(depth=100),
                                       callback=on_sample)
        pub = node.create_publisher("/shared", INT)
        with RclpyOracle(jazzy_python, "flood", domain_id=domain_id) as oracle:
            await oracle.acall("publisher", topic="/shared", type=INT)
            await sub.wait_for_publishers(2, timeout=30)
            await oracle.acall("publish_periodic", topic="/shared", type=INT, value={"data": -1},
                               rate=200.0)
            loop = asyncio.get_running_loop()
            start = loop.time()
            sent = 0
            while loop.time() - start < SECONDS:
                for _ in range(20):  # bursts of local writes from the event loop
                    pub.publish({"data": sent})
                    sent += 1
                await asyncio.sleep(0.005)
            published = await oracle.acall("stop_periodic", topic="/shared")
        await eventually(lambda: counts["theirs"] > 0, timeout=30,
                         what=lambda: f"a remote sample: {published=} {counts}")
        assert published > 0 and counts["theirs"] > 0, (published, counts)
        assert counts["mine"] > 0 and sent > 1000
        # Never a Cyclone thread (those show as Dummy-N): the node's reader thread only.
        assert counts["callbacks_on"] == {f"dds-read {node.fqn}"}, counts["callbacks_on"]
    finally:
        node.close()
