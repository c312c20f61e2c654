"""One STATUS owner (`StatusHub`) pushes to every transport; nobody polls.

The unit tests drive the hub with a tick so slow it never fires, so every push they see was
caused by a change. The API tests do the same through a bridge configured with a slow
`telemetry_rate_hz`: what arrives at once arrived because the owner was told.
"""

from __future__ import annotations

import asyncio
import json
import threading
from typing import Any

import aiohttp
import pytest

from rcan_rtps.api._status import StatusHub
from rcan_rtps.rcan import Position, RosInfo, Status, Telemetry
from tests.api.apihelpers import RURI, Api, auth

NEVER = 3600.0  # a tick period no test lives to see


class Source:
    """What STATUS is made of, changed by the test; counts how often it is computed."""

    def __init__(self) -> None:
        self.state: Any = "idle"
        self.x = 0.0
        self.computed = 0
        self.broken = False

    def __call__(self) -> Status:
        self.computed += 1
        if self.broken:
            raise RuntimeError("telemetry source broke")
        return Status(ruri=RURI, state=self.state, estop=self.state == "estop",
                      battery_pct=None, telemetry=Telemetry(position=Position(self.x, 0, 0)),
                      faults=[], active_goals=[], pending_auth=0,
                      ros=RosInfo(domain_id=0, distro="jazzy", connected=True,
                                  last_telemetry_age_s=0.0), timestamp_ms=1)


async def _next(sub: Any, timeout: float = 10.0) -> Status:
    return await asyncio.wait_for(sub.next(), timeout)


async def _nothing_pending(sub: Any) -> bool:
    """True if the subscription holds no unread snapshot (checked after the loop settles)."""
    for _ in range(5):
        await asyncio.sleep(0)
    return not sub._ready.is_set()


@pytest.fixture
async def hub() -> Any:
    source = Source()
    owner = StatusHub(source, period_s=NEVER)
    await owner.start()
    yield owner, source
    await owner.close()


async def test_a_subscriber_gets_the_current_snapshot_first(hub: Any) -> None:
    owner, _ = hub
    sub = owner.subscribe()
    assert (await _next(sub)).state == "idle"


async def test_a_change_that_matters_is_pushed_at_once(hub: Any) -> None:
    owner, source = hub
    sub = owner.subscribe()
    await _next(sub)
    source.state = "estop"
    owner.changed()
    assert (await _next(sub)).estop


async def test_positions_wait_for_the_tick(hub: Any) -> None:
    owner, source = hub
    sub = owner.subscribe()
    await _next(sub)
    source.x = 3.0
    owner.changed()
    assert await _nothing_pending(sub)  # a position alone is not worth a push
    assert owner.snapshot().telemetry.position == Position(3.0, 0, 0)  # but readers see it


async def test_a_slow_subscriber_gets_only_the_newest(hub: Any) -> None:
    owner, source = hub
    sub = owner.subscribe()
    for state in ("moving", "fault", "estop", "idle", "executing"):
        source.state = state
        owner.snapshot()  # each a change that matters: offered to the subscriber
    assert (await _next(sub)).state == "executing"
    assert await _nothing_pending(sub)


async def test_changes_may_be_reported_from_any_thread(hub: Any) -> None:
    owner, source = hub
    sub = owner.subscribe()
    await _next(sub)
    source.state = "fault"
    thread = threading.Thread(target=owner.changed)  # like the node's reader thread
    thread.start()
    thread.join()
    assert (await _next(sub)).state == "fault"


async def test_many_subscribers_cost_no_computation(hub: Any) -> None:
    owner, source = hub
    owner.snapshot()
    before = source.computed
    subs = [owner.subscribe() for _ in range(200)]
    assert [(await _next(s)).state for s in subs] == ["idle"] * 200
    assert source.computed == before  # they share the owner's snapshot
    source.state = "moving"
    owner.changed()
    assert {(await _next(s)).state for s in subs} == {"moving"}
    assert source.computed == before + 1  # one computation for all 200


@pytest.mark.logs_traceback  # (a fault injected on purpose)
async def test_a_broken_source_is_logged_once_and_survived(
        hub: Any, caplog: pytest.LogCaptureFixture) -> None:
    owner, source = hub
    sub = owner.subscribe()
    await _next(sub)
    source.broken = True
    for _ in range(5):
        owner.changed()
        await asyncio.sleep(0)
    assert [r.message for r in caplog.records].count("computing STATUS failed") == 1
    source.broken = False
    source.state = "estop"
    owner.changed()
    assert (await _next(sub)).estop


async def test_unsubscribed_gets_nothing(hub: Any) -> None:
    owner, source = hub
    sub = owner.subscribe()
    await _next(sub)
    sub.close()
    source.state = "estop"
    owner.changed()
    assert await _nothing_pending(sub)
    assert owner.subscribers == 0


# -- through the API --------------------------------------------------------------------------


@pytest.fixture
async def slow_api(tmp_path: Any) -> Any:
    harness = await Api(tmp_path, rate=1.0 / NEVER).start()
    yield harness
    await harness.close()


async def _status_frame(ws: aiohttp.ClientWebSocketResponse) -> dict[str, Any]:
    while True:
        msg = await asyncio.wait_for(ws.receive(), 10)
        frame: dict[str, Any] = json.loads(msg.data)
        if frame["type"] == "status":
            return frame["body"]


async def test_an_estop_reaches_every_socket_without_a_tick(slow_api: Api) -> None:
    sockets = [await slow_api.http.ws_connect("/api/ws", headers=auth("viewer"))
               for _ in range(5)]
    try:
        for ws in sockets:
            assert (await _status_frame(ws))["estop"] is False
        status, _ = await slow_api.command("viewer", {"action": "estop"})
        assert status == 200
        for ws in sockets:
            assert (await _status_frame(ws))["estop"] is True
    finally:
        for ws in sockets:
            await ws.close()


async def test_pending_approvals_are_pushed(tmp_path: Any) -> None:
    gate = "[{action: move, require_auth: true, authorized_roles: [OWNER]}]"
    api = await Api(tmp_path, rate=1.0 / NEVER, gates=gate).start()
    try:
        async with api.http.ws_connect("/api/ws", headers=auth("viewer")) as ws:
            assert (await _status_frame(ws))["pending_auth"] == 0
            status, _ = await api.command("planner", {"action": "move",
                                                      "params": {"linear_x": 0.1}})
            assert status == 202
            assert (await _status_frame(ws))["pending_auth"] == 1
    finally:
        await api.close()


async def test_robot_side_changes_are_pushed(slow_api: Api) -> None:
    async with slow_api.http.ws_connect("/api/ws", headers=auth("viewer")) as ws:
        assert (await _status_frame(ws))["state"] == "idle"
        slow_api.robot.state = "fault"
        slow_api.robot.changed()  # what the bridge's telemetry does on a new fault
        assert (await _status_frame(ws))["state"] == "fault"
