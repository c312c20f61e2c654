"""`rcan-rtps mcp`'s client of the bridge (`BridgeClient`) when the MCP call it serves is
cancelled: a stop goes on to the bridge (it must stop all the same), anything else that is not
motion goes no further than its caller — a `clear_estop` its client no longer wants is not
sent on. (Motion: tests/mcp/test_mcp_stdio_cancel.py.) Against the API in process."""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path
from typing import Any

import pytest
from aiohttp import web
from aiohttp.test_utils import TestClient, TestServer
from aiohttp.typedefs import Handler
from waiting import eventually

from rcan_rtps.mcp_server import bridge as bridge_module
from rcan_rtps.mcp_server.bridge import BridgeClient
from tests.api.apihelpers import TOKENS, Api


async def cancelled_after_a_turn(bridge: BridgeClient, body: dict[str, Any]) -> None:
    """`body` sent, its caller cancelled one loop turn later: the command has begun (a request
    carried on is under way by then), its connection not yet made."""
    call = asyncio.ensure_future(bridge.command(body))
    await asyncio.sleep(0)
    call.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await call


async def test_a_cancelled_clear_estop_is_not_sent_on(tmp_path: Path) -> None:
    api = await Api(tmp_path).start()
    try:
        status, estopped = await api.command("ops", {"action": "estop"})
        assert (status, estopped["outcome"]) == (200, "executed"), estopped
        async with BridgeClient(str(api.http.make_url("/")), TOKENS["ops"]) as bridge:
            await cancelled_after_a_turn(bridge, {"action": "clear_estop"})
            stopped = await bridge.command({"action": "stop"})  # answered after it
            assert stopped.ok, stopped
        # Leaving waited for every request carried on: a clear sent on is decided by now.
        assert api.gov.latch.latched
        assert [e for e in api.entries if e["event"] == "ESTOP_CLEARED"] == []
    finally:
        await api.close()


async def test_a_cancelled_stop_still_stops(tmp_path: Path) -> None:
    api = await Api(tmp_path).start()
    try:
        status, moved = await api.command("ops", {"action": "move",
                                                  "params": {"linear_x": 0.3}})
        assert (status, moved["outcome"]) == (200, "executed"), moved
        async with BridgeClient(str(api.http.make_url("/")), TOKENS["planner"]) as bridge:
            await cancelled_after_a_turn(bridge, {"action": "stop"})
        await eventually(lambda: api.gov.streams.active is None, what="the stop")
        assert [e["principal"] for e in api.entries
                if e["event"] == "COMMAND_DISPATCHED" and e["action_type"] == "stop"] == [
                    "planner"]
    finally:
        await api.close()


async def test_a_bridge_without_the_cancel_route_is_named_too_old_once(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
        ) -> None:
    """A bridge that predates POST /api/command/cancel answers it 404 (as its router answers
    any unknown route): the server logs, once, that the bridge is too old to withdraw a
    cancelled motion call and that the agent should send stop. Before, it logged nothing."""
    monkeypatch.setattr(bridge_module, "_warned_too_old", False)
    api = Api(tmp_path)
    app = await api.build()

    @web.middleware
    async def without_cancel(request: web.Request, handler: Handler) -> web.StreamResponse:
        if request.path == "/api/command/cancel":
            raise web.HTTPNotFound()  # innermost: as the router's own 404 would
        return await handler(request)

    app.middlewares.append(without_cancel)
    api.client = TestClient(TestServer(app, host="127.0.0.1"))
    await api.client.start_server()
    try:
        async with BridgeClient(str(api.http.make_url("/")), TOKENS["planner"]) as bridge:
            for _ in range(2):
                told = await bridge.cancel_motion()
                assert told.status == 404, told
        warned = [r for r in caplog.records if "too old" in r.getMessage()]
        assert len(warned) == 1, caplog.records
        assert "send stop" in warned[0].getMessage() and warned[0].levelname == "WARNING"
    finally:
        await api.close()
