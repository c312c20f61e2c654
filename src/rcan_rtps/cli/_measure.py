"""`rcan-rtps topic bw|delay`: bandwidth and header-stamp delay, printed each second like ros2."""

from __future__ import annotations

import argparse
import asyncio
import collections
import math
import statistics
import time
from collections.abc import Callable
from typing import Any

from cyclonedds.idl import IdlStruct

from .. import _stop_signals as stop_signals
from ..ros import qos as qos_mod
from ..ros.errors import WireError
from ..ros.graph import RosGraph
from ..ros.participant import RosNode
from ._common import TOPIC_HELP, make_node, resolve_type

BW_WINDOW = 100  # ros2 topic bw's default
DELAY_WINDOW = 10000  # ros2 topic delay's default
HEADER_TYPE = "std_msgs/msg/Header"


def register(actions: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    bw = actions.add_parser("bw", help="bandwidth used by a topic")
    _add_common(bw, BW_WINDOW)
    bw.set_defaults(func=lambda a: stop_signals.run(_bw(a)))

    delay = actions.add_parser("delay", help="delay between now and each message's header stamp")
    _add_common(delay, DELAY_WINDOW)
    delay.set_defaults(func=lambda a: stop_signals.run(_delay(a)))


def _add_common(parser: argparse.ArgumentParser, window: int) -> None:
    parser.add_argument("topic", metavar="TOPIC", help=TOPIC_HELP)
    parser.add_argument("type", metavar="TYPE", nargs="?",
                        help="message type (default: from the graph)")
    parser.add_argument("-w", "--window", type=_positive, default=window, metavar="WINDOW",
                        help=f"compute over the last WINDOW messages (default {window})")
    parser.add_argument("--duration", type=float, default=0.0,
                        help="stop after S seconds (default: until Ctrl-C)")


def _positive(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError("must be a positive integer")
    return value


class BandwidthWindow:
    """Arrival times and serialized sizes of the last `size` messages."""

    def __init__(self, size: int, clock: Callable[[], float] = time.monotonic) -> None:
        self.samples: collections.deque[tuple[float, int]] = collections.deque(maxlen=size)
        self._clock = clock

    def add(self, data: bytes) -> None:  # on the node's reader thread
        # The size on the wire: CDR with its 4-byte encapsulation header, as rclpy's raw=True.
        self.add_size(len(data))

    def add_size(self, size: int) -> None:
        self.samples.append((self._clock(), size))

    def report(self) -> str | None:
        samples = list(self.samples)
        if len(samples) < 2:
            return None
        elapsed = self._clock() - samples[0][0]
        sizes = [size for _, size in samples]
        rate = sum(sizes) / elapsed if elapsed > 0 else 0.0
        bw, mean, low, high = _in_units(rate, rate, statistics.fmean(sizes), min(sizes),
                                        max(sizes))
        return (f"{bw}/s from {len(sizes)} messages\n"
                f"\tMessage size mean: {mean} min: {low} max: {high}")


def _in_units(rate: float, *values: float) -> list[str]:
    """Every figure in one unit, chosen by the rate (as ros2 does)."""
    if rate < 1000:
        return [f"{v:.0f} B" for v in values]
    divisor, unit = (1000, "KB") if rate < 1_000_000 else (1_000_000, "MB")
    return [f"{v / divisor:.2f} {unit}" for v in values]


class DelayWindow:
    """now − header.stamp (wall clock, like ROS time without sim time) of the last messages."""

    def __init__(self, size: int) -> None:
        self.delays: collections.deque[int] = collections.deque(maxlen=size)
        self.received = 0
        self._reported = 0

    def add(self, message: IdlStruct) -> None:  # on the node's reader thread
        now = time.time_ns()
        stamp = message.header.stamp  # type: ignore[attr-defined]
        self.delays.append(now - (stamp.sec * 1_000_000_000 + stamp.nanosec))
        self.received += 1

    def report(self) -> str | None:
        """None before the first message; 'no new messages' when none came since the last."""
        if not self.delays:
            return None
        if self.received == self._reported:
            return "no new messages"
        self._reported = self.received
        delays = [d * 1e-9 for d in self.delays]
        mean = statistics.fmean(delays)
        std_dev = math.sqrt(statistics.fmean([(d - mean) ** 2 for d in delays]))
        return (f"average delay: {mean:.3f}\n\tmin: {min(delays):.3f}s max: {max(delays):.3f}s "
                f"std dev: {std_dev:.5f}s window: {len(delays)}")


async def _bw(args: argparse.Namespace) -> int:
    window = BandwidthWindow(args.window)
    return await _measure(args, window.add, window.report, needs_header=False, raw=True)


async def _delay(args: argparse.Namespace) -> int:
    window = DelayWindow(args.window)
    return await _measure(args, window.add, window.report, needs_header=True)


async def _measure(args: argparse.Namespace, add: Callable[[Any], None],
                   report: Callable[[], str | None],
                   *, needs_header: bool, raw: bool = False) -> int:
    node = make_node(args)
    with node:
        graph = RosGraph(node)
        topic = node.resolve(args.topic)
        type_name, _ = await resolve_type(args, node, graph, topic, args.type, 5.0)
        if needs_header:
            _check_header(node, type_name)
        # sensor_data (best effort) matches every publisher, as in ros2 topic bw/delay.
        node.create_subscription(topic, type_name, qos_mod.SENSOR_DATA, callback=add, raw=raw)
        print(f"Subscribed to [{topic}]", flush=True)
        start = time.monotonic()
        while not args.duration or time.monotonic() - start < args.duration:
            await asyncio.sleep(min(1.0, args.duration or 1.0))
            text = report()
            if text:
                print(text, flush=True)
    return 0


def _check_header(node: RosNode, type_name: str) -> None:
    fields = {f.name: f.type for f in node.store.message(type_name).fields}
    header = fields.get("header")
    if header is None or header.nested != HEADER_TYPE or header.is_collection:
        raise WireError(f"{type_name} has no 'header' field of type {HEADER_TYPE}; "
                        "topic delay needs one")
