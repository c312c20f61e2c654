"""Red team 26: a WebSocket ticket does not outlive the JWT it was asked for with.

A ticket (`POST /api/ws-ticket`) lives 30 s and carries its issuer's principal, whose JWT
may run out sooner. Redeemed after that, the socket opened all the same: its first frames
pushed the status and the held commands its role may read to a credential that REST
refuses (401), before the first wait found it expired and closed it 1008. A ticket whose
principal's credential has run out is refused (401) before the handshake, as the JWT itself
would be."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from pathlib import Path

import aiohttp
import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from jwthelpers import expiring_jwt, jwt_issuer

from tests.api.apihelpers import Api
from tests.api.test_redteam25_pending_list import GATES, held_navigation


@pytest.fixture
async def jwt_gated(tmp_path: Path) -> AsyncIterator[tuple[Api, Ed25519PrivateKey]]:
    key, trusted = jwt_issuer(tmp_path)
    api = await Api(tmp_path, gates=GATES, api_extra=trusted).start()
    yield api, key
    await api.close()


def approver_token(api: Api, key: Ed25519PrivateKey, left_s: float) -> str:
    """A LEASEE's JWT (it may approve navigation) taken for `left_s` more seconds."""
    return expiring_jwt(key, api.clock.time(), left_s, sub="approver-3", role="LEASEE")


async def ticket(api: Api, jwt: str, good_for_s: float = 5) -> str:
    """A ticket, said to be good for as long as the JWT has left (`good_for_s`), not for
    the ticket's own 30 s."""
    async with api.http.post("/api/ws-ticket",
                             headers={"Authorization": f"Bearer {jwt}"}) as resp:
        assert resp.status == 200, await resp.text()
        body = await resp.json()
        assert body["expires_in_s"] == pytest.approx(good_for_s, abs=0.5), body
        return str(body["ticket"])


async def test_a_ticket_redeemed_after_its_jwt_ran_out_opens_no_socket(
        jwt_gated: tuple[Api, Ed25519PrivateKey]) -> None:
    api, key = jwt_gated
    held = await held_navigation(api, "planner")
    jwt = approver_token(api, key, 5)
    fresh, late = await ticket(api, jwt), await ticket(api, jwt)
    # While the token holds, its ticket's socket lists the held navigation.
    async with api.http.ws_connect(f"/api/ws?ticket={fresh}") as ws:
        while True:
            frame = json.loads((await asyncio.wait_for(ws.receive(), timeout=30)).data)
            if frame["type"] == "approvals":
                assert [p["pending_id"] for p in frame["body"]["pending"]] == [held]
                break
    api.clock.advance(10)  # the token has run out; the ticket (30 s) has not
    async with api.http.post("/api/ws-ticket",
                             headers={"Authorization": f"Bearer {jwt}"}) as resp:
        assert resp.status == 401  # (REST refuses the token)
    with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
        async with api.http.ws_connect(f"/api/ws?ticket={late}") as ws:
            frames = []
            async for msg in ws:
                frames.append(json.loads(msg.data)["type"])
            pytest.fail(f"a socket opened on an expired credential: {frames}, "
                        f"closed {ws.close_code}")
    assert refused.value.status == 401
    # Nothing of the expired credential's: the held command waits on.
    assert (await api.call("GET", f"/api/hitl/pending/{held}", "ops"))[1]["state"] == "pending"
