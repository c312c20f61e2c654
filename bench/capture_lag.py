"""How long the event loop is blocked while a Fast DDS call looks for its reply in the capture.

A Fast DDS call whose reply has not come after CAPTURE_REPLY_AFTER (0.5 s) asks the packet
capture for it every CAPTURE_POLL (0.1 s) (`services.py` `_reply_from_capture`); a miss
flushes the capture and reads it to its end (at most MISS_BUDGET bytes, rtps_capture.py).
This measures, in a process that receives a 640×480 rgb8 Image at 30 Hz and a Twist at 1 kHz
from an rclpy Jazzy node on rmw_fastrtps: the event loop's lag (a probe task that sleeps
1 ms and records by how much it woke late; its maximum and 99.9th percentile), and how long
each capture lookup took (wall time, and whether it ran on the event loop's thread), in two
windows of `--seconds`: calls to an echo server that answers at once, and calls to a
Trigger server that answers after `--delay` s (so each call looks in the capture ~15 times);
`lookup` is the related-identity look each reply taken from the reader makes (in delivery).
First, with no peer, the worst case a look allows: MISS_BUDGET bytes of small datagrams not
read yet at each of `--worst-looks` looks (`worst_case`).

Run it with PYTHONPATH naming the tree measured (before/after a change: two trees).

DDS runs here, so run it in a private network namespace (as root):
    scripts/netns .venv/bin/python bench/capture_lag.py [--oracle .cache/ros-jazzy/bin/python]
Prints a table (docs/design/rpc-identity.md quotes it); writes nothing.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from e2e import DOMAIN, ROOT
from interop.cpu_load import burning_cpus
from oracle.client import RclpyOracle
from ros.test_rtps_capture import PCAP_HEADER, REQUEST_WRITER, SERVER, data_message, pcap_record

from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.rtps_capture import (
    MISS_BUDGET,
    IdentityCapture,
    SampleIdentity,
    capture_directory,
)
from rcan_rtps.ros.services import RequestMapping, ServiceClient

IMAGE = "sensor_msgs/msg/Image"
TWIST = "geometry_msgs/msg/Twist"
ECHO, TRIGGER = "test_msgs/srv/BasicTypes", "std_srvs/srv/Trigger"
IMAGE_HZ, TWIST_HZ = 30.0, 1000.0
PROBE_PERIOD = 0.001
IDLE_WINDOW = 2.0  # s of probing with no look, before the worst case's looks
TABLE_HEAD = ("| calls | lag max (ms) | lag p99.9 (ms) | lag median (ms) | `captured_reply` "
              "| `lookup` |\n|---|---|---|---|---|---|")


class Timings:
    """How long each call of one capture method took, on which thread it ran, and how many
    bytes of the capture it read itself (its own `_consume` calls)."""

    def __init__(self, capture: IdentityCapture, method: str) -> None:
        self.seconds: list[float] = []
        self.read: list[int] = []
        self.on_loop = 0
        self.loop_thread = threading.get_ident()
        original: Callable[..., Any] = getattr(capture, method)
        consume: Callable[[int], int] = capture._consume
        mine = threading.local()

        def counted(limit: int) -> int:
            used = consume(limit)
            mine.read = getattr(mine, "read", 0) + used
            return used

        def timed(*args: Any) -> Any:
            mine.read, start = 0, time.perf_counter()
            try:
                return original(*args)
            finally:
                self.seconds.append(time.perf_counter() - start)
                self.read.append(mine.read)
                self.on_loop += threading.get_ident() == self.loop_thread
        setattr(capture, method, timed)
        capture._consume = counted  # type: ignore[method-assign]


async def probe(lags: list[float], stop: asyncio.Event) -> None:
    loop = asyncio.get_running_loop()
    while not stop.is_set():
        start = loop.time()
        await asyncio.sleep(PROBE_PERIOD)
        lags.append(loop.time() - start - PROBE_PERIOD)


async def window(seconds: float, calls: Callable[[], Any]) -> list[float]:
    lags: list[float] = []
    stop = asyncio.Event()
    prober = asyncio.create_task(probe(lags, stop))
    end = asyncio.get_running_loop().time() + seconds
    while asyncio.get_running_loop().time() < end:
        await calls()
    stop.set()
    await prober
    return lags


def looked(timings: Timings, before: tuple[int, int]) -> str:
    took, read = timings.seconds[before[0]:], timings.read[before[0]:]
    if not took:
        return "none"
    return (f"{len(took)} ({timings.on_loop - before[1]} on the loop): longest "
            f"{max(took) * 1e3:.1f} ms, median {statistics.median(took) * 1e3:.2f} ms; "
            f"read itself up to {max(read) / 1e6:.2f} MB")


def row(name: str, lags: list[float], timings: dict[str, Timings],
        before: dict[str, tuple[int, int]]) -> str:
    lags_ms = sorted(x * 1e3 for x in lags)
    p999 = lags_ms[min(len(lags_ms) - 1, int(len(lags_ms) * 0.999))]
    return (f"| {name} | {max(lags_ms):.1f} | {p999:.1f} | {statistics.median(lags_ms):.2f} | "
            + " | ".join(looked(t, before[m]) for m, t in timings.items()) + " |")


async def worst_case(looks: int) -> None:
    """A capture that no drain thread reads holds `looks` × MISS_BUDGET bytes of small
    received DATA (replies naming another request) while `ServiceClient._reply_from_capture`
    looks for a reply that never comes: each look that misses reads MISS_BUDGET itself."""
    capture = IdentityCapture(tempfile.mkdtemp(prefix="lag-bench-", dir=capture_directory()))
    writer = os.open(capture.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
    os.write(writer, PCAP_HEADER)
    assert capture.start()
    capture._stop.set()  # no drain thread: each look reads its own MISS_BUDGET
    assert capture._thread is not None
    capture._thread.join()
    capture.use()
    ours = SampleIdentity(REQUEST_WRITER, 1)
    capture.expect_reply(ours, [SERVER])
    record = pcap_record(data_message(SERVER, 1, SampleIdentity(REQUEST_WRITER, 2), bytes(52)))
    os.write(writer, record * (looks * MISS_BUDGET // len(record) + 1))
    timings = Timings(capture, "captured_reply")
    with RosNode("lag_worst", "/", domain_id=DOMAIN) as node:
        client = ServiceClient(node, "/nobody", TRIGGER, mapping=RequestMapping.FASTDDS)
        idle = await window(IDLE_WINDOW, lambda: asyncio.sleep(0.01))  # the machine's own
        lags: list[float] = []
        stop = asyncio.Event()
        prober = asyncio.create_task(probe(lags, stop))
        pair: Any = None  # (used only to deliver a reply found: none is)
        looking = asyncio.create_task(client._reply_from_capture(
            pair, capture, ours, asyncio.get_running_loop().create_future(), None))
        while len(timings.seconds) < looks:
            await asyncio.sleep(0.01)
        looking.cancel()
        stop.set()
        await prober
    capture.close()
    os.close(writer)
    print(f"| none, {IDLE_WINDOW:g} s (the machine's own lag) | {max(idle) * 1e3:.1f} | - | "
          f"{statistics.median(idle) * 1e3:.2f} | - | - |")
    print(f"| {looks} looks, {MISS_BUDGET >> 20} MiB of {len(record)}-byte records each, "
          f"no drain thread | {max(lags) * 1e3:.1f} | - | "
          f"{statistics.median(lags) * 1e3:.2f} | {looked(timings, (0, 0))} | - |", flush=True)


async def run(args: argparse.Namespace) -> None:
    share = args.oracle.parent.parent / "share"
    with RosNode("lag_bench", "/", domain_id=DOMAIN, distro="jazzy", idl_paths=[share]) as node:
        assert node.identities is not None, "the capture is off here"
        timings = {m: Timings(node.identities, m) for m in ("captured_reply", "lookup")}
        node.create_subscription("/bench/image", IMAGE, raw=True)
        node.create_subscription("/bench/twist", TWIST, raw=True)
        echo = ServiceClient(node, "/echo", ECHO, mapping=RequestMapping.FASTDDS)
        slow = ServiceClient(node, "/slow", TRIGGER, mapping=RequestMapping.FASTDDS)
        await echo.call({"string_value": "hello"}, timeout=15)
        await slow.wait_for_service(15)
        await asyncio.sleep(2.0)  # streaming settles

        async def fast_call() -> None:
            await echo.call({"string_value": "x"}, timeout=5)
            await asyncio.sleep(0.1)

        async def slow_call() -> None:
            await slow.call({}, timeout=args.delay + 5)

        print(TABLE_HEAD)
        for name, calls in (("answered at once", fast_call),
                            (f"answered after {args.delay:g} s", slow_call)) * args.rounds:
            before = {m: (len(t.seconds), t.on_loop) for m, t in timings.items()}
            lags = await window(args.seconds, calls)
            print(row(name, lags, timings, before), flush=True)
        print(f"capture: {node.identities.datagrams} datagrams parsed")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--oracle", type=Path, default=ROOT / ".cache/ros-jazzy/bin/python")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--delay", type=float, default=2.0)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--load", action="store_true", help="one busy process per core")
    parser.add_argument("--worst-looks", type=int, default=5)
    args = parser.parse_args()
    print(TABLE_HEAD)
    asyncio.run(worst_case(args.worst_looks))
    image = {"height": 480, "width": 640, "encoding": "rgb8", "step": 640 * 3,
             "data": [k % 251 for k in range(640 * 480 * 3)]}
    with RclpyOracle(args.oracle, "lag_pub", "/", domain_id=DOMAIN) as oracle:
        oracle.call("echo_server", name="/echo")
        oracle.call("service_server", name="/slow", type=TRIGGER, delay=args.delay)
        for topic, kind, value, rate in (("/bench/image", IMAGE, image, IMAGE_HZ),
                                         ("/bench/twist", TWIST, {"linear": {"x": 0.5}},
                                          TWIST_HZ)):
            oracle.call("publisher", topic=topic, type=kind)
            oracle.call("publish_periodic", topic=topic, type=kind, value=value, rate=rate)
        try:
            with burning_cpus() if args.load else contextlib.nullcontext():
                asyncio.run(run(args))
        finally:
            for topic in ("/bench/image", "/bench/twist"):
                oracle.call("stop_periodic", topic=topic)


if __name__ == "__main__":
    main()
