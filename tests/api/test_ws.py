"""GET /api/ws: STATUS stream, commands and outcomes, heartbeats, and session loss on close."""

from __future__ import annotations

import asyncio
import json

import aiohttp
import pytest
from waiting import eventually

from rcan_rtps.governance import Principal
from rcan_rtps.rcan import Role
from tests.api.apihelpers import Api, auth, next_frame


async def test_status_is_pushed(api: Api) -> None:
    async with api.http.ws_connect("/api/ws", headers=auth("viewer")) as ws:
        first = await next_frame(ws, "status")
        assert first["body"]["ruri"] == api.robot.status(pending_auth=0).ruri
        api.robot.x = 7.5
        while (await next_frame(ws, "status"))["body"]["telemetry"]["position"]["x"] != 7.5:
            pass


async def test_commands_in_outcomes_out_like_rest(api: Api) -> None:
    rest_status, rest = await api.command("planner", {"action": "move",
                                                      "params": {"linear_x": 0.3}})
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        await ws.send_str(json.dumps({"action": "move", "params": {"linear_x": 0.3}}))
        frame = await next_frame(ws, "outcome")
        assert frame["http_status"] == rest_status == 200
        assert frame["body"].keys() == rest.keys()
        # The same, but ramped from what the REST move commands now (its stream is held).
        # and it replaces that stream, which its entry records.
        assert frame["body"]["applied"] == {
            **rest["applied"], "ramp_from": [0.3, 0.0, 0.0],
            "replaces": {"message_id": rest["message_id"], "reason": "replaced"}}
        assert api.entry(frame["body"]["audit_id"])["principal"] == "planner"

        await ws.send_str('{"action": "move", "params": {"linear_x": NaN}}')
        frame = await next_frame(ws, "outcome")
        assert (frame["http_status"], frame["body"]["error_code"]) == (
            400, "SCHEMA_VALIDATION_FAILED")
        assert api.entry(frame["body"]["audit_id"])["deny_reason"].startswith("SCHEMA")

        await ws.send_bytes(b'{"action": "fly"}')
        frame = await next_frame(ws, "outcome")
        assert (frame["http_status"], frame["body"]["path"]) == (400, "$.action")

        await ws.send_str(json.dumps({"action": "move", "role": "CREATOR"}))
        assert (await next_frame(ws, "outcome"))["http_status"] == 403
    assert [a for a, _ in api.dispatcher.calls].count("move") == 2


async def test_oversized_frames(api: Api) -> None:
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        await ws.send_str('{"action": "move", "pad": "' + "x" * (64 * 1024) + '"}')
        frame = await next_frame(ws, "outcome")
        assert (frame["http_status"], frame["body"]["error_code"]) == (413,
                                                                       "PAYLOAD_TOO_LARGE")
        assert api.entry(frame["body"]["audit_id"])["deny_reason"] == "PAYLOAD_TOO_LARGE"
        await ws.send_str("x" * (1024 * 1024))  # beyond 4x the limit: the socket closes
        msg = await asyncio.wait_for(ws.receive(), timeout=30)
        while msg.type is aiohttp.WSMsgType.TEXT:
            msg = await asyncio.wait_for(ws.receive(), timeout=30)
        assert msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED)
        assert ws.close_code == aiohttp.WSCloseCode.MESSAGE_TOO_BIG
    assert api.dispatcher.calls == []


async def test_websocket_needs_credentials(api: Api) -> None:
    with pytest.raises(aiohttp.WSServerHandshakeError) as info:
        await api.http.ws_connect("/api/ws")
    assert info.value.status == 401


async def _hold_session(api: Api, ws: aiohttp.ClientWebSocketResponse) -> None:
    await ws.send_str(json.dumps({"action": "move", "params": {"linear_x": 0.2}}))
    assert (await next_frame(ws, "outcome"))["http_status"] == 200


async def test_ping_counts_as_heartbeat(api: Api) -> None:
    async with api.http.ws_connect("/api/ws", headers=auth("planner"), autoping=False) as ws:
        await _hold_session(api, ws)
        api.clock.advance(50)  # session_timeout_s is 60
        await ws.ping(b"hb")
        while (await asyncio.wait_for(ws.receive(), 30)).type is not aiohttp.WSMsgType.PONG:
            pass
        api.clock.advance(50)  # 100 s since the command, 50 s since the ping
        await api.gov.sweep()
        assert [a for a, _ in api.dispatcher.calls] == ["move"]
        api.clock.advance(11)  # now 61 s of silence
        await api.gov.sweep()
        assert [a for a, _ in api.dispatcher.calls] == ["move", "stop"]


async def test_any_frame_counts_as_heartbeat(api: Api) -> None:
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        await _hold_session(api, ws)
        api.clock.advance(50)
        await ws.send_str("{}")  # not a valid command, but the client is there
        await next_frame(ws, "outcome")
        api.clock.advance(50)
        await api.gov.sweep()
        assert [a for a, _ in api.dispatcher.calls] == ["move"]


async def test_closing_the_socket_of_a_controller_stops_the_robot(api: Api) -> None:
    ws = await api.http.ws_connect("/api/ws", headers=auth("planner"))
    await _hold_session(api, ws)
    await ws.close()
    # No sweeper runs and the clock stands still: only the closed socket can cause this.
    await eventually(lambda: ("stop", {}) in api.dispatcher.calls, timeout=30)
    stops = [e for e in api.entries if e["event"] == "NETWORK_LOSS_SAFE_STOP"]
    assert [(e["principal"], e["action_type"], e["outcome"]) for e in stops] == [
        ("planner", "stop", "executed")]


async def test_closing_without_a_session_does_not_stop(api: Api) -> None:
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        await next_frame(ws, "status")
    async with api.http.ws_connect("/api/ws", headers=auth("viewer")) as ws:
        await next_frame(ws, "status")
    # A socket that held a session, closing after those: its stop is the only one.
    ws = await api.http.ws_connect("/api/ws", headers=auth("planner"))
    await _hold_session(api, ws)
    await ws.close()
    await eventually(lambda: ("stop", {}) in api.dispatcher.calls, timeout=30)
    assert [a for a, _ in api.dispatcher.calls] == ["move", "stop"]


async def test_a_move_not_yet_sent_when_its_socket_closes_never_starts(api: Api) -> None:
    """The socket's move waits for the robot (no session opened yet) when the client closes
    it: the move is refused `stopped` and nothing reaches the robot. It used to be awaited
    first and sent, after its connection was gone (then halted: it had opened a session by
    then), and with another socket of no session, run until its session timed out."""
    release = api.dispatcher.hold_ready = asyncio.Event()
    entered = api.dispatcher.ready_entered
    closed, connection_closed = asyncio.Event(), api.gov.connection_closed

    def seen_closed(principal: Principal) -> bool:
        closed.set()
        return connection_closed(principal)

    api.gov.connection_closed = seen_closed  # type: ignore[method-assign]
    ws = await api.http.ws_connect("/api/ws", headers=auth("planner"))
    await ws.send_str(json.dumps({"action": "move", "params": {"linear_x": 0.2}}))
    await asyncio.wait_for(entered.wait(), timeout=30)
    await ws.close()
    lost = lambda: [e for e in api.entries if e["event"] == "NETWORK_LOSS_SAFE_STOP"]  # noqa: E731
    await asyncio.wait_for(closed.wait(), timeout=30)  # the server saw the socket close
    release.set()
    await eventually(lambda: bool(lost()), timeout=30)
    [move] = [e for e in api.entries if e["event"] == "COMMAND_FAILED"]
    assert (move["action_type"], move["deny_reason"]) == ("move", "COMMAND_REJECTED:stopped"), move
    assert lost()[0]["applied"] == {"scope": "own", "goals_cancelled": [],
                                    "before_session": True}
    assert api.dispatcher.calls == [] and api.dispatcher.samples == []
    assert await api.gov.end_session(Principal("planner", Role.USER, None)) is None


async def test_a_queued_estop_is_decided_even_after_close(api: Api) -> None:
    api.dispatcher.hold = asyncio.Event()
    ws = await api.http.ws_connect("/api/ws", headers=auth("planner"))
    await ws.send_str(json.dumps({"action": "move"}))
    await asyncio.wait_for(api.dispatcher.entered.wait(), timeout=30)
    await ws.send_str(json.dumps({"action": "estop"}))
    await ws.send_str(json.dumps({"action": "move"}))  # queued motion: dropped on close
    await ws.close()
    # The e-stop does not wait for the move in flight (the e-stop lane): it reaches the robot
    # while that move's dispatch is still held.
    await eventually(lambda: ("estop", {}) in api.dispatcher.calls, timeout=30)
    api.dispatcher.hold.set()
    await eventually(lambda: len(api.dispatcher.calls) >= 3, timeout=30)
    # The move in flight finishes (it passed the latch before the e-stop), the queued move is
    # dropped, then the session-loss stop.
    assert [a for a, _ in api.dispatcher.calls] == ["estop", "move", "stop"]
    assert api.gov.latch.latched


async def test_server_shutdown_closes_sockets(api: Api) -> None:
    ws = await api.http.ws_connect("/api/ws", headers=auth("viewer"))
    await next_frame(ws, "status")
    closing = asyncio.create_task(api.http.server.close())  # the client answers meanwhile
    msg = await asyncio.wait_for(ws.receive(), timeout=30)
    while msg.type is aiohttp.WSMsgType.TEXT:
        msg = await asyncio.wait_for(ws.receive(), timeout=30)
    assert msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED)
    assert ws.close_code == aiohttp.WSCloseCode.GOING_AWAY
    await ws.close()
    await asyncio.wait_for(closing, timeout=30)


# -- the governor's part --------------------------------------------------------------------


async def test_end_session_stops_once_and_only_for_a_session_holder(api: Api) -> None:
    planner = Principal("planner", Role.USER, None)
    assert await api.gov.end_session(planner) is None  # no session yet
    status, _ = await api.command("planner", {"action": "move"})
    assert status == 200
    decision = await api.gov.end_session(planner)
    assert decision is not None
    assert decision.outcome.value == "executed"
    assert api.entry(decision.audit_id or "")["event"] == "NETWORK_LOSS_SAFE_STOP"
    assert await api.gov.end_session(planner) is None  # ended: nothing left to stop
    await api.command("planner", {"action": "move"})
    await api.command("planner", {"action": "stop"})  # stopped on purpose: session over
    assert await api.gov.end_session(planner) is None
    assert [a for a, _ in api.dispatcher.calls] == ["move", "stop", "move", "stop"]
