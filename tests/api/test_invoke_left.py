"""An INVOKE whose client leaves before its answer, and INVOKE_CANCEL on the WebSocket.

An INVOKE is answered when its skill is done (a goal's end, a move's stream's end, an arm's
trajectory's time). A client that leaves before that — its HTTP request hung up on, its
WebSocket closed — leaves nobody to answer: its motion is stopped as its INVOKE_CANCEL would
stop it (the stream ended with zero, the arm held, the goal cancelled; each audited, `why:
INVOKE's client left`) and the INVOKE is answered once, in the log (`failure`). Before, the
motion ran on until the INVOKE's `timeout_ms` or its principal's session lapsed, or (the
WebSocket) until its command in flight had been decided.

An INVOKE_CANCEL is the stop of one skill's motion: on the WebSocket it goes through the stop
lane, never behind the socket's queue (a command held for a human, a full backlog), never 429.
Before, it waited its turn behind them while the skill's motion ran on.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from waiting import eventually

from rcan_rtps.api import ApiServer
from rcan_rtps.api._keys import DEADLINES, INVOCATIONS, SOCKETS_OF
from rcan_rtps.governance import Principal
from rcan_rtps.rcan import Invoke, Role, validate_message
from tests.api.apihelpers import ZERO, Api, auth, own_stops
from tests.api.test_invoke import cancel, invoke, nudge, results, sent, stream_ends, wave

SKILLS = ("skills: {go_home: {action: navigate, params: {x: 0, y: 0, yaw: 0}}, "
          "nudge: {action: move, params: {linear_x: 0.3}, allow: [duration_s]}, "
          "wave: {action: arm_joint, params: {joints: [elbow], positions: [0.8]}, "
          "allow: [duration_s]}}\n"
          "  motion: {locks: [{name: teleop, priority: 0}]}")  # a lock a USER may engage
LOCK = {"action": "lock", "params": {"name": "teleop"}}
WS_BACKLOG = 32  # ApiSettings.ws_max_in_flight
BY_CLIENT_LEFT = "INVOKE's client left"  # the `why` of what stopped its motion
PLANNER = Principal("planner", Role.USER)  # the sender of each INVOKE here


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[Api]:
    harness = await Api(tmp_path, bridge_extra=SKILLS, gates="[]").start()
    yield harness
    await harness.close()


@pytest.fixture
async def served(tmp_path: Path) -> AsyncIterator[tuple[Api, str]]:
    """The API served as `rcan-rtps run` serves it (`ApiServer`: aiohttp's real server, which
    runs a handler on after its client hung up), and its URL."""
    api = Api(tmp_path, bridge_extra=SKILLS, gates="[]")
    app = await api.build()
    async with ApiServer(app, host="127.0.0.1", port=0) as server:
        yield api, server.url
    await api.close()


def _stopped(api: Api, kind: str, msg_id: str) -> list[dict[str, Any]]:
    """The entry that stopped the skill's motion because its client left."""
    if kind == "move":
        return [e for e in stream_ends(api, msg_id) if e["params"].get("why") == BY_CLIENT_LEFT]
    action = {"arm": "hold_trajectory", "goal": "cancel_goal"}[kind]
    return [e for e in api.entries if e.get("action_type") == action
            and e["message_id"] == msg_id and e["params"]["why"] == BY_CLIENT_LEFT]


def _stops(api: Api, kind: str, msg_id: str) -> bool:
    """Whether the skill's motion no longer runs: its stream ended, its arm held, its goal
    cancelled."""
    if kind == "move":
        return api.gov.streams.active is None
    if kind == "arm":
        return not api.gov.trajectory_running(msg_id, PLANNER)
    return api.dispatcher.cancelled == ["goal-1"]


def _not_running(api: Api, kind: str, msg_id: str) -> None:
    if kind == "move":
        assert api.dispatcher.samples[-1] == ZERO
    elif kind == "arm":
        assert api.dispatcher.holds == [[msg_id]] and api.dispatcher.running == []
    assert _stops(api, kind, msg_id)


SKILL_OF: dict[str, tuple[str, Callable[[str], dict[str, Any]]]] = {
    "move": ("move", lambda m: nudge(m)),  # until something ends it
    "arm": ("arm_joint", lambda m: wave(m, 60.0)),
    "goal": ("navigate", lambda m: invoke("go_home", m)),
}


@pytest.mark.parametrize("kind", ["move", "arm", "goal"])
async def test_a_rest_invoke_hung_up_on_stops_its_motion(served: tuple[Api, str],
                                                         kind: str) -> None:
    """The production server: its client hangs up while the skill runs. Before, the handler
    ran on, the motion with it (until `timeout_ms`, 30 s, or the session lapsed)."""
    api, url = served
    action, body = SKILL_OF[kind]
    async with aiohttp.ClientSession() as session:
        call = asyncio.ensure_future(session.post(f"{url}/api/command", json=body("inv-h"),
                                                  headers=auth("planner")))
        await sent(api, action)
        call.cancel()  # the request's connection closes
    await eventually(lambda: _stops(api, kind, "inv-h"), what="its motion stopped")
    [stop] = _stopped(api, kind, "inv-h")
    assert stop["principal"] == "planner"
    [answer] = await eventually(lambda: results(api, "inv-h"), what="its INVOKE_RESULT")
    assert (answer["status"], answer["params"]["error"]["name"]) == ("failure", "SkillFailed")
    assert answer["deny_reason"].startswith("its client left before it was done"), answer
    _not_running(api, kind, "inv-h")
    assert own_stops(api.entries) == []  # its own motion alone: no stop of the principal's


async def test_a_rest_invoke_hung_up_on_while_it_is_decided_stops_once_started(
        served: tuple[Api, str]) -> None:
    """The client hangs up while the skill's command is being decided (its stream started,
    the decision not yet returned): the wait for its answer begins after its connection is
    gone, and its motion stops then."""
    api, url = served
    release, entered = api.hold_decisions(lambda c: c.action == "move", decided=True)
    async with aiohttp.ClientSession() as session:
        call = asyncio.ensure_future(session.post(f"{url}/api/command", json=nudge("inv-d"),
                                                  headers=auth("planner")))
        await asyncio.wait_for(entered.wait(), 10)
        call.cancel()
    await eventually(lambda: _conn_count(api) == 0, what="its connection gone")
    assert api.gov.streams.active is not None  # started, its INVOKE not yet waiting
    release.set()
    await eventually(lambda: _stops(api, "move", "inv-d"), what="its motion stopped")
    assert len(_stopped(api, "move", "inv-d")) == 1
    [answer] = await eventually(lambda: results(api, "inv-d"), what="its INVOKE_RESULT")
    assert answer["status"] == "failure", answer


def _conn_count(api: Api) -> int:
    """Connections the server still watches (`ConnectionDeadlines`)."""
    assert api.app is not None
    return len(api.app[DEADLINES].watched)


@pytest.mark.parametrize("kind", ["move", "arm", "goal"])
async def test_a_websocket_invoke_is_stopped_as_its_socket_closes(api: Api, kind: str
                                                                  ) -> None:
    """The socket closes with a command in flight (held before the governor has it): the
    skill's motion stops at once, not once that command is decided. Before, it ran on until
    then (the session's safe stop comes after the command in flight)."""
    action, body = SKILL_OF[kind]
    release, entered = api.hold_decisions(lambda c: c.action == "lock", decided=False)
    ws = await api.http.ws_connect("/api/ws", headers=auth("planner"))
    await ws.send_str(json.dumps(body("inv-w")))
    await sent(api, action)
    await ws.send_str(json.dumps(LOCK))
    await asyncio.wait_for(entered.wait(), 10)
    closing = asyncio.ensure_future(ws.close())
    try:
        await eventually(lambda: _stops(api, kind, "inv-w"), what="its motion stopped")
        [answer] = await eventually(lambda: results(api, "inv-w"), what="its INVOKE_RESULT")
        assert [e for e in api.entries if e.get("action_type") == "lock"] == []  # still held
    finally:
        release.set()
    assert answer["status"] == "failure", answer
    [stop] = _stopped(api, kind, "inv-w")
    assert stop["principal"] == "planner"
    _not_running(api, kind, "inv-w")
    await asyncio.wait_for(closing, 30)
    assert len(results(api, "inv-w")) == 1


async def _outcomes(ws: aiohttp.ClientWebSocketResponse, count: int) -> list[dict[str, Any]]:
    """The next `count` outcome frames (others skipped)."""
    found: list[dict[str, Any]] = []

    async def wait() -> None:
        while len(found) < count:
            msg = await ws.receive()
            assert msg.type is aiohttp.WSMsgType.TEXT, msg
            frame = json.loads(msg.data)
            if frame["type"] == "outcome":
                found.append(frame)

    await asyncio.wait_for(wait(), 30)
    return found


@pytest.mark.parametrize("ahead", ["held", "full"])
async def test_a_websocket_invoke_cancel_does_not_wait_behind_the_queue(api: Api,
                                                                        ahead: str) -> None:
    """A command in flight that is not decided (`held`), and behind it a full backlog
    (`full`): the INVOKE_CANCEL is answered and the skill's stream ended before any of them
    is decided. Before, it waited behind them (`held`), or was refused 429 (`full`)."""
    release, entered = api.hold_decisions(lambda c: c.action == "lock", decided=False)
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        await ws.send_str(json.dumps(nudge("inv-c")))
        await sent(api, "move")
        await ws.send_str(json.dumps(LOCK))
        await asyncio.wait_for(entered.wait(), 10)
        if ahead == "full":
            for _ in range(WS_BACKLOG):
                await ws.send_str(json.dumps(LOCK))  # each held in its turn
        await ws.send_str(json.dumps(cancel("inv-c")))
        try:  # the INVOKE's answer and the cancel's, each the INVOKE_RESULT `cancelled`
            answers = await _outcomes(ws, 2)
            assert [e for e in api.entries if e.get("action_type") == "lock"] == []
        finally:
            release.set()
        assert [(f["http_status"], f["body"].get("reply_to"), f["body"].get("status"))
                for f in answers] == [(200, "inv-c", "cancelled")] * 2, answers
        assert api.dispatcher.samples[-1] == ZERO
        [end] = stream_ends(api, "inv-c")
        assert (end["params"]["reason"], end["params"]["why"]) == ("cancelled",
                                                                   "INVOKE_CANCEL"), end
        [locked] = await _outcomes(ws, 1)
        assert locked["body"]["outcome"] == "executed", locked
    assert len(results(api, "inv-c")) == 1


async def test_a_websocket_invoke_cancel_of_a_queued_invoke_cancels_it_once_decided(
        api: Api) -> None:
    """Guard of the lane above (passes before it too): an INVOKE_CANCEL that comes while its
    INVOKE still waits in the socket's queue is not `not_found` for overtaking it — it is
    decided once its INVOKE is, which it then cancels."""
    release, entered = api.hold_decisions(lambda c: c.action == "lock", decided=False)
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        await ws.send_str(json.dumps(LOCK))
        await asyncio.wait_for(entered.wait(), 10)
        await ws.send_str(json.dumps(nudge("inv-q")))
        await ws.send_str(json.dumps(cancel("inv-q")))
        release.set()
        answers = await _outcomes(ws, 3)
    by_invoke = [(f["body"]["reply_to"], f["body"]["status"]) for f in answers
                 if f["body"].get("reply_to") == "inv-q"]
    assert by_invoke == [("inv-q", "cancelled")] * 2, answers
    assert api.gov.streams.active is None and api.dispatcher.samples[-1] == ZERO
    [end] = stream_ends(api, "inv-q")
    assert end["params"]["why"] == "INVOKE_CANCEL", end


async def test_a_websocket_invoke_cancel_past_its_room_is_refused_and_a_stop_still_goes(
        api: Api, monkeypatch: pytest.MonkeyPatch) -> None:
    """`ws_max_in_flight` INVOKE_CANCELs being decided (a goal slow to wind down): one more is
    refused 429 at once, and a `stop` behind it is decided. Before, the reader waited for
    room in the cancel lane, and the stop behind it with it."""
    wound_down = asyncio.Event()
    recorded = api.dispatcher.cancel_goal

    async def slow_cancel(goal_id: str) -> bool:
        await wound_down.wait()
        return await recorded(goal_id)

    monkeypatch.setattr(api.dispatcher, "cancel_goal", slow_cancel)
    slow = cancel("inv-g")
    slow["payload"]["cancel_timeout_ms"] = 600_000  # each waits for the goal, not a clock
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        await ws.send_str(json.dumps(invoke("go_home", "inv-g")))
        await sent(api, "navigate")
        for _ in range(WS_BACKLOG + 1):
            await ws.send_str(json.dumps(slow))
        await ws.send_str(json.dumps({"action": "stop"}))
        try:
            frames = await _outcomes(ws, 2)
        finally:
            wound_down.set()
        assert [f["http_status"] for f in frames] == [429, 200], frames
        assert frames[1]["body"]["outcome"] == "executed", frames
        assert [e["outcome"] for e in api.entries if e.get("action_type") == "stop"] == [
            "executed"]


@pytest.mark.parametrize("kind", ["move", "arm", "goal"])
async def test_a_websocket_invoke_decided_as_its_socket_closes_is_answered_in_the_log(
        api: Api, kind: str) -> None:
    """The race below, made certain: the INVOKE's command is decided (its motion started)
    and its decision held back from the INVOKE while the socket closes. Once it comes, the
    INVOKE is answered in the log (`failure`, its client gone) and its motion is stopped.
    Before, the close cancelled the INVOKE's wait for its decision: no INVOKE_RESULT entry."""
    action, body = SKILL_OF[kind]
    release, entered = api.hold_decisions(lambda c: c.action == action, decided=True)
    ws = await api.http.ws_connect("/api/ws", headers=auth("planner"))
    await ws.send_str(json.dumps(body("inv-x")))
    await asyncio.wait_for(entered.wait(), 10)
    await ws.close()
    await eventually(lambda: own_stops(api.entries), what="the socket's session stop")
    release.set()
    [answer] = await eventually(lambda: results(api, "inv-x"), what="its INVOKE_RESULT")
    assert (answer["status"], answer["params"]["error"]["name"]) == ("failure", "SkillFailed")
    assert {"move": api.gov.streams.active is None, "arm": api.dispatcher.running == [],
            "goal": not api.gov.goal_held("goal-1")}[kind]  # (the session's stop, first)
    await asyncio.sleep(0.05)
    assert len(results(api, "inv-x")) == 1


async def test_an_invoke_on_its_way_as_its_connection_closes_never_starts(api: Api) -> None:
    """An INVOKE's command arrives at the governor in its caller's step, as any command: a
    connection closing from the next step on wins over it (`Governor.connection_closed`): its
    move never starts, and its answer is in the log. (Decided in a task begun a step later,
    the move arrived after the close and started, to be stopped again once decided.)"""
    invoke = validate_message(json.dumps(nudge("inv-a")).encode())
    assert isinstance(invoke, Invoke) and api.app is not None
    starting = asyncio.ensure_future(
        api.app[INVOCATIONS].invocations().start(api.gov, PLANNER, invoke))
    await asyncio.sleep(0)  # its first step: the INVOKE is a command, on its way
    api.gov.connection_closed(PLANNER)
    starting.cancel()  # as its socket's close cancels it
    [answer] = await eventually(lambda: results(api, "inv-a"), what="its INVOKE_RESULT")
    assert answer["status"] == "failure", answer
    assert api.dispatcher.calls == [] and api.gov.streams.active is None


RACE_TRIALS = 90  # 30 a skill, the close moved one loop turn further each time
DECIDED = ("COMMAND_DISPATCHED", "COMMAND_FAILED", "COMMAND_REJECTED")


def _decided(api: Api, msg_id: str, action: str) -> bool:
    """Whether the governor decided the INVOKE `msg_id`'s command (its entry is in the log)."""
    return any(e["event"] in DECIDED and e["message_id"] == msg_id
               and e.get("action_type") == action for e in api.entries)


async def _socket_of_planner(api: Api) -> aiohttp.ClientWebSocketResponse:
    """A WebSocket of planner's, once one is free: the bridge counts a closed socket against
    its principal's 32 until its handler has finished (its INVOKE answered, its session's
    safe stop done), which on a busy machine can be after the next trials connect (429)."""
    async def connected() -> aiohttp.ClientWebSocketResponse | None:
        try:
            return await api.http.ws_connect("/api/ws", headers=auth("planner"))
        except aiohttp.WSServerHandshakeError as exc:
            if exc.status != 429:
                raise
            return None

    socket: aiohttp.ClientWebSocketResponse = await eventually(
        connected, what="a WebSocket of planner's accepted")
    return socket


async def test_every_decided_websocket_invoke_is_answered_in_the_log_whenever_its_socket_closes(
        api: Api) -> None:
    """Red team 15: a socket closing in the loop step in which its INVOKE's decision completes
    (or while it is decided) cut off the INVOKE before it was answered: no INVOKE_RESULT entry
    (the session's safe stop still stopped its motion). Each trial sends an INVOKE and closes
    its socket a few loop turns later, sweeping the close across the decision; every INVOKE
    the governor decided must have exactly one INVOKE_RESULT entry."""
    kinds = list(SKILL_OF)
    sent_ids: list[tuple[str, str]] = []
    for trial in range(RACE_TRIALS):
        action, body = SKILL_OF[kinds[trial % len(kinds)]]
        msg_id = f"inv-race-{trial}"
        ws = await _socket_of_planner(api)
        await ws.send_str(json.dumps(body(msg_id)))
        for _ in range(trial // len(kinds)):
            await asyncio.sleep(0)
        await ws.close()
        sent_ids.append((msg_id, action))

    # Each socket's handler is done once its INVOKE is answered and its session's safe stop
    # done; on a busy machine the last trials' take a while. Waited for, then counted:
    # (a fixed window used to be read as "unanswered" on a loaded machine).
    assert api.app is not None
    sockets_of = api.app[SOCKETS_OF]
    await eventually(lambda: sockets_of["planner"] == 0, timeout=120,
                     what=lambda: f"planner's {sockets_of['planner']} sockets' handlers done")
    decided = [m for m, action in sent_ids if _decided(api, m, action)]
    assert decided, "no INVOKE was decided: the sweep missed the decisions"

    def answered() -> bool:  # (a left client's INVOKE is answered by a task of its own)
        unanswered = [m for m in decided if not results(api, m)]
        assert unanswered == [], f"{len(unanswered)} of {len(decided)}: {unanswered}"
        return True

    await eventually(answered, timeout=60, what="every decided INVOKE answered")
    missing = [(m, len(results(api, m))) for m in decided if len(results(api, m)) != 1]
    assert missing == [], f"{len(missing)} of {len(decided)} decided INVOKEs: {missing}"
