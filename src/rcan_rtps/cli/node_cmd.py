"""`rcan-rtps node list|info`, shaped like `ros2 node`."""

from __future__ import annotations

import argparse
import sys

from .. import _stop_signals as stop_signals
from .._printable import shown
from ..ros.graph import Direction, Endpoint, RosGraph, node_fqn
from ..ros.names import EndpointKind, action_of, is_hidden
from ._common import make_node, warn_if_alone
from ._options import add_spin_time


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser("node", help="nodes on the graph")
    actions = parser.add_subparsers(dest="node_command", required=True)
    listing = actions.add_parser("list", help="every node announced on the graph")
    listing.add_argument("-a", "--all", action="store_true", help="include hidden nodes")
    add_spin_time(listing)
    listing.set_defaults(func=lambda a: stop_signals.run(_list(a)))
    info = actions.add_parser("info", help="endpoints of a node, grouped like ros2 node info")
    info.add_argument("node", metavar="NODE_NAME", help="the node, e.g. /robot1/rcan_bridge")
    info.add_argument("--include-hidden", action="store_true",
                      help="show hidden topics, services and actions too")
    add_spin_time(info)
    info.set_defaults(func=lambda a: stop_signals.run(_info(a)))


async def _list(args: argparse.Namespace) -> int:
    node = make_node(args)
    with node:
        graph = RosGraph(node)
        await graph.settle(args.spin_time)
        for namespace, name in graph.nodes():
            if args.all or not name.startswith("_"):
                print(shown(node_fqn(namespace, name)))  # (as a peer named itself)
        _warn_of_shared_names(graph.nodes_sharing_a_name())
        warn_if_alone(args, node, graph)
    return 0


def _warn_of_shared_names(shared: list[tuple[str, str]]) -> None:
    """One line, as `ros2 node list` warns: listed once, two processes would pass unseen."""
    if shared:
        names = ", ".join(shown(node_fqn(namespace, name)) for namespace, name in shared)
        print(f"rcan-rtps: warning: several nodes share the name {names}: services, "
              "parameters and the graph cannot tell them apart", file=sys.stderr)


SECTIONS = ("Subscribers", "Publishers", "Service Servers", "Service Clients",
            "Action Servers", "Action Clients")


def _section_of(e: Endpoint) -> tuple[str, str, str] | None:
    """(section, name, type) an endpoint stands for in `node info`, or None (reply
    endpoints and action parts other than send_goal are implied by another one)."""
    member = action_of(e.ros_name)
    if member is not None:
        if member[1] != "send_goal" or e.kind is not EndpointKind.REQUEST:
            return None
        role = "Action Servers" if e.direction is Direction.SUBSCRIPTION else "Action Clients"
        return role, member[0], e.ros_type.removesuffix("_SendGoal")
    if e.kind is EndpointKind.TOPIC:
        role = "Subscribers" if e.direction is Direction.SUBSCRIPTION else "Publishers"
        return role, e.ros_name, e.ros_type
    if e.kind is EndpointKind.REQUEST:
        role = "Service Servers" if e.direction is Direction.SUBSCRIPTION else "Service Clients"
        return role, e.ros_name, e.ros_type
    return None


def describe_node(endpoints: list[Endpoint],
                  include_hidden: bool) -> dict[str, dict[str, set[str]]]:
    sections: dict[str, dict[str, set[str]]] = {s: {} for s in SECTIONS}
    for e in endpoints:
        found = _section_of(e)
        if found is None:
            continue
        section, name, type_name = found
        if include_hidden or not is_hidden(name):
            sections[section].setdefault(name, set()).add(type_name)
    return sections


async def _info(args: argparse.Namespace) -> int:
    node = make_node(args)
    with node:
        graph = RosGraph(node)
        await graph.settle(args.spin_time)
        target = args.node if args.node.startswith("/") else "/" + args.node
        if target not in {node_fqn(ns, name) for ns, name in graph.nodes()}:
            print(f"Unable to find node '{target}'")
            return 1
        mine = [e for e in graph.endpoints()
                if node_fqn(e.node_namespace, e.node_name) == target]
        print(shown(target))
        for section, entries in describe_node(mine, args.include_hidden).items():
            print(f"  {section}:")
            for name, types in sorted(entries.items()):
                print(shown(f"    {name}: {', '.join(sorted(types))}"))
    return 0
