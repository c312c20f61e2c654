"""`rcan-rtps service list|call`, shaped like `ros2 service`."""

from __future__ import annotations

import argparse
import asyncio
import re
import time

from .. import _stop_signals as stop_signals
from ..ros.errors import ServiceUnavailable, WireError, seconds
from ..ros.graph import RosGraph, shared_graph
from ..ros.participant import RosNode
from ..ros.services import RequestMapping, ServiceClient
from ..ros.typesys.store import normalize_name
from ._common import VALUES_HELP, alone_hint, dump, make_node, parse_values, warn_if_alone
from ._governed import UNGOVERNED, GovernorGuard, service_topics
from ._options import add_spin_time

# How long `call` looks for a server on the graph before saying there is none (discovery
# on a quiet domain takes well under a second; --timeout, when shorter, wins).
SERVER_PATIENCE = 3.0
TYPE_NAME = re.compile(r"[A-Za-z]\w*/(?:srv/)?[A-Za-z]\w*")
MAPPINGS = [m.value for m in RequestMapping]
MAPPING_HELP = ("how requests and replies are matched on the wire: cyclone (rmw_cyclonedds) or "
                "fastdds (rmw_fastrtps) layout; auto (default) picks from the server's DDS vendor")


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser("service", help="inspect and call services")
    actions = parser.add_subparsers(dest="service_command", required=True)

    listing = actions.add_parser("list", help="services on the graph")
    listing.add_argument("-t", "--show-types", action="store_true",
                         help="show each service's type")
    listing.add_argument("--include-hidden-services", action="store_true",
                         help="include services whose name has a part starting with '_'")
    add_spin_time(listing)
    listing.set_defaults(func=lambda a: stop_signals.run(_list(a)))

    kind = actions.add_parser("type", help="type of a service")
    kind.add_argument("service", metavar="NAME", help="the service, e.g. /robot1/get_parameters")
    add_spin_time(kind)
    kind.set_defaults(func=lambda a: stop_signals.run(_type(a)))

    find = actions.add_parser("find", help="services of a type")
    find.add_argument("type", metavar="TYPE", help="a service type, e.g. std_srvs/srv/Trigger")
    find.add_argument("--include-hidden-services", action="store_true",
                      help="also services whose name has a part starting with `_`")
    add_spin_time(find)
    find.set_defaults(func=lambda a: stop_signals.run(_find(a)))

    call = actions.add_parser("call", help="call a service with a request built from YAML")
    call.add_argument("service", metavar="NAME", help="service name, e.g. /reset")
    call.add_argument("type", metavar="TYPE", nargs="?", default=None,
                      help="service type, e.g. std_srvs/srv/Trigger (default: the server's, "
                      "from the graph)")
    call.add_argument("values", metavar="VALUES", nargs="?", default=None, help=VALUES_HELP)
    call.add_argument("--timeout", type=float, default=10.0, help="seconds (default 10)")
    call.add_argument("--mapping", choices=MAPPINGS, default="auto", help=MAPPING_HELP)
    call.add_argument(UNGOVERNED[0], action="store_true", help=UNGOVERNED[1])
    call.set_defaults(func=lambda a: stop_signals.run(_call(a)))


async def _list(args: argparse.Namespace) -> int:
    with make_node(args) as node:
        graph = RosGraph(node)
        await graph.settle(args.spin_time)
        for name, types in graph.services(args.include_hidden_services).items():
            print(f"{name} [{', '.join(types)}]" if args.show_types else name)
        warn_if_alone(args, node, graph)
    return 0


async def _type(args: argparse.Namespace) -> int:
    with make_node(args) as node:
        graph = RosGraph(node)
        await graph.settle(args.spin_time)
        types = graph.services(include_hidden=True).get(node.resolve(args.service), [])
    for name in types:
        print(name)
    return 0 if types else 1


async def _find(args: argparse.Namespace) -> int:
    wanted = normalize_name(args.type)
    with make_node(args) as node:
        graph = RosGraph(node)
        await graph.settle(args.spin_time)
        for name, types in graph.services(args.include_hidden_services).items():
            if wanted in types:
                print(name)
    return 0


def type_and_values(type_word: str | None, values_word: str | None) -> tuple[str | None, str]:
    """TYPE and VALUES from the words after NAME: TYPE may be left out, so a lone word that
    is not a type name (`{data: true}`, `data: 1`) is VALUES."""
    if values_word is None and type_word is not None and not TYPE_NAME.fullmatch(type_word):
        return None, type_word
    return type_word, "{}" if values_word is None else values_word


async def _server_type(args: argparse.Namespace, node: RosNode, service: str, given: str | None,
                       patience: float) -> str:
    """Waits (up to `patience` s) for a server of `service` on the graph; its type, or
    `given`. No server: an error naming the service, not its DDS topics."""
    graph = RosGraph(node)
    deadline = time.monotonic() + patience
    while True:
        graph.refresh()
        types = graph.services(include_hidden=True).get(service, [])
        if types or time.monotonic() >= deadline:
            break
        await asyncio.sleep(0.1)
    if not types:
        hint = alone_hint(args, node, graph) \
            or "`rcan-rtps service list` shows the services there are"
        raise ServiceUnavailable(f"no server for service {service} within "
                                 f"{seconds(patience)}; {hint}")
    if given is not None:
        asked = node.store.service(given).name
        if asked not in types:  # DDS never matches the two: waiting cannot help
            raise WireError(f"type mismatch: {service} has {', '.join(types)}, you asked for "
                            f"{asked}")
        return given
    if len(types) > 1:
        raise ServiceUnavailable(f"servers of {service} have several types "
                                 f"({', '.join(types)}); pass TYPE")
    return types[0]


async def _call(args: argparse.Namespace) -> int:
    type_word, values_text = type_and_values(args.type, args.values)
    values = parse_values(values_text)
    with make_node(args) as node:
        service = node.resolve(args.service)
        if type_word is not None:  # bad values fail before any wait
            node.values.build(node.store.service(type_word).request.name, values)
        type_name = await _server_type(args, node, service, type_word,
                                       min(args.timeout, SERVER_PATIENCE))
        client = ServiceClient(node, service, type_name, mapping=RequestMapping(args.mapping))
        request = node.values.build(client.request_type, values)  # bad values fail here
        await GovernorGuard(shared_graph(node), service_topics(service),
                            allowed=args.ungoverned).look_before_sending()
        print(f"requester: making request: {client.request_type}", flush=True)
        response = await client.call(request, args.timeout)
        print("response:\n" + dump(node.values.to_plain(client.response_type, response)))
    return 0
