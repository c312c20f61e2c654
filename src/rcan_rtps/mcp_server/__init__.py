"""`rcan-rtps mcp`: the robot's governed actions as MCP tools, for AI agents (issue 25).

An MCP server that is a client of a running bridge: every tool call is a request to its REST
API with the agent's own token, so the agent meets the same roles, limits, approvals and audit
as anyone else, and nothing reaches the robot around them.

- `tools`: the tools, derived from the action registry (no code per action) plus the reads an
  agent needs (status, goals, its pending approvals); no MCP SDK import.
- `bridge`: the REST client.
- `keepalive`: heartbeats for the motion this server started, while it runs.
- `server`: the MCP server on the official SDK's low-level `Server`, served over stdio.

Only `rcan-rtps mcp` imports this package (a bridge run never does), and only `server` needs
the `mcp` extra (`pip install 'rcan-rtps[mcp]'`).
"""

__all__ = ["McpServerError"]


class McpServerError(Exception):
    """Base of this package's errors."""
