"""A held INVOKE (HiTL) ends with one INVOKE_RESULT, whatever ends its hold.

An INVOKE a HiTL gate holds is answered 202 `pending` at once; its INVOKE_RESULT follows when
its hold ends: withdrawn (a stop of the robot, its connection closing, its issuer), denied,
expired, or approved and run. On the WebSocket that is a second outcome frame (`reply_to` its
msg_id); over REST, where the request was answered already, it is in the log alone (and its
INVOKE_CANCEL gets it, 409 `invoke_finished`). Before, only an INVOKE_CANCEL's withdrawal was
answered: a client waiting on its socket for the INVOKE_RESULT of an INVOKE a stop withdrew,
a reviewer denied or that expired waited for ever, and the log had no INVOKE_RESULT for it."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from waiting import eventually

from tests.api.apihelpers import Api, auth, next_frame
from tests.api.test_invoke import SKILLS, cancel, invoke, results

ARM_SKILL = "raise_elbow"  # arm_joint: gated for an OWNER (apihelpers.ARM_GATE)


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[Api]:
    harness = await Api(tmp_path, bridge_extra=SKILLS).start()
    yield harness
    await harness.close()


async def _held_on(ws: aiohttp.ClientWebSocketResponse, msg_id: str) -> str:
    """Sends the INVOKE of the gated arm skill; its pending id, from its 202 frame."""
    await ws.send_str(json.dumps(invoke(ARM_SKILL, msg_id)))
    frame = await next_frame(ws, "outcome")
    body = frame["body"]
    assert (frame["http_status"], body["status"], body["msg_id"]) == (
        202, "pending", msg_id), frame
    return str(body["pending_id"])


async def _result_frame(ws: aiohttp.ClientWebSocketResponse) -> dict[str, Any]:
    frame = await asyncio.wait_for(next_frame(ws, "outcome"), 10)
    body: dict[str, Any] = frame["body"]
    assert body["type"] == "INVOKE_RESULT", frame
    return body


async def _one_result(api: Api, msg_id: str) -> dict[str, Any]:
    """The INVOKE's one INVOKE_RESULT entry (and never a second one)."""
    [entry] = await eventually(lambda: results(api, msg_id))
    await asyncio.sleep(0.05)
    assert len(results(api, msg_id)) == 1, results(api, msg_id)
    return entry


async def test_a_held_invoke_a_stop_withdraws_is_answered_on_its_socket(api: Api) -> None:
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        await _held_on(ws, "inv-s")
        status, body = await api.command("ops", {"action": "stop"})
        assert (status, body["outcome"]) == (200, "executed"), body
        result = await _result_frame(ws)
    assert (result["reply_to"], result["status"], result["reason"]) == (
        "inv-s", "failure", "hitl_withdrawn"), result
    assert result["error"]["message"] == ("withdrawn: the robot was stopped while it was held "
                                          "(a stop by 'ops')"), result
    entry = await _one_result(api, "inv-s")
    assert (entry["status"], entry["outcome"]) == ("failure", "denied"), entry
    assert api.entry(result["audit_id"])["event"] == "HITL_WITHDRAWN"
    assert [a for a, _ in api.dispatcher.calls] == ["stop"]


async def test_a_held_invoke_denied_is_answered_on_its_socket(api: Api) -> None:
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        pending_id = await _held_on(ws, "inv-d")
        status, body = await api.call("POST", "/api/hitl/deny", "ops",
                                      body={"pending_id": pending_id, "reason": "not now"})
        assert (status, body["reason"]) == (200, "hitl_denied"), body
        result = await _result_frame(ws)
    assert (result["reply_to"], result["status"], result["reason"]) == (
        "inv-d", "failure", "hitl_denied"), result
    assert result["error"]["message"] == "denied by 'ops': not now", result
    assert (await _one_result(api, "inv-d"))["status"] == "failure"
    assert api.dispatcher.calls == []


async def test_a_held_invoke_that_expired_is_answered_on_its_socket(api: Api) -> None:
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        await _held_on(ws, "inv-e")
        api.clock.advance(301)  # past hitl.timeout_seconds
        await api.gov.expire_pending()  # (the harness runs no sweeper)
        result = await _result_frame(ws)
    assert (result["reply_to"], result["status"], result["reason"]) == (
        "inv-e", "timeout", "pending_expired"), result
    assert result["error"]["code"] == 7002, result
    assert (await _one_result(api, "inv-e"))["status"] == "timeout"
    assert api.dispatcher.calls == []


async def test_a_held_invoke_approved_is_answered_on_its_socket(api: Api) -> None:
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        pending_id = await _held_on(ws, "inv-a")
        status, body = await api.call("POST", "/api/hitl/authorize", "ops",
                                      body={"pending_id": pending_id})
        assert (status, body["outcome"]) == (200, "executed"), body
        result = await _result_frame(ws)
        assert [a for a, _ in api.dispatcher.calls] == ["arm_joint"]  # (its close: a stop)
    assert (result["reply_to"], result["status"], result["outcome"]) == (
        "inv-a", "success", "executed"), result
    assert (await _one_result(api, "inv-a"))["status"] == "success"


async def test_a_held_invoke_over_rest_that_a_stop_withdrew_is_answered_in_the_log(
        api: Api) -> None:
    status, body = await api.command("planner", invoke(ARM_SKILL, "inv-r"))
    assert (status, body["status"]) == (202, "pending"), body
    status, body = await api.command("ops", {"action": "stop"})
    assert (status, body["outcome"]) == (200, "executed"), body
    entry = await _one_result(api, "inv-r")
    assert (entry["status"], entry["deny_reason"]) == (
        "failure", "withdrawn: the robot was stopped while it was held (a stop by 'ops')"), entry
    status, body = await api.command("planner", cancel("inv-r"))  # §19.4: its result stands
    assert (status, body["reason"], body["status"]) == (409, "invoke_finished", "failure"), body


async def test_a_held_invoke_whose_socket_closed_is_answered_in_the_log(api: Api) -> None:
    ws = await api.http.ws_connect("/api/ws", headers=auth("planner"))
    await _held_on(ws, "inv-c")
    await ws.close()
    entry = await _one_result(api, "inv-c")
    assert (entry["status"], entry["outcome"]) == ("failure", "denied"), entry
    assert entry["deny_reason"].startswith("withdrawn: "), entry
    assert api.gov.pending() == [] and api.dispatcher.calls == []


LONG_ARM = ("skills: {reach: {action: arm_joint, params: {joints: [elbow], positions: [0.8], "
            "duration_s: 30}}}")


async def test_a_held_invoke_whose_socket_closes_as_its_approved_motion_runs(
        tmp_path: Path) -> None:
    """Approved, it runs as the approval decided it; its socket closing then stops its motion
    and answers it in the log. That answer reported the hold's decision (`pending_auth`) as
    what it ran under, not the approval's (`executed`)."""
    api = await Api(tmp_path, bridge_extra=LONG_ARM).start()
    try:
        ws = await api.http.ws_connect("/api/ws", headers=auth("planner"))
        await ws.send_str(json.dumps(invoke("reach", "inv-l")))
        frame = await next_frame(ws, "outcome")
        assert frame["body"]["status"] == "pending", frame
        status, body = await api.call("POST", "/api/hitl/authorize", "ops",
                                      body={"pending_id": frame["body"]["pending_id"]})
        assert (status, body["outcome"]) == (200, "executed"), body
        await ws.close()  # its 30 s trajectory under way
        entry = await _one_result(api, "inv-l")
        assert (entry["status"], entry["outcome"]) == ("failure", "executed"), entry
        assert entry["deny_reason"].startswith("its client left before it was done"), entry
    finally:
        await api.close()
