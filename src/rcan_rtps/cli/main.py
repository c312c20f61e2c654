"""Entry point of `rcan-rtps`: argparse sub-commands, errors as messages, never tracebacks."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from .. import __version__
from ..config import ConfigError
from ..governance import GovernanceError
from ..rcan import RcanError
from ..ros.errors import WireError
from . import (
    action_cmd,
    audit_cmd,
    config_cmd,
    discover_cmd,
    interface_cmd,
    node_cmd,
    run_cmd,
    service_cmd,
    sim_cmd,
    topic_cmd,
)
from ._common import add_global_options

EXIT_ERROR = 1
EXIT_INTERRUPTED = 130


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rcan-rtps",
        description="RCAN governance for ROS 2 robots, as a plain DDS peer (no ROS needed).")
    parser.add_argument("--version", action="version", version=f"rcan-rtps {__version__}")
    add_global_options(parser)
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in (run_cmd, topic_cmd, node_cmd, interface_cmd, config_cmd, audit_cmd, sim_cmd,
                   service_cmd, action_cmd, discover_cmd):
        module.register(commands)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except (WireError, ConfigError, GovernanceError, RcanError, ValueError, OSError) as exc:
        print(f"rcan-rtps: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
