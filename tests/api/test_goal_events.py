"""WebSocket goal events: every change of a navigation goal, newest per goal when behind."""

from __future__ import annotations

import asyncio
import json
from typing import Any

import aiohttp

from rcan_rtps.api._goal_events import MAX_PENDING_GOALS, GoalEvents
from rcan_rtps.api.ports import GoalState, GoalView
from tests.api.apihelpers import Api, auth


def _view(goal_id: str, state: GoalState, left: float | None = None) -> GoalView:
    feedback = None if left is None else {"distance_remaining": left}
    return GoalView(goal_id=goal_id, action="/robot1/navigate_to_pose", state=state,
                    feedback=feedback, created_ms=1, updated_ms=2)


async def _goal_frame(ws: aiohttp.ClientWebSocketResponse) -> dict[str, Any]:
    async def wait() -> dict[str, Any]:
        while True:
            msg = await ws.receive()
            assert msg.type is aiohttp.WSMsgType.TEXT, msg
            frame: dict[str, Any] = json.loads(msg.data)
            if frame["type"] == "goal":
                return frame

    return await asyncio.wait_for(wait(), timeout=30)


async def test_each_goal_change_reaches_the_socket(api: Api) -> None:
    async with api.http.ws_connect("/api/ws", headers=auth("viewer")) as ws:
        await ws.receive()  # the first STATUS: the socket is subscribed
        changes = [_view("g1", "accepted"), _view("g1", "executing", 3.0),
                   _view("g1", "executing", 1.5), _view("g1", "succeeded", 0.0)]
        for change in changes:
            api.robot.goal_changed(change)
            frame = await _goal_frame(ws)
            assert frame["body"]["state"] == change.state
            assert frame["body"]["feedback"] == change.feedback


async def test_a_slow_subscriber_gets_the_newest_view_of_each_goal() -> None:
    events = GoalEvents()
    sub = events.subscribe()
    events.offer(_view("a", "executing", 4.0))
    events.offer(_view("b", "executing", 9.0))
    events.offer(_view("a", "executing", 2.0))
    events.offer(_view("a", "aborted", 2.0))
    first, second = await sub.next(), await sub.next()
    assert (first.goal_id, first.state) == ("b", "executing")  # a changed after b did
    assert (second.goal_id, second.state) == ("a", "aborted")  # the end is what is left
    waiting = asyncio.ensure_future(sub.next())
    await asyncio.sleep(0)
    assert not waiting.done()  # nothing pending: it waits
    events.offer(_view("c", "canceled"))
    assert (await waiting).goal_id == "c"
    sub.close()
    assert events.subscribers == 0


async def test_memory_stays_bounded_for_a_subscriber_that_never_reads() -> None:
    events = GoalEvents()
    sub = events.subscribe()
    for i in range(MAX_PENDING_GOALS + 50):
        events.offer(_view(f"g{i}", "executing", float(i)))
    taken = [await sub.next() for _ in range(MAX_PENDING_GOALS)]
    assert taken[0].goal_id == "g50" and taken[-1].goal_id == f"g{MAX_PENDING_GOALS + 49}"
