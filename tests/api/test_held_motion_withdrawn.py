"""Held motion leaves the approvers' list when a stop makes it unapprovable, over the API.

A principal's WebSocket closing withdraws its motion held for a human (nobody else's): an
approval must not start motion for a client that is gone. A `stop` withdraws all held
motion (red team 25 had it refused `stopped` when approved later, but still listed). Either
way an approver's socket is sent the list without it, and its issuer reads `hitl_withdrawn`
in `GET /api/hitl/pending/{id}`."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from waiting import eventually

from rcan_rtps.governance.governor import CONNECTION_CLOSED, ROBOT_STOPPED
from tests.api.apihelpers import Api, auth, next_frame
from tests.api.test_hitl_reviews import ARM, hold


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[Api]:
    api = await Api(tmp_path).start()
    yield api
    await api.close()


async def _next(ws: aiohttp.ClientWebSocketResponse, kind: str) -> dict[str, Any]:
    """The body of the next frame of `kind`, skipping the others."""
    return dict((await next_frame(ws, kind))["body"])


async def _listed_until(ws: aiohttp.ClientWebSocketResponse, wanted: set[str]) -> None:
    """Approvals frames until one lists `wanted` (each frame is a change of the list)."""
    while {p["pending_id"] for p in (await _next(ws, "approvals"))["pending"]} != wanted:
        pass


def _withdrawals(api: Api) -> dict[str, tuple[str, list[str | None]]]:
    return {e["pending_id"]: (e["principal"], [r.get("reason") for r in e["approvals"]])
            for e in api.entries if e["event"] == "HITL_WITHDRAWN"}


async def _withdrawn_for_its_issuer(api: Api, pending_id: str, issuer: str) -> None:
    async def read() -> dict[str, Any]:  # `resolving` until its entry is durable
        status, body = await api.call("GET", f"/api/hitl/pending/{pending_id}", issuer)
        assert (status, body["state"]) == (200, "resolved"), body
        return dict(body)

    body = await eventually(read)
    assert body["decision"]["reason"] == "hitl_withdrawn", body
    status, body = await api.call("POST", "/api/hitl/authorize", "ops",
                                  body={"pending_id": pending_id})
    assert (status, body["reason"]) == (404, "pending_not_found"), body


async def test_a_closed_socket_withdraws_its_principals_held_motion(api: Api) -> None:
    theirs = await hold(api, "slow")  # another principal's, over REST: it stays
    async with api.http.ws_connect("/api/ws", headers=auth("ops")) as approver:
        await _listed_until(approver, {theirs})
        planner = await api.http.ws_connect("/api/ws", headers=auth("planner"))
        await planner.send_str(json.dumps(ARM))
        held = await _next(planner, "outcome")
        assert held["outcome"] == "pending_auth", held
        mine = held["pending_id"]
        await _listed_until(approver, {theirs, mine})
        await planner.close()
        await _listed_until(approver, {theirs})
    await eventually(lambda: mine in _withdrawals(api))  # out of the list, then its entry
    assert _withdrawals(api) == {mine: ("planner", [CONNECTION_CLOSED])}
    assert [e for e in api.entries if e["event"] == "COMMAND_REJECTED"] == []  # once
    await _withdrawn_for_its_issuer(api, mine, "planner")
    assert api.dispatcher.calls == []
    status, body = await api.call("POST", "/api/hitl/authorize", "ops",
                                  body={"pending_id": theirs})
    assert (status, body["outcome"]) == (200, "executed"), body


async def test_a_stop_withdraws_all_held_motion(api: Api) -> None:
    held = {await hold(api, "planner"), await hold(api, "slow")}
    async with api.http.ws_connect("/api/ws", headers=auth("ops")) as approver:
        await _listed_until(approver, held)
        status, body = await api.command("ops2", {"action": "stop"})
        assert (status, body["outcome"]) == (200, "executed"), body
        await _listed_until(approver, set())
    await eventually(lambda: len(_withdrawals(api)) == len(held))
    why = ROBOT_STOPPED.format("a stop by 'ops2'")
    issuers = {pending_id: who for pending_id, (who, _) in _withdrawals(api).items()}
    assert _withdrawals(api) == {pending_id: (issuers[pending_id], [why]) for pending_id in held}
    assert sorted(issuers.values()) == ["planner", "slow"]
    for pending_id, issuer in issuers.items():
        await _withdrawn_for_its_issuer(api, pending_id, issuer)
    assert [a for a, _ in api.dispatcher.calls] == ["stop"]
