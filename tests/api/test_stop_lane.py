"""Issue 9, the WebSocket edge: `stop`/`estop` never wait behind (or get refused by) the socket's
queue, and no bad frame or failing decision ends a socket's command handling."""

from __future__ import annotations

import asyncio
import json
import uuid
from collections import Counter
from typing import Any

import aiohttp
import pytest

from rcan_rtps.governance import Governor
from tests.api.apihelpers import Api, auth

WS_BACKLOG = 32  # ApiSettings.ws_max_in_flight


async def _outcome(ws: aiohttp.ClientWebSocketResponse) -> dict[str, Any]:
    """The next outcome frame (STATUS frames skipped)."""
    async def wait() -> dict[str, Any]:
        while True:
            msg = await ws.receive()
            assert msg.type is aiohttp.WSMsgType.TEXT, msg
            frame: dict[str, Any] = json.loads(msg.data)
            if frame["type"] == "outcome":
                return frame

    return await asyncio.wait_for(wait(), timeout=60)


def _cmd(action: str, **extra: Any) -> str:
    return json.dumps({"action": action, "message_id": str(uuid.uuid4()), **extra})


async def _held_socket(api: Api) -> aiohttp.ClientWebSocketResponse:
    """A planner socket whose first move is stuck in dispatch, so nothing queued moves on."""
    api.dispatcher.hold = asyncio.Event()
    ws = await api.http.ws_connect("/api/ws", headers=auth("planner"))
    await ws.send_str(_cmd("move", params={"linear_x": 0.1}))
    await asyncio.wait_for(api.dispatcher.entered.wait(), timeout=60)
    return ws


async def test_estop_behind_100_queued_moves_is_decided_at_once(api: Api) -> None:
    ws = await _held_socket(api)
    for _ in range(100):
        await ws.send_str(_cmd("move", params={"linear_x": 0.1}))
    # Mentions an e-stop but does not say one: no lane for it, the full queue refuses it.
    await ws.send_str('{"action": "move", "params": {"estop": 1}}')
    estop_id = str(uuid.uuid4())
    await ws.send_str(json.dumps({"action": "estop", "message_id": estop_id}))

    refused = 0
    while True:  # everything queued is stuck behind the held move; only refusals and the e-stop
        frame = await _outcome(ws)
        if frame["body"].get("message_id") == estop_id:
            break
        assert (frame["http_status"], frame["body"]["error_code"]) == (429, "RATE_LIMITED")
        refused += 1
    assert (frame["http_status"], frame["body"]["outcome"]) == (200, "executed")
    assert api.entry(frame["body"]["audit_id"])["event"] == "ESTOP"
    # Decided and dispatched while the move ahead of it is still held.
    assert not api.dispatcher.hold.is_set()
    assert [a for a, _ in api.dispatcher.calls] == ["estop"]
    assert api.gov.latch.latched

    api.dispatcher.hold.set()
    rest = [await _outcome(ws) for _ in range(1 + WS_BACKLOG)]
    statuses = Counter(f["http_status"] for f in rest)
    # The held move (it passed the latch before the e-stop; its stream never starts once the
    # latch is seen) and the queued moves, all refused by the latch; the overflow and the
    # move that mentions an e-stop got 429 above.
    assert refused == 100 - WS_BACKLOG + 1
    assert statuses == {409: WS_BACKLOG + 1}, statuses
    assert all(f["body"]["reason"] == "estop_active" for f in rest if f["http_status"] == 409)
    await ws.close()


async def test_stop_also_takes_the_lane(api: Api) -> None:
    ws = await _held_socket(api)
    for _ in range(WS_BACKLOG + 5):
        await ws.send_str(_cmd("move"))
    stop_id = str(uuid.uuid4())
    await ws.send_str(json.dumps({"action": "stop", "message_id": stop_id}))
    while (frame := await _outcome(ws))["body"].get("message_id") != stop_id:
        assert frame["http_status"] == 429
    assert (frame["http_status"], frame["body"]["outcome"]) == (200, "executed")
    assert ("stop", {}) in api.dispatcher.calls
    assert not api.dispatcher.hold.is_set()
    api.dispatcher.hold.set()
    await ws.close()


async def test_many_estops_are_all_decided_none_refused(api: Api) -> None:
    ws = await _held_socket(api)
    ids = [str(uuid.uuid4()) for _ in range(40)]  # more than the lane's width and the backlog
    for mid in ids:
        await ws.send_str(json.dumps({"action": "estop", "message_id": mid}))
    frames = [await _outcome(ws) for _ in ids]
    assert sorted(f["body"]["message_id"] for f in frames) == sorted(ids)
    assert {f["http_status"] for f in frames} == {200}
    api.dispatcher.hold.set()
    await ws.close()


async def test_bad_frames_never_end_the_socket(api: Api) -> None:
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        bad: list[tuple[bytes | str, int, str | None]] = [
            (b'{"action": "\xff"}', 400, "$"),  # invalid UTF-8 in a binary frame
            (b"\xff\xfe\x00", 400, "$"),
            (b'{"action": "move"', 400, "$"),  # not JSON
            ("not json at all", 400, "$"),
            ('{"action": "fly"}', 400, "$.action"),  # schema
            ('{"action": "move", "params": {"x": 1}}', 400, "$.params"),
            ('{"action": "move", "action": "move"}', 400, "$.action"),  # duplicate key
            ('{"action": "move", "pad": "' + "x" * (64 * 1024) + '"}', 413, None),  # oversize
        ]
        for frame_data, status, path in bad:
            before = len(api.entries)
            if isinstance(frame_data, bytes):
                await ws.send_bytes(frame_data)
            else:
                await ws.send_str(frame_data)
            frame = await _outcome(ws)
            assert frame["http_status"] == status, (frame_data[:40], frame)
            assert frame["body"].get("path") == path
            entry = api.entry(frame["body"]["audit_id"])  # audited for the principal
            assert (entry["event"], entry["principal"]) == ("COMMAND_REJECTED", "planner")
            assert len(api.entries) == before + 1
        # The same socket still works: an e-stop is decided and reaches the robot.
        await ws.send_str(_cmd("estop"))
        frame = await _outcome(ws)
        assert (frame["http_status"], frame["body"]["outcome"]) == (200, "executed")
        assert api.dispatcher.calls == [("estop", {})]


@pytest.mark.logs_traceback  # (a fault injected on purpose)
async def test_a_decision_that_raises_does_not_end_the_socket(
        api: Api, monkeypatch: Any) -> None:
    real = Governor.decide
    failures = 0

    async def flaky(self: Governor, command: Any, principal: Any) -> Any:
        nonlocal failures
        if command.action == "move" and failures == 0:
            failures += 1
            raise RuntimeError("bug in the bridge")
        return await real(self, command, principal)

    monkeypatch.setattr(Governor, "decide", flaky)
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        await ws.send_str(_cmd("move"))
        frame = await _outcome(ws)
        assert (frame["http_status"], frame["body"]["outcome"], frame["body"]["reason"]) == (
            503, "failed", "internal_error")
        await ws.send_str(_cmd("move"))
        assert (await _outcome(ws))["http_status"] == 200
        await ws.send_str(_cmd("estop"))
        assert (await _outcome(ws))["http_status"] == 200
    assert [a for a, _ in api.dispatcher.calls] == ["move", "estop"]
