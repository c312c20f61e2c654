"""`rcan-rtps discover`: RCAN robots announced over mDNS (`_rcan._tcp.local.`), with their TXT."""

from __future__ import annotations

import argparse
import json

from .. import _stop_signals as stop_signals
from .._printable import shown


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser("discover", help="list RCAN robots on the network (mDNS)")
    parser.add_argument("--timeout", type=float, default=3.0, metavar="S",
                        help="listen for S seconds (default 3)")
    parser.add_argument("--json", action="store_true", help="one JSON object per robot")
    parser.add_argument("--interface", action="append", default=None, metavar="IP",
                        help="only this interface address (repeatable; default: all)")
    parser.set_defaults(func=lambda a: stop_signals.run(_discover(a)))


async def _discover(args: argparse.Namespace) -> int:
    if not 0 < args.timeout <= 3600:
        raise ValueError("--timeout must be in (0, 3600] seconds")
    from ..bridge.mdns import browse  # zeroconf only when this command runs

    robots = await browse(args.timeout, interfaces=args.interface)
    for robot in robots:
        if args.json:
            print(json.dumps({"instance": robot.instance, "host": robot.host,
                              "port": robot.port, "addresses": robot.addresses,
                              "txt": robot.txt}, sort_keys=True))
            continue
        where = ", ".join(f"{a}:{robot.port}" for a in robot.addresses) or "?"
        print(f"{shown(robot.instance)}  {shown(robot.txt.get('ruri', '?'))}  [{where}]")
        for key in sorted(robot.txt):
            print(f"    {shown(key)}={shown(robot.txt[key])}")
    if not robots and not args.json:
        print(f"no RCAN robots found in {args.timeout:g} s")
    return 0
