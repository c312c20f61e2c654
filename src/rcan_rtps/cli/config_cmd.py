"""`rcan-rtps config check FILE`: exit 0 for a valid config, else print every issue and exit 1."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Mapping

from rcan_rtps.config import ConfigError, RcanConfig, load_config
from rcan_rtps.governance.rbac import MIN_TOKEN_BYTES


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    config = subparsers.add_parser("config", help="work with .rcan.yaml files")
    actions = config.add_subparsers(dest="config_command", required=True)
    check = actions.add_parser(
        "check", help="validate a config file, listing every problem",
        description="Validates FILE and checks that every token variable it names is set "
        "here, as `rcan-rtps run` needs (--file-only: for a machine that will not run it).")
    check.add_argument("file", metavar="FILE", help="the .rcan.yaml to check")
    check.add_argument("--file-only", action="store_true",
                       help="check the file alone, not the token environment variables "
                       "(for checking a config on a machine that will not run it)")
    check.set_defaults(func=check_command)


def check_command(args: argparse.Namespace) -> int:
    try:
        config = load_config(args.file)
    except ConfigError as exc:
        print(str(exc), file=sys.stderr)
        return 1
    missing = [] if args.file_only else missing_tokens(config, os.environ)
    if missing:
        print(f"{args.file}: valid, but `rcan-rtps run` would fail here: token variables "
              f"unset or shorter than {MIN_TOKEN_BYTES} bytes: {', '.join(missing)} "
              "(--file-only skips this check)", file=sys.stderr)
        return 1
    print(f"{args.file}: ok ({config.robot.ruri})")
    return 0


def missing_tokens(config: RcanConfig, env: Mapping[str, str]) -> list[str]:
    """The token variables the config names that cannot authenticate anybody as they are."""
    api = config.bridge.api
    names = [p.token_env for p in api.principals if p.token_env]
    if not api.principals and api.auth_token_env:
        names.append(api.auth_token_env)
    return [n for n in dict.fromkeys(names)
            if len(env.get(n, "").encode()) < MIN_TOKEN_BYTES]
