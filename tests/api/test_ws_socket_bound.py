"""One principal's WebSockets are bounded (`_ws.MAX_SOCKETS_PER_PRINCIPAL`, beyond: 429 before
the handshake): a GUEST opened 300 and all were taken (red team 19) — with the common soft
limit of 1024 open files, a thousand would leave no descriptor for anyone's e-stop. The run
raises its soft limit toward the hard one (`bridge.open_files`)."""

from __future__ import annotations

import asyncio
import contextlib
import subprocess
import sys

import aiohttp
import pytest

from rcan_rtps.api._ws import MAX_SOCKETS_PER_PRINCIPAL
from tests.api.apihelpers import Api, auth


async def test_a_principal_holds_a_bounded_number_of_sockets(api: Api) -> None:
    async with contextlib.AsyncExitStack() as held:
        for _ in range(MAX_SOCKETS_PER_PRINCIPAL):
            await held.enter_async_context(api.http.ws_connect("/api/ws", headers=auth("viewer")))
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            await api.http.ws_connect("/api/ws", headers=auth("viewer"))
        assert refused.value.status == 429
        # others are not shut out; the bounded principal's e-stop still stops (REST)
        async with api.http.ws_connect("/api/ws", headers=auth("ops")) as other:
            assert not other.closed
        status, body = await api.command("viewer", {"action": "estop"})
        assert (status, body["outcome"]) == (200, "executed"), body
    assert api.gov.latch.latched
    # its sockets closed, its places are free again
    async with api.http.ws_connect("/api/ws", headers=auth("viewer")) as again:
        assert not again.closed


async def test_sockets_opened_at_once_are_bounded_too(api: Api) -> None:
    """Counted before the handshake's await: 48 at once, 32 taken."""
    async def attempt() -> aiohttp.ClientWebSocketResponse | int:
        try:
            return await api.http.ws_connect("/api/ws", headers=auth("viewer"))
        except aiohttp.WSServerHandshakeError as exc:
            return exc.status

    results = await asyncio.gather(*(attempt() for _ in range(MAX_SOCKETS_PER_PRINCIPAL + 16)))
    opened = [r for r in results if not isinstance(r, int)]
    assert len(opened) == MAX_SOCKETS_PER_PRINCIPAL
    assert [r for r in results if isinstance(r, int)] == [429] * 16
    for ws in opened:
        await ws.close()


def test_a_run_raises_its_soft_open_file_limit() -> None:
    """In a child whose soft limit is 256 (the hard one as it was): raised to the hard one,
    up to 65536."""
    code = ("import resource\n"
            "from rcan_rtps.bridge.open_files import raise_open_file_limit\n"
            "soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)\n"
            "resource.setrlimit(resource.RLIMIT_NOFILE, (256, hard))\n"
            "now = raise_open_file_limit()\n"
            "print(now, resource.getrlimit(resource.RLIMIT_NOFILE)[0], hard)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=60).stdout.split()
    now, soft, hard = (int(x) for x in out)
    expected = 65536 if hard < 0 else min(hard, 65536)
    assert now == soft == max(expected, 256)
