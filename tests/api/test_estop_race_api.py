"""E-stop and clear racing over the real transports: REST and WebSocket, different principals.

After each interleaving the HTTP/WS replies, the audit order, the latch, the latch file and the
last value sent to the robot must agree (the later of the two in the audit decides; an e-stop
that came before the clear was decided gets the clear refused 409 `estop_active`: it wins too).
"""

from __future__ import annotations

import asyncio
import json
import random
from typing import Any

import aiohttp
import pytest

from tests.api.apihelpers import Api, auth

ROUNDS = 150


def _seq(api: Api, audit_id: str) -> int:
    for line in (api.tmp / "audit.jsonl").read_text().splitlines():
        entry = json.loads(line)
        if entry["audit_id"] == audit_id:
            return int(entry["seq"])
    raise AssertionError(f"{audit_id} is not in the audit log")


def _last_sent(api: Api) -> bool | None:
    sent = [a == "estop" for a, _ in api.dispatcher.calls if a in ("estop", "clear_estop")]
    return sent[-1] if sent else None


def _persisted(api: Api) -> bool:
    return bool(json.loads((api.tmp / "estop.state").read_bytes())["latched"])


async def _ws_decide(ws: aiohttp.ClientWebSocketResponse, body: dict[str, Any]) -> Any:
    await ws.send_str(json.dumps(body))
    while True:
        frame = json.loads((await asyncio.wait_for(ws.receive(), 30)).data)
        if frame["type"] == "outcome":
            return frame["http_status"], frame["body"]


async def _rest_decide(api: Api, who: str, body: dict[str, Any]) -> Any:
    return await api.call("POST", "/api/command", who, body=body)


@pytest.mark.parametrize("transport", ["rest", "ws", "mixed"])
async def test_estop_and_clear_race_over_the_api(api: Api, transport: str) -> None:
    rng = random.Random(transport)
    viewer_ws = await api.http.ws_connect("/api/ws", headers=auth("viewer"))
    ops_ws = await api.http.ws_connect("/api/ws", headers=auth("ops"))
    orders = {"estop last": 0, "clear last": 0, "clear refused": 0}
    try:
        for trial in range(ROUNDS):
            use_ws = {"rest": (False, False), "ws": (True, True),
                      "mixed": (rng.random() < 0.5, rng.random() < 0.5)}[transport]

            async def estop(ws: bool = use_ws[0]) -> Any:
                await asyncio.sleep(rng.uniform(0, 0.003))
                if ws:
                    return await _ws_decide(viewer_ws, {"action": "estop"})
                return await _rest_decide(api, "viewer", {"action": "estop"})

            async def clear(ws: bool = use_ws[1]) -> Any:
                await asyncio.sleep(rng.uniform(0, 0.003))
                if ws:
                    return await _ws_decide(ops_ws, {"action": "clear_estop"})
                return await _rest_decide(api, "ops", {"action": "clear_estop"})

            (e_code, e_body), (c_code, c_body) = await asyncio.gather(estop(), clear())
            assert e_code == 200, (trial, e_body)
            if c_code == 409:  # overtaken: the e-stop came while the clear waited its turn
                assert c_body["reason"] == "estop_active", (trial, c_body)
                estop_last, order = True, "clear refused"
            else:
                assert c_code == 200, (trial, c_body)
                estop_last = _seq(api, e_body["audit_id"]) > _seq(api, c_body["audit_id"])
                order = "estop last" if estop_last else "clear last"
            orders[order] += 1
            assert api.gov.latch.latched is estop_last, trial
            assert _persisted(api) is estop_last, trial
            assert _last_sent(api) is estop_last, trial
            code, _ = await _rest_decide(api, "root", {"action": "move",
                                                       "params": {"linear_x": 0.1}})
            assert code == (409 if estop_last else 200), trial
    finally:
        await viewer_ws.close()
        await ops_ws.close()
    print(transport, orders)
    # both orders happened (a refused clear is the e-stop winning too)
    assert orders["clear last"] > 0 and orders["estop last"] + orders["clear refused"] > 0, orders
