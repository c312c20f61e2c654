"""What every graph command shares: global options and a short-lived hidden node."""

from __future__ import annotations

import argparse
import os
from typing import Any

import yaml

from ..ros.errors import ValueFitError
from ..ros.participant import RosNode
from ..ros.typesys.store import TypeStore, env_idl_paths


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
