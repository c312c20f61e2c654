"""Load: 500 concurrent clients, 20 commands each, over keep-alive connections (a bounded
connector) to the app on 127.0.0.1 — no 5xx, no hang, every decision in the verified chain."""

from __future__ import annotations

import asyncio
import uuid
from collections import Counter
from pathlib import Path

import aiohttp
import pytest

from rcan_rtps.governance import verify
from tests.api.apihelpers import TOKENS, Api

CLIENTS = 500
COMMANDS = 20
CONNECTIONS = 100
PRINCIPALS = ["planner", "lessee", "ops", "ops2", "root"]
BOUND_S = 600  # a hang fails the test instead of stalling the run


@pytest.mark.slow
async def test_500_clients_20_commands_each(tmp_path: Path) -> None:
    api = await Api(tmp_path).start()
    try:
        await _load(api)
    finally:
        await api.close()


async def _load(api: Api) -> None:
    url = str(api.http.make_url("/api/command"))
    results: list[tuple[int, dict[str, object]]] = []

    async def client(session: aiohttp.ClientSession, n: int) -> None:
        who = PRINCIPALS[n % len(PRINCIPALS)]
        headers = {"Authorization": f"Bearer {TOKENS[who]}"}
        for i in range(COMMANDS):
            body = {"action": "move", "message_id": str(uuid.uuid4()),
                    "params": {"linear_x": 0.1 * (i % 5), "angular_z": 0.05},
                    "ai_provider": "load", "ai_model": f"client-{n}", "confidence": 0.9,
                    "thought_id": f"{n}-{i}"}
            async with session.post(url, json=body, headers=headers) as resp:
                results.append((resp.status, await resp.json()))

    connector = aiohttp.TCPConnector(limit=CONNECTIONS, force_close=False)
    async with aiohttp.ClientSession(connector=connector) as session:
        await asyncio.wait_for(asyncio.gather(*(client(session, n) for n in range(CLIENTS))),
                               timeout=BOUND_S)

    statuses = Counter(status for status, _ in results)
    assert statuses == {200: CLIENTS * COMMANDS}, statuses
    assert len(api.dispatcher.calls) == CLIENTS * COMMANDS

    entries = api.entries
    by_id = {e["audit_id"]: e for e in entries}
    answered = [str(body["audit_id"]) for _, body in results]
    assert len(set(answered)) == CLIENTS * COMMANDS
    assert all(by_id[a]["event"] == "COMMAND_DISPATCHED" for a in answered)
    assert all(by_id[a]["ai"]["provider"] == "load" for a in answered)
    assert [e["seq"] for e in entries] == list(range(1, len(entries) + 1))
    assert api.log is not None
    head = verify(api.tmp / "audit.jsonl", api.log.public_key)
    # Each move's velocity stream ended (replaced by the next one): an entry each.
    ended = [e for e in entries if e["event"] == "STREAM_ENDED"]
    assert head.count == len(entries) == CLIENTS * COMMANDS + len(ended)
