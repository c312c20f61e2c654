"""Who makes a tool call, and through what (no MCP SDK import: the bridge builds seats)."""

from __future__ import annotations

from dataclasses import dataclass

from .keepalive import Keepalive
from .ports import RobotApi


@dataclass(frozen=True)
class Agent:
    """What the agent says it is, as every command it sends names it (§16 AI fields). The
    bridge refuses an AI command without a model: a seat without one sends none, and its
    commands are refused with that reason (stops excepted)."""

    provider: str | None
    model: str | None


@dataclass(frozen=True)
class Seat:
    """One agent's view of the bridge (`api`, as its principal), what it says it is, the
    heartbeats of its principal's motion, and its MCP session (None over stdio)."""

    api: RobotApi
    agent: Agent
    keepalive: Keepalive
    session: str | None = None
