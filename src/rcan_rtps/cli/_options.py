"""The options every command takes: light, so parsing a command line imports no graph tools."""

from __future__ import annotations

import argparse
from typing import Any

IDL_PATH_AFTER_VERB = "idl_path_after_verb"


def add_global_options(parser: argparse.ArgumentParser, *, after_verb: bool = False) -> None:
    """The options of every command. `after_verb`: the copy a command's own parser gets, so
    they may follow the verb too; its defaults are SUPPRESS, so an option left out there
    keeps what was given before the verb, and one given there wins."""
    def default(value: Any) -> Any:
        return argparse.SUPPRESS if after_verb else value

    parser.add_argument("--domain-id", type=int, default=default(None),
                        help="DDS domain (default: ROS_DOMAIN_ID or 0)")
    # Repeatable: directories given before and after the verb add up (see merge_*).
    parser.add_argument("--idl-path", action="append", default=default([]), metavar="DIR",
                        dest=IDL_PATH_AFTER_VERB if after_verb else "idl_path",
                        help="extra IDL directory (repeatable; also RCAN_RTPS_IDL_PATH)")
    parser.add_argument("--localhost", action="store_true", default=default(None),
                        help="discover peers on this machine only")
    parser.add_argument("--distro", choices=("humble", "jazzy", "kilted"), default=default(None),
                        help="ROS distro of the graph (default: ROS_DISTRO or jazzy)")


def merge_global_options(args: argparse.Namespace) -> argparse.Namespace:
    """One `idl_path` list: the directories given before the verb, then those after it."""
    args.idl_path = [*args.idl_path, *vars(args).pop(IDL_PATH_AFTER_VERB, [])]
    return args


def add_spin_time(parser: argparse.ArgumentParser, default: float = 1.5) -> None:
    """`--spin-time`: how long a graph command listens before it answers."""
    parser.add_argument("--spin-time", type=float, default=default,
                        help=f"seconds to listen for the graph before answering "
                             f"(default {default:g})")
