"""What the MCP server needs of a bridge: `RobotApi`, one principal's view of its API.

Two implementations: `bridge.BridgeClient`, the REST API with the agent's token (`rcan-rtps
mcp`, over stdio), and the bridge's own `/mcp` endpoint (`rcan_rtps.api._mcp`), which calls
the same functions its REST handlers call, as the principal that authenticated the request.
Either way a reply is what the REST API would have answered: its status and JSON body,
refusals included — deciding is the bridge's.
"""

from __future__ import annotations

from collections.abc import Awaitable
from dataclasses import dataclass
from typing import Any, Protocol

from . import McpServerError


class BridgeUnavailable(McpServerError):
    """No usable reply from the bridge."""


@dataclass(frozen=True)
class Reply:
    status: int
    body: dict[str, Any]

    @property
    def ok(self) -> bool:
        return self.status < 400


@dataclass(frozen=True)
class Blob:
    """An image the bridge served (GET /api/images/{name} when it had a frame)."""

    mime: str
    data: bytes


class RobotApi(Protocol):
    """The bridge as one principal sees it; each call as its REST route answers it."""

    async def command(self, body: dict[str, Any]) -> Reply:
        """POST /api/command."""

    async def motion(self, body: dict[str, Any]) -> Reply:
        """POST /api/command of a motion command (`move`, `navigate`, ...) that its caller
        may cancel (its MCP client's `notifications/cancelled`): cancelled before its reply,
        the bridge is told at once (`cancel_motion`)."""

    def cancel_motion(self) -> Awaitable[Reply]:
        """POST /api/command/cancel, under way when this returns: a motion command of the
        principal's was cancelled by its client; the principal's motion that has not started
        never does, and what of it runs stops (its own alone: `Governor.command_cancelled`)."""

    async def heartbeat(self) -> Reply:
        """POST /api/heartbeat."""

    async def status(self) -> Reply:
        """GET /api/status."""

    async def goals(self) -> Reply:
        """GET /api/goals."""

    async def goal(self, goal_id: str) -> Reply:
        """GET /api/goals/{goal_id}."""

    async def pending(self, pending_id: str) -> Reply:
        """GET /api/hitl/pending/{pending_id}."""

    async def my_pending(self) -> Reply:
        """GET /api/hitl/pending?mine=true: the caller's own held commands."""

    async def my_audit(self, last: int) -> Reply:
        """GET /api/audit/mine?last=N: the caller's own newest entries."""

    async def safety_manifest(self) -> Reply:
        """GET /api/safety/manifest (the limits every command is held to)."""

    async def images(self) -> Reply:
        """GET /api/images: the configured cameras."""

    async def image(self, name: str) -> Reply | Blob:
        """GET /api/images/{name}: its newest frame, or why not."""
