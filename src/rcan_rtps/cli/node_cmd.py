"""`rcan-rtps node list`."""

from __future__ import annotations

import argparse
import asyncio

from ..ros.graph import RosGraph, node_fqn
from ._common import make_node, warn_if_alone


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser("node", help="nodes on the graph")
    actions = parser.add_subparsers(dest="node_command", required=True)
    listing = actions.add_parser("list", help="every node announced on the graph")
    listing.add_argument("-a", "--all", action="store_true", help="include hidden nodes")
    listing.add_argument("--spin-time", type=float, default=1.5, help="discovery wait (s)")
    listing.set_defaults(func=lambda a: asyncio.run(_list(a)))


async def _list(args: argparse.Namespace) -> int:
    node = make_node(args)
    with node:
        graph = RosGraph(node)
        await graph.settle(args.spin_time)
        for namespace, name in graph.nodes():
            if args.all or not name.startswith("_"):
                print(node_fqn(namespace, name))
        warn_if_alone(args, node, graph)
    return 0
