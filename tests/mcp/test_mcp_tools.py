"""Issue 25: the MCP tools are derived from the action registry — with the SDK's own client,
in process (no bridge is needed to list them): a registry action added here is a tool, with
its params' schema; a move is timed; what fails is a tool error, never a traceback."""

from __future__ import annotations

import contextlib
import socket
from collections.abc import AsyncIterator
from types import MappingProxyType
from typing import Annotated, Any

import msgspec
import pytest
from mcp import Client
from mcp_types import Implementation

from rcan_rtps.mcp_server.bridge import BridgeClient
from rcan_rtps.mcp_server.keepalive import Keepalive
from rcan_rtps.mcp_server.seat import Agent, Seat
from rcan_rtps.mcp_server.server import RobotTools, build_server
from rcan_rtps.mcp_server.tools import READS, action_tool, derive_tools
from rcan_rtps.rcan import Role
from rcan_rtps.rcan._types import ActionParams
from rcan_rtps.rcan.actions import ActionSpec, Effect, Invariant, NoRoute, _registry, names

READ_TOOLS = {t.name for t in READS}


class BeepParams(ActionParams, frozen=True):
    volume: Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
    pattern: str | None = None


BEEP = ActionSpec(name="beep", summary="Beep (a test's action).", params=BeepParams,
                  effect=Effect.LOCK, default_role=Role.USER, ros=NoRoute(),
                  invariants=(Invariant.FINITE,))


def closed_port() -> int:
    """A loopback port nothing listens on (bound, then released)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@contextlib.asynccontextmanager
async def agent_client() -> AsyncIterator[Client]:
    """The SDK's client, in process, on a server whose bridge does not answer (a context
    manager, not a fixture: the SDK's task groups must be left in the task that entered them).
    """
    async with BridgeClient(f"http://127.0.0.1:{closed_port()}", "agent-token") as bridge:
        seat = Seat(bridge, Agent("acme", "planner-7b"), Keepalive(bridge))
        tools = RobotTools(lambda ctx: seat)
        async with Client(build_server(tools),
                          client_info=Implementation(name="test-agent", version="1.2")) as c:
            yield c


async def listed(client: Client) -> dict[str, Any]:
    return {t.name: t for t in (await client.list_tools()).tools}


async def test_every_registry_action_is_a_tool() -> None:
    async with agent_client() as client:
        tools = await listed(client)
    assert set(tools) == set(names()) | READ_TOOLS
    for tool in tools.values():
        assert tool.input_schema["type"] == "object", tool.name
        assert tool.description
    move = tools["move"].input_schema
    assert "duration_s" in move["required"]  # timed, for an agent
    assert move["properties"]["duration_s"]["type"] == "number"
    assert move["properties"]["duration_s"]["maximum"] == 86400.0
    assert move["properties"]["linear_x"]["maximum"] == 1e9  # the registry's limits
    assert move["properties"]["confidence"]["maximum"] == 1.0
    assert move["additionalProperties"] is False
    assert "m/s" in tools["move"].description and "Timed" in tools["move"].description
    arm = tools["arm_joint"].input_schema
    assert arm["required"] == ["joints"] and "TrajectoryPoint" in arm["$defs"]
    assert "wait_for_approval" in tools["arm_joint"].description
    assert "Never refused" in tools["estop"].description
    assert set(tools["navigate"].input_schema["required"]) == {"x", "y", "yaw"}


async def test_an_action_added_to_the_registry_is_a_tool(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_registry, "ACTIONS",
                        MappingProxyType({**_registry.ACTIONS, "beep": BEEP}))
    async with BridgeClient(f"http://127.0.0.1:{closed_port()}", "t") as bridge:
        seat = Seat(bridge, Agent("acme", "m"), Keepalive(bridge))
        tools = RobotTools(lambda ctx: seat)
        async with Client(build_server(tools)) as client:
            beep = (await listed(client))["beep"]
    assert beep.description.startswith("Beep (a test's action).")
    schema = beep.input_schema
    assert schema["required"] == ["volume"]
    assert schema["properties"]["volume"] == {"type": "number", "minimum": 0.0,
                                              "maximum": 1.0}
    assert {"pattern", "confidence", "reasoning"} <= set(schema["properties"])


def test_a_streamed_action_that_cannot_be_timed_is_not_offered() -> None:
    class HeldParams(ActionParams, frozen=True):
        linear_x: float = 0.0

    from rcan_rtps.rcan.actions import action_spec
    untimed = ActionSpec(name="creep", summary="s", params=HeldParams, effect=Effect.MOTION,
                         default_role=Role.USER, ros=action_spec("move").ros,
                         invariants=(Invariant.ESTOP_GUARD, Invariant.FINITE), streamed=True)
    assert action_tool(untimed) is None
    assert "creep" not in derive_tools([untimed])


def test_a_parameter_named_like_an_agent_statement_is_refused() -> None:
    class Clash(ActionParams, frozen=True):
        confidence: float = 0.0

    clash = ActionSpec(name="clash", summary="s", params=Clash, effect=Effect.LOCK,
                       default_role=Role.USER, ros=NoRoute(), invariants=(Invariant.FINITE,))
    with pytest.raises(ValueError, match="clash"):
        derive_tools([clash])


async def test_an_untimed_move_is_refused_before_the_bridge() -> None:
    async with agent_client() as client:
        done = await client.call_tool("move", {"linear_x": 0.2, "confidence": 0.9})
    assert done.is_error
    assert done.structured_content == {
        "error_code": "SCHEMA_VALIDATION_FAILED",
        "reason": "`duration_s` is required: a move an agent starts is timed"}


async def test_an_unreachable_bridge_is_a_tool_error_without_traceback() -> None:
    async with agent_client() as client:
        for name, args in (("estop", {}), ("get_status", {}),
                           ("wait_for_approval", {"pending_id": "abc", "timeout_s": 1})):
            done = await client.call_tool(name, args)
            assert done.is_error, name
            assert done.structured_content is not None
            assert done.structured_content["error_code"] == "BRIDGE_UNAVAILABLE", name
            text = done.content[0].text  # type: ignore[union-attr]
            assert "Traceback" not in text and "did not answer" in text, text
        unknown = await client.call_tool("fly", {})
    assert unknown.is_error and unknown.structured_content["error_code"] == "UNKNOWN_TOOL"
