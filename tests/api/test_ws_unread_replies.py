"""A WebSocket client that sends and never reads its replies (red team 8's suspicion): its
e-stop, sent after a flood, must still be read and stop the robot; the bridge then closes the
socket of a client that does not read (1008).

The receive loop awaited each reply's send (a 429 once the socket's queue was full): with
the client not reading, the send waited for a drain that never came, no later frame was
read, and the e-stop behind the flood never reached the governor."""

from __future__ import annotations

import asyncio
import contextlib
import socket
from pathlib import Path

import pytest

from rcan_rtps.api._keys import SOCKETS
from tests.api.apihelpers import Api, auth

FLOOD = 100_000  # frames, each answered: far more than the buffers between us hold (~15 MB)
HANG_S = 60.0  # against a hang only: the e-stop latches well within it, or never
CLOSE_S = 10.0


async def test_an_estop_behind_replies_never_read_stops(tmp_path: Path,
                                                         caplog: pytest.LogCaptureFixture
                                                         ) -> None:
    api = await Api(tmp_path).start()
    ws = await api.http.ws_connect("/api/ws", headers=auth("ops"))
    sock = ws.get_extra_info("socket")
    assert sock is not None
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a client that reads nothing

    async def flood_then_estop() -> None:
        for n in range(FLOOD):
            await ws.send_str(f'{{"action": "status", "message_id": "flood-{n}"}}')
        await ws.send_str('{"action": "estop", "message_id": "the-estop"}')

    sending = asyncio.create_task(flood_then_estop())
    try:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + HANG_S
        while not api.gov.latch.latched and loop.time() < deadline:
            await asyncio.sleep(0.05)
        assert api.gov.latch.latched, "the e-stop behind the unread replies never stopped"
        assert [a for a, _ in api.dispatcher.calls if a == "estop"] == ["estop"]
        sockets = api.http.app[SOCKETS]
        while sockets and loop.time() < deadline:
            await asyncio.sleep(0.05)
        assert not sockets, "the socket of a client that does not read stayed open"
        assert "does not read its outcome frames: closed (1008)" in caplog.text
    finally:
        sending.cancel()
        await asyncio.gather(sending, return_exceptions=True)
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(ws.close(), CLOSE_S)
        await api.close()

