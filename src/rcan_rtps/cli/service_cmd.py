"""`rcan-rtps service list|call`, shaped like `ros2 service`."""

from __future__ import annotations

import argparse
import asyncio

from ..ros.graph import RosGraph
from ..ros.services import RequestMapping, ServiceClient
from ..ros.typesys.store import normalize_name
from ._common import VALUES_HELP, dump, make_node, parse_values, warn_if_alone

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
    listing.add_argument("--spin-time", type=float, default=1.5, help="discovery wait (s)")
    listing.set_defaults(func=lambda a: asyncio.run(_list(a)))

    kind = actions.add_parser("type", help="type of a service")
    kind.add_argument("service", metavar="NAME", help="the service, e.g. /robot1/get_parameters")
    kind.add_argument("--spin-time", type=float, default=1.5,
                      help="seconds to listen for the graph before answering (default 1.5)")
    kind.set_defaults(func=lambda a: asyncio.run(_type(a)))

    find = actions.add_parser("find", help="services of a type")
    find.add_argument("type", metavar="TYPE", help="a service type, e.g. std_srvs/srv/Trigger")
    find.add_argument("--include-hidden-services", action="store_true",
                      help="also services whose name has a part starting with `_`")
    find.add_argument("--spin-time", type=float, default=1.5,
                      help="seconds to listen for the graph before answering (default 1.5)")
    find.set_defaults(func=lambda a: asyncio.run(_find(a)))

    call = actions.add_parser("call", help="call a service with a request built from YAML")
    call.add_argument("service", metavar="NAME", help="service name, e.g. /reset")
    call.add_argument("type", metavar="TYPE", help="service type, e.g. std_srvs/srv/Trigger")
    call.add_argument("values", metavar="VALUES", nargs="?", default="{}", help=VALUES_HELP)
    call.add_argument("--timeout", type=float, default=10.0, help="seconds (default 10)")
    call.add_argument("--mapping", choices=MAPPINGS, default="auto", help=MAPPING_HELP)
    call.set_defaults(func=lambda a: asyncio.run(_call(a)))


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


async def _call(args: argparse.Namespace) -> int:
    values = parse_values(args.values)
    with make_node(args) as node:
        client = ServiceClient(node, args.service, args.type,
                               mapping=RequestMapping(args.mapping))
        request = node.values.build(client.request_type, values)  # bad values fail here
        print(f"requester: making request: {client.request_type}", flush=True)
        response = await client.call(request, args.timeout)
        print("response:\n" + dump(node.values.to_plain(client.response_type, response)))
    return 0
