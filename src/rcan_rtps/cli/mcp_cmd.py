"""`rcan-rtps mcp`: an MCP server on stdio for an AI agent, in front of a running bridge.

It holds no robot and no governance of its own: every tool call is a request to the bridge's
REST API with the agent's token (see `rcan_rtps.mcp_server`). The SDK is the `mcp` extra,
imported only here and only when the command runs.
"""

from __future__ import annotations

import argparse
import os

from .. import _stop_signals as stop_signals

DEFAULT_URL = "http://127.0.0.1:8765"
EXTRA_HINT = "`rcan-rtps mcp` needs the MCP SDK: pip install 'rcan-rtps[mcp]'"


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "mcp", help="serve the robot's governed actions to an AI agent (MCP over stdio)",
        description="An MCP server on stdin/stdout for an AI agent's client (Claude Desktop, "
        "an IDE, an agent framework): the registry's actions as tools, the robot's status, "
        "goals and the agent's pending approvals, each call a request to a running bridge "
        "with the agent's token — the same roles, limits, approvals and audit as any client.")
    parser.add_argument("--url", default=DEFAULT_URL,
                        help=f"the bridge's API (default {DEFAULT_URL})")
    parser.add_argument("--token-env", required=True, metavar="VAR",
                        help="environment variable holding the agent's bearer token")
    parser.add_argument("--ai-provider", required=True, metavar="NAME",
                        help="the model's provider, recorded with every command (e.g. acme)")
    parser.add_argument("--ai-model", required=True, metavar="NAME",
                        help="the model, recorded with every command (the bridge refuses an "
                        "AI command that names none; an agent principal must name its own)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    token = os.environ.get(args.token_env, "")
    if not token:
        raise ValueError(f"--token-env {args.token_env}: that variable is not set (it must "
                         "hold the agent's bearer token)")
    for option, value in (("--ai-provider", args.ai_provider), ("--ai-model", args.ai_model)):
        if not value.strip() or len(value) > 256:
            raise ValueError(f"{option}: expected 1 to 256 characters")
    try:
        from ..mcp_server.server import serve_stdio
    except ModuleNotFoundError as exc:
        if exc.name is not None and exc.name.split(".")[0] in ("mcp", "mcp_types"):
            raise ValueError(EXTRA_HINT) from None
        raise
    from ..mcp_server.bridge import check_url
    from ..mcp_server.seat import Agent

    ended_by = stop_signals.run(serve_stdio(check_url(args.url), token,
                                            Agent(args.ai_provider, args.ai_model)))
    return 0 if ended_by is None else 128 + ended_by  # as the shell reports a signal's end
