"""`rcan-rtps topic list|info|echo|pub|hz`, shaped like `ros2 topic`."""

from __future__ import annotations

import argparse
import asyncio
import itertools
import statistics
import sys
import time
from typing import Any

from .. import _stop_signals as stop_signals
from .._printable import shown
from ..ros import qos as qos_mod
from ..ros.errors import GraphTimeout, seconds
from ..ros.graph import Direction, Endpoint, RosGraph, short_gid
from ..ros.names import mangle_topic
from ..ros.participant import RosNode, RosPublisher
from ..ros.typesys.store import normalize_name
from . import _measure
from ._common import (
    TOPIC_HELP,
    TYPE_CHECK_PERIOD,
    VALUES_HELP,
    TypeGuard,
    alone_hint,
    make_node,
    parse_values,
    resolve_type,
    warn_if_alone,
)
from ._echo import EchoFormat, adapted_qos, add_qos_options, chosen_qos
from ._governed import UNGOVERNED, GovernorGuard
from ._options import add_spin_time

SUBSCRIBER_PATIENCE = 5.0  # s `pub --once/--times` waits for subscriptions to match


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser("topic", help="inspect and use topics")
    actions = parser.add_subparsers(dest="topic_command", required=True)

    listing = actions.add_parser("list", help="topics on the graph")
    listing.add_argument("-t", "--show-types", action="store_true",
                         help="show each topic's ROS type(s)")
    listing.add_argument("--include-hidden-topics", action="store_true",
                         help="include topics whose name has a part starting with '_'")
    add_spin_time(listing)
    listing.set_defaults(func=lambda a: stop_signals.run(_list(a)))

    info = actions.add_parser("info", help="type and endpoints of a topic")
    info.add_argument("topic", metavar="TOPIC", help=TOPIC_HELP)
    info.add_argument("-v", "--verbose", action="store_true",
                      help="list every endpoint: node, QoS, type hash, GID, DDS vendor")
    add_spin_time(info)
    info.set_defaults(func=lambda a: stop_signals.run(_info(a)))

    echo = actions.add_parser("echo", help="print messages of a topic")
    echo.add_argument("topic", metavar="TOPIC", help=TOPIC_HELP)
    echo.add_argument("type", metavar="TYPE", nargs="?",
                      help="message type, e.g. nav_msgs/msg/Odometry (default: from the graph)")
    echo.add_argument("--once", action="store_true", help="print one message and exit")
    echo.add_argument("--count", type=int, default=0, help="stop after N messages")
    style = echo.add_mutually_exclusive_group()
    style.add_argument("--json", action="store_true", help="one JSON object per line")
    style.add_argument("--csv", action="store_true",
                       help="one line per message: every value, comma-separated, in field order")
    echo.add_argument("--field", metavar="FIELD",
                      help="print only this field; '.' selects sub-fields, e.g. "
                      "pose.pose.position")
    echo.add_argument("--no-arr", action="store_true",
                      help="print arrays and sequences as a placeholder with type and length")
    echo.add_argument("--timeout", type=float, default=0.0, help="give up after S seconds")
    add_qos_options(echo)
    echo.set_defaults(func=lambda a: stop_signals.run(_echo(a)))

    pub = actions.add_parser("pub", help="publish messages built from YAML values")
    pub.add_argument("topic", metavar="TOPIC", help=TOPIC_HELP)
    pub.add_argument("type", metavar="TYPE", help="message type, e.g. geometry_msgs/msg/Twist")
    pub.add_argument("values", metavar="VALUES", nargs="?", default="{}", help=VALUES_HELP)
    mode = pub.add_mutually_exclusive_group()
    mode.add_argument("-1", "--once", action="store_true", help="publish one message and exit")
    mode.add_argument("-t", "--times", type=int, default=0, metavar="N",
                      help="publish N messages and exit (default: until Ctrl-C)")
    pub.add_argument("-r", "--rate", type=float, default=1.0, help="Hz (default 1)")
    pub.add_argument(UNGOVERNED[0], action="store_true", help=UNGOVERNED[1])
    pub.add_argument("-w", "--wait-matching-subscriptions", type=int, default=None, metavar="N",
                     help="first wait up to 5 s for N subscribers (default: 1 with --once or "
                     "--times, else 0)")
    pub.add_argument("--qos-profile", default="default", choices=sorted(qos_mod.PRESETS),
                     help="QoS preset of the publisher (default: default)")
    pub.set_defaults(func=lambda a: stop_signals.run(_pub(a)))

    kind = actions.add_parser("type", help="type of a topic")
    kind.add_argument("topic", metavar="TOPIC", help="the topic, e.g. /robot1/odom")
    add_spin_time(kind)
    kind.set_defaults(func=lambda a: stop_signals.run(_type(a)))

    find = actions.add_parser("find", help="topics of a type")
    find.add_argument("type", metavar="TYPE", help="a message type, e.g. nav_msgs/msg/Odometry")
    find.add_argument("--include-hidden-topics", action="store_true",
                      help="also topics whose name has a part starting with `_`")
    add_spin_time(find)
    find.set_defaults(func=lambda a: stop_signals.run(_find(a)))

    hz = actions.add_parser("hz", help="rate of a topic")
    hz.add_argument("topic", metavar="TOPIC", help=TOPIC_HELP)
    hz.add_argument("type", metavar="TYPE", nargs="?",
                    help="message type (default: from the graph)")
    hz.add_argument("--window", type=int, default=10000, metavar="N",
                    help="compute the rate over the last N messages (default 10000)")
    hz.add_argument("--duration", type=float, default=0.0, help="stop after S seconds")
    hz.set_defaults(func=lambda a: stop_signals.run(_hz(a)))
    _measure.register(actions)


async def _graph(args: argparse.Namespace) -> tuple[RosNode, RosGraph]:
    node = make_node(args)
    graph = RosGraph(node)
    await graph.settle(getattr(args, "spin_time", 1.5))
    return node, graph


async def _list(args: argparse.Namespace) -> int:
    node, graph = await _graph(args)
    with node:
        for name, types in graph.topics(args.include_hidden_topics).items():
            # (names and types are what any participant on the domain says: shown, not obeyed)
            print(shown(f"{name} [{', '.join(types)}]" if args.show_types else name))
        warn_if_alone(args, node, graph)
    return 0


async def _type(args: argparse.Namespace) -> int:
    node, graph = await _graph(args)
    with node:
        types = graph.topics(include_hidden=True).get(node.resolve(args.topic), [])
    for name in types:
        print(shown(name))
    return 0 if types else 1


async def _find(args: argparse.Namespace) -> int:
    wanted = normalize_name(args.type)
    node, graph = await _graph(args)
    with node:
        for name, types in graph.topics(args.include_hidden_topics).items():
            if wanted in types:
                print(shown(name))
    return 0


def _describe_endpoint(e: Endpoint) -> str:
    q = e.qos
    depth = f"KEEP_LAST ({q.depth})" if q.history is qos_mod.History.KEEP_LAST else "KEEP_ALL"
    return "\n".join([
        f"Node name: {shown(e.node_name)}",
        f"Node namespace: {shown(e.node_namespace)}",
        f"Topic type: {shown(e.ros_type)}",
        f"Topic type hash: {e.type_hash or 'INVALID'}",
        f"Endpoint type: {e.direction.value}",
        f"GID: {short_gid(e.gid)}",
        f"DDS vendor: {e.vendor}",
        "QoS profile:",
        f"  Reliability: {q.reliability.name}",
        f"  History (Depth): {depth}",
        f"  Durability: {q.durability.name}",
        "",
    ])


async def _info(args: argparse.Namespace) -> int:
    node, graph = await _graph(args)
    with node:
        topic = node.resolve(args.topic)
        endpoints = graph.topic_endpoints(topic)
        if not endpoints:
            hint = alone_hint(args, node, graph)
            print(f"Unknown topic '{topic}'" + (f" ({hint})" if hint else ""), file=sys.stderr)
            return 1
        pubs = [e for e in endpoints if e.direction is Direction.PUBLISHER]
        subs = [e for e in endpoints if e.direction is Direction.SUBSCRIPTION]
        print(shown(f"Type: {', '.join(sorted({e.ros_type for e in endpoints}))}"))
        print(f"Publisher count: {len(pubs)}")
        if args.verbose:
            print()
            for e in pubs:
                print(_describe_endpoint(e))
        print(f"Subscription count: {len(subs)}")
        if args.verbose:
            print()
            for e in subs:
                print(_describe_endpoint(e))
    return 0


async def _echo(args: argparse.Namespace) -> int:
    node = make_node(args)
    with node:
        graph = RosGraph(node)
        topic = node.resolve(args.topic)
        type_name, pubs = await resolve_type(args, node, graph, topic, args.type, args.timeout)
        shape = EchoFormat(args, node.values, type_name)  # bad type or field: fail now
        guard = TypeGuard(node, graph, topic, type_name)
        guard.check()
        sub = node.create_subscription(topic, type_name, chosen_qos(args, pubs),
                                       warn_other_type=False)
        guard.watch(sub)
        limit = 1 if args.once else args.count
        seen = 0
        deadline = time.monotonic() + args.timeout if args.timeout else None
        while not limit or seen < limit:
            guard.check_when_due()  # a publisher of another type is never heard: say so
            now = time.monotonic()
            left = deadline - now if deadline else None
            if left is not None and left <= 0:
                break
            try:
                msg = await sub.get(timeout=min(left or TYPE_CHECK_PERIOD, TYPE_CHECK_PERIOD))
            except asyncio.TimeoutError:
                continue
            print(shape.text(msg), flush=True)
            seen += 1
        if limit and not seen:
            hint = alone_hint(args, node, graph) or f"is anything publishing on {topic}?"
            print(f"rcan-rtps: no message on {topic} within {seconds(args.timeout)}; {hint}",
                  file=sys.stderr)
        return 0 if seen or not limit else 1


async def _pub(args: argparse.Namespace) -> int:
    values = parse_values(args.values)
    node = make_node(args)
    with node:
        pub = node.create_publisher(args.topic, args.type, qos_mod.preset(args.qos_profile),
                                    warn_other_type=False)
        graph = RosGraph(node)
        guard = TypeGuard(node, graph, pub.topic, args.type)
        guard.watch(pub)
        governor = GovernorGuard(graph, {mangle_topic(pub.topic): pub.topic},
                                 allowed=args.ungoverned)
        message = node.values.build(args.type, values)
        times = 1 if args.once else args.times
        wait_for = args.wait_matching_subscriptions
        if wait_for is None:
            wait_for = 1 if times else 0
        if wait_for:
            await _await_subscribers(pub, guard, wait_for, SUBSCRIBER_PATIENCE)
        else:
            guard.check()
        await governor.look_before_sending()
        print("publisher: beginning loop", flush=True)
        said = _shown(node.values.to_plain(args.type, message))
        period = 1.0 / args.rate if args.rate > 0 else 0.0
        sent = 0
        while not times or sent < times:
            guard.check_when_due()  # a subscription of another type appeared
            governor.check_when_due()  # a governor found since
            pub.publish(message)
            sent += 1
            print(f"publishing #{sent}: {args.type}({said})", flush=True)
            if not times or sent < times:
                await asyncio.sleep(period)
        await asyncio.sleep(0.3)  # let reliable delivery finish before the participant goes
    return 0


async def _await_subscribers(pub: RosPublisher, guard: TypeGuard, wanted: int,
                             patience: float) -> None:
    """Up to `patience` s for `wanted` matched subscriptions; a subscription of another type
    (which never matches) ends the wait with an error."""
    deadline = time.monotonic() + patience
    while True:
        guard.check()
        left = deadline - time.monotonic()
        if left <= 0:
            print(f"warning: no subscriber matched {pub.topic}; publishing anyway",
                  file=sys.stderr)
            return
        try:
            await pub.wait_for_subscribers(wanted, timeout=min(left, TYPE_CHECK_PERIOD))
            return
        except GraphTimeout:
            continue


def _shown(plain: Any) -> str:
    """A message on one line, as `field=value` pairs (ros2 topic pub prints its repr)."""
    if isinstance(plain, dict):
        return ", ".join(f"{k}={_shown_value(v)}" for k, v in plain.items())
    return str(plain)


def _shown_value(value: Any) -> str:
    if isinstance(value, dict):
        return f"({_shown(value)})"
    return repr(value)


async def _hz(args: argparse.Namespace) -> int:
    node = make_node(args)
    with node:
        graph = RosGraph(node)
        topic = node.resolve(args.topic)
        type_name, pubs = await resolve_type(args, node, graph, topic, args.type, 5.0)
        sub = node.create_subscription(topic, type_name, adapted_qos(pubs))
        stamps: list[float] = []
        start = last_report = time.monotonic()
        while not args.duration or time.monotonic() - start < args.duration:
            try:
                await sub.get(timeout=0.2)
                stamps.append(time.monotonic())
                del stamps[: max(0, len(stamps) - args.window)]
            except asyncio.TimeoutError:
                pass
            if time.monotonic() - last_report >= 1.0:
                last_report = time.monotonic()
                _report_rate(stamps)
        _report_rate(stamps)
    return 0


def _report_rate(stamps: list[float]) -> None:
    if len(stamps) < 2:
        print("no new messages", flush=True)
        return
    gaps = [b - a for a, b in itertools.pairwise(stamps)]
    mean = statistics.fmean(gaps)
    print(f"average rate: {1.0 / mean:.3f}\n\tmin: {min(gaps):.3f}s max: {max(gaps):.3f}s "
          f"std dev: {statistics.pstdev(gaps):.5f}s window: {len(stamps)}", flush=True)
