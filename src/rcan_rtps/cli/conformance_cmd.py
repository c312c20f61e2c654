"""`rcan-rtps conformance --url URL --token T|--token-env VAR [--level L1|L2|L3]`: the
published RCAN conformance suite's cases against a running bridge, one line per case.

It commands the robot: zero-velocity moves, an arm trajectory to where the arm already is,
an e-stop it clears again, and INVOKEs of one skill the bridge lists (GET /api/skills): by
default the first that moves nothing (a move fixed at zero velocity for a fixed duration, the
invoker setting nothing; the demo's `hold_still`), else the one `--skill` names. Run it
against a simulator or a robot that may be stopped.
"""

from __future__ import annotations

import argparse
import os
import sys

from .. import _stop_signals as stop_signals

_ROLES = ("GUEST", "USER", "LEASEE", "OWNER", "CREATOR")


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "conformance", help="run the published RCAN conformance suite against a bridge",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--url", required=True, help="the bridge's API, e.g. http://127.0.0.1:8765")
    owner = parser.add_mutually_exclusive_group(required=True)
    owner.add_argument("--token", help="an OWNER's bearer token (reads the audit, approves, "
                       "clears the e-stops the safety cases raise); --token=T if T begins "
                       "with '-'")
    owner.add_argument("--token-env", metavar="VAR", help="the environment variable holding "
                       "the OWNER's token (keeps it off the command line other users can see)")
    parser.add_argument("--token-for", metavar="ROLE=TOKEN", action="append", default=[],
                        type=_role_token, help="a token of another role the cases need "
                        "(GUEST, USER); repeatable")
    parser.add_argument("--level", choices=("L1", "L2", "L3"), default="L3",
                        help="run the cases up to this level (default L3: all)")
    parser.add_argument("--skill", metavar="NAME",
                        help="the skill the INVOKE cases invoke, as a USER and with no "
                             "parameters: choose a harmless one (default: one the bridge "
                             "lists that moves nothing)")
    parser.set_defaults(func=_conformance)


def _role_token(text: str) -> tuple[str, str]:
    role, sep, token = text.partition("=")
    if not sep or role.upper() not in _ROLES or not token:
        raise argparse.ArgumentTypeError(f"expected ROLE=TOKEN with ROLE one of {_ROLES}")
    if _has_control(token):
        raise argparse.ArgumentTypeError(f"{role.upper()}'s token {_CONTROL}")
    return role.upper(), token


# A token goes in an HTTP header, which aiohttp refuses (ValueError) with a line end in it.
_CONTROL = "has a control character (a line end read with it?): a bearer token is one line"


def _has_control(token: str) -> bool:
    return any(ord(c) < 32 or ord(c) == 127 for c in token)


def _owner_token(args: argparse.Namespace) -> str | None:
    """The OWNER's token, or None once the reason it is unusable was printed."""
    owner: str | None
    if args.token is not None:
        source, owner = "--token", str(args.token)
    else:
        source, owner = f"--token-env {args.token_env}", os.environ.get(args.token_env)
    problem = ("that variable is not set" if owner is None else
               "empty" if not owner else _CONTROL if _has_control(owner) else None)
    if problem is None:
        return owner
    print(f"rcan-rtps conformance: {source}: {problem} (it must hold an OWNER's bearer "
          "token)", file=sys.stderr)
    return None


def _conformance(args: argparse.Namespace) -> int:
    from rcan_rtps.conformance import load_suite, run_suite
    from rcan_rtps.conformance.runner import unusable

    suite = load_suite()
    source = suite.vendored.source
    print(f"RCAN conformance suite v{suite.version} ({source.repository}, {source.path} at "
          f"{source.snapshot_commit[:12]}), up to {args.level}, against {args.url}")
    owner = _owner_token(args)
    if owner is None:
        return 2
    tokens = {"OWNER": owner, **dict(args.token_for)}
    problem = stop_signals.run(unusable(args.url, tokens))
    if problem is not None:
        print(f"rcan-rtps conformance: {problem}", file=sys.stderr)
        return 2
    results = stop_signals.run(run_suite(suite, args.level, args.url, tokens,
                                         skill=args.skill,
                                         report=lambda r: print(r.line(), flush=True)))
    counts = {o: sum(r.outcome == o for r in results)
              for o in ("pass", "fail", "n/a", "out of scope")}
    print(", ".join(f"{n} {o}" for o, n in counts.items()))
    if counts["fail"]:
        print("not conformant: see the FAIL lines", file=sys.stderr)
        return 1
    return 0
