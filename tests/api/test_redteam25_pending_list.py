"""Red team 25: the list of held commands shows each reader what it may read, no more.

Whoever may list held commands (`hitl_list_role`: the lowest role any gate names) was shown
every held command — its issuer, its parameters, its message id — over `GET /api/hitl/pending`
and the WebSocket's approvals frames, also those it could not approve and that
`GET /api/hitl/pending/{id}` answered it 404 (not found) for. A LEASEE that may approve
navigation saw the arm moves held for an OWNER."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from tests.api.apihelpers import Api, auth
from tests.api.test_hitl_reviews import hold

GATES = ("[{action: arm_joint, require_auth: true, authorized_roles: [OWNER]}, "
         "{action: navigate, require_auth: true, authorized_roles: [LEASEE]}]")
NAVIGATE = {"action": "navigate", "params": {"x": 1.0, "y": 1.0, "yaw": 0.0}}


@pytest.fixture
async def gated(tmp_path: Path) -> AsyncIterator[Api]:
    api = await Api(tmp_path, gates=GATES).start()
    yield api
    await api.close()


async def held_navigation(api: Api, who: str) -> str:
    status, body = await api.command(who, NAVIGATE)
    assert (status, body["outcome"]) == (202, "pending_auth"), body
    return str(body["pending_id"])


async def listed(api: Api, who: str) -> set[str]:
    status, body = await api.call("GET", "/api/hitl/pending", who)
    assert status == 200, body
    return {p["pending_id"] for p in body["pending"]}


async def approvals_frame(api: Api, who: str) -> set[str]:
    async with api.http.ws_connect("/api/ws", headers=auth(who)) as ws:
        while True:
            msg = await asyncio.wait_for(ws.receive(), timeout=30)
            assert msg.type is aiohttp.WSMsgType.TEXT, msg
            frame: dict[str, Any] = json.loads(msg.data)
            if frame["type"] == "approvals":
                return {p["pending_id"] for p in frame["body"]["pending"]}


async def test_a_reader_lists_what_it_could_approve_and_its_own(gated: Api) -> None:
    arm = await hold(gated, "planner")  # for an OWNER
    navigation = await held_navigation(gated, "planner")  # for a LEASEE
    own = await held_navigation(gated, "lessee")
    assert (await gated.call("GET", f"/api/hitl/pending/{arm}", "lessee"))[0] == 404
    assert await listed(gated, "lessee") == {navigation, own}
    assert await listed(gated, "ops") == {arm, navigation, own}  # an OWNER: every one
    assert await approvals_frame(gated, "ops") == {arm, navigation, own}
    # Last: a principal's socket closing withdraws its held motion (`own`, here).
    assert await approvals_frame(gated, "lessee") == {navigation, own}
