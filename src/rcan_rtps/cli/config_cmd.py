"""`rcan-rtps config check FILE`: exit 0 for a valid config, else print every issue and exit 1."""

from __future__ import annotations

import argparse
import sys

from rcan_rtps.config import ConfigError, load_config


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    config = subparsers.add_parser("config", help="work with .rcan.yaml files")
    actions = config.add_subparsers(dest="config_command", required=True)
    check = actions.add_parser("check", help="validate a config file, listing every problem")
    check.add_argument("file", metavar="FILE")
    check.set_defaults(func=check_command)


def check_command(args: argparse.Namespace) -> int:
    try:
        config = load_config(args.file)
    except ConfigError as exc:
        print(str(exc), file=sys.stderr)
        return 1
    print(f"{args.file}: ok ({config.robot.ruri})")
    return 0
