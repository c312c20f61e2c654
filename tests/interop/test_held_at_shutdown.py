"""`rcan-rtps run --sim` stopped (SIGINT, its graceful path) while commands wait for a human.

Held commands live in the bridge's memory alone. Before, they ended with the process: each
stayed a PENDING_AUTH with no end in the signed log, and an issuer waiting on its WebSocket
for a held INVOKE's INVOKE_RESULT was never answered. Now the stop path withdraws each one
(HITL_WITHDRAWN, `withdrawn: the bridge stopped while it was held`) before the API closes,
and each held INVOKE is answered (INVOKE_RESULT `failure`): all of it in the log before
BRIDGE_STOPPED. (Its answer on a socket still open races the API's closing of the sockets,
and may lose: not checked here.) The INVOKEs are built with the official `rcan` SDK."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import aiohttp
from rcan.message import RCANResponse

from rcan_rtps.governance.governor import BRIDGE_STOPPING
from tests.interop.test_demo import _run_demo
from tests.interop.test_sdk_invoke import (
    outcome_frames,
    robot_of,
    sdk_invoke,
    sdk_wire,
)


async def test_a_stopping_bridge_withdraws_what_is_held_and_tells_its_issuer(
        tmp_path: Path, domain_id: int) -> None:
    running = _run_demo(tmp_path, domain_id, "--state-dir", str(tmp_path / "state"))
    demo = next(running)
    async with aiohttp.ClientSession() as http:
        robot = await robot_of(http, demo)
        by_socket, by_rest = sdk_invoke(robot, "raise_elbow"), sdk_invoke(robot, "raise_elbow")
        async with http.ws_connect(demo.url + "/api/ws",
                                   headers={"Authorization": f"Bearer {demo.user}"}) as ws:
            await ws.send_json(sdk_wire(by_socket))
            [held] = await outcome_frames(ws, 1)
            assert (held["http_status"], RCANResponse.from_dict(held).status) == (
                202, "pending"), held
            async with http.post(f"{demo.url}/api/command", json=sdk_wire(by_rest),
                                 headers={"Authorization": f"Bearer {demo.user}"}) as response:
                assert response.status == 202, await response.text()
            await asyncio.to_thread(next, running, None)  # SIGINT; exits 0, BRIDGE_STOPPED
    log = [json.loads(line) for line in demo.audit.read_text().splitlines()]
    events = [e["event"] for e in log]
    stopped = events.index("BRIDGE_STOPPED")
    for invoke in (by_socket, by_rest):
        mine = [e for e in log[:stopped] if e.get("message_id") == invoke.msg_id]
        assert [e["event"] for e in mine] == [
            "PENDING_AUTH", "HITL_WITHDRAWN", "INVOKE_RESULT"], mine
        withdrawn: dict[str, Any] = mine[1]
        assert [r["reason"] for r in withdrawn["approvals"]] == [BRIDGE_STOPPING], withdrawn
        assert (mine[2]["status"], mine[2]["deny_reason"]) == ("failure", BRIDGE_STOPPING)
    assert stopped == len(events) - 1
