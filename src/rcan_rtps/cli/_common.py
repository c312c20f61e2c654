"""What every graph command shares: global options and a short-lived hidden node."""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any

import yaml

from ..ros.errors import ValueFitError
from ..ros.graph import RosGraph
from ..ros.participant import RosNode, localhost_requested
from ..ros.typesys.store import TypeStore, env_idl_paths

TOPIC_HELP = "topic name, e.g. /robot1/odom (relative names resolve from /)"
VALUES_HELP = "field values as YAML, e.g. \"{linear: {x: 0.2}}\" (default: all defaults)"


def add_global_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--domain-id", type=int, default=None,
                        help="DDS domain (default: ROS_DOMAIN_ID or 0)")
    parser.add_argument("--idl-path", action="append", default=[], metavar="DIR",
                        help="extra IDL directory (repeatable; also RCAN_RTPS_IDL_PATH)")
    parser.add_argument("--localhost", action="store_true", default=None,
                        help="discover peers on this machine only")
    parser.add_argument("--distro", choices=("humble", "jazzy", "kilted"), default=None,
                        help="ROS distro of the graph (default: ROS_DISTRO or jazzy)")


def make_store(args: argparse.Namespace) -> TypeStore:
    return TypeStore([*args.idl_path, *env_idl_paths()], args.distro)


def make_node(args: argparse.Namespace) -> RosNode:
    # Hidden (leading '_') like ros2cli's own nodes, so `node list` leaves it out.
    return RosNode(f"_rcan_rtps_cli_{os.getpid()}", "/", domain_id=args.domain_id,
                   localhost=args.localhost, store=make_store(args))


def parse_values(text: str) -> Any:
    """VALUES as ros2cli takes them: YAML (an empty string means all defaults)."""
    try:
        return yaml.safe_load(text) if text.strip() else {}
    except yaml.YAMLError as exc:
        raise ValueFitError("", f"VALUES is not valid YAML: {exc}") from None


def dump(values: Any) -> str:
    return yaml.safe_dump(values, sort_keys=False, allow_unicode=True).rstrip()


def alone_hint(args: argparse.Namespace, node: RosNode, graph: RosGraph) -> str:
    """What to try next when the graph shows nobody but this tool; '' when others are there."""
    if any(name != node.name for _, name in graph.nodes()):
        return ""
    where = f"nothing found on ROS domain {node.domain_id}"
    if localhost_requested(args.localhost):
        return f"{where}: is anything running with this ROS_DOMAIN_ID (or --domain-id)?"
    return (f"{where}; the demo (`rcan-rtps run --sim`) keeps to loopback: add `--localhost` "
            "(or set ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST)")


def warn_if_alone(args: argparse.Namespace, node: RosNode, graph: RosGraph) -> None:
    hint = alone_hint(args, node, graph)
    if hint:
        print(f"rcan-rtps: {hint}", file=sys.stderr)
