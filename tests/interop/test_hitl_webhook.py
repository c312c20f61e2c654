"""The whole bridge (`Bridge`) tells the configured `hitl.notify_webhook` of a held command
(bridge spec §3.1 flow 3 step 3, §10.3): the governor's webhook is tested on its own in
tests/governance/test_hitl.py; this is the wiring from `.rcan.yaml` to it."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from aiohttp import web
from local_http import serve_post

from rcan_rtps.bridge.runtime import Bridge, BridgeOptions

from .bridge_rig import bridge_config

TOKEN = "t" * 32
ARM = {"action": "arm_joint",
       "params": {"joints": ["j1"], "positions": [0.1], "duration_s": 1.0}}


class Hook:
    """A webhook receiver that holds every request open until `release` is set."""

    def __init__(self) -> None:
        self.received: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
        self.release = asyncio.Event()

    async def handle(self, request: web.Request) -> web.Response:
        await self.received.put(await request.json())
        await self.release.wait()
        return web.Response(status=204)


@pytest.fixture
async def hook() -> AsyncIterator[tuple[Hook, str]]:
    receiver = Hook()
    runner, url = await serve_post("/hitl", receiver.handle)
    try:
        yield receiver, url
    finally:
        receiver.release.set()
        await runner.cleanup()


async def test_the_configured_webhook_hears_of_a_held_command_without_holding_it_up(
        tmp_path: Path, domain_id: int, hook: tuple[Hook, str]) -> None:
    receiver, url = hook
    config = bridge_config(tmp_path, domain_id, extra=(
        f"hitl:\n  notify_webhook: {url}\n"
        "  gates:\n    - {action: arm_joint, require_auth: true}\n"))
    bridge = Bridge(config, BridgeOptions(port=0, mdns=False,
                                          env={"RCAN_BRIDGE_TOKEN": TOKEN}))
    await bridge.start()
    try:
        headers = {"Authorization": f"Bearer {TOKEN}"}
        async with (aiohttp.ClientSession(headers=headers) as http,
                    http.post(bridge.url + "/api/command", json=ARM) as resp):
            status, body = resp.status, await resp.json()
        # Answered while the webhook still holds its request open: it never blocks.
        assert (status, body["outcome"]) == (202, "pending_auth"), body
        message = await asyncio.wait_for(receiver.received.get(), 30)
        assert not receiver.release.is_set()
        assert message["message_type"] == "PENDING_AUTH"
        assert message["pending_id"] == body["pending_id"]
        assert message["expires_at_ms"] == body["expires_at_ms"]
        assert message["original_command"]["action"] == "arm_joint"
        assert message["requires_auth_from_role"] == "OWNER"
    finally:
        receiver.release.set()
        await bridge.stop()
