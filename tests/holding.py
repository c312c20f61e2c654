"""Holding a node's reader thread, as a busy CPU does: samples for its readers pile up in
their histories meanwhile (docs/design/zero-loss.md, history overflow)."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from rcan_rtps.ros import qos
from rcan_rtps.ros.names import mangle_topic
from rcan_rtps.ros.participant import RosNode


@asynccontextmanager
async def reader_thread_held(node: RosNode, peer: RosNode) -> AsyncIterator[None]:
    """`node`'s reader thread held for the block: a watch of `node` on /hold blocks it on
    the sample `peer` publishes there, until the block ends."""
    held, release = threading.Event(), threading.Event()
    hold = node.create_reader(mangle_topic("/hold"), "std_msgs/msg/Empty", qos.DEFAULT)
    node.watch(hold, lambda _: (held.set(), release.wait(60)), "hold")
    holder = peer.create_publisher("/hold", "std_msgs/msg/Empty")
    await holder.wait_for_subscribers(1, 15)
    holder.publish({})
    try:
        assert await asyncio.to_thread(held.wait, 15), "the reader thread was not held"
        yield
    finally:
        release.set()
