"""INVOKE / INVOKE_CANCEL (§19) built with the official `rcan` SDK against a real
`rcan-rtps run --sim`, and the INVOKE_RESULTs the bridge answers read with it: a client that
leaves mid-INVOKE (its HTTP request hung up on, its WebSocket closed) stops the skill's motion,
and the audit says why; an INVOKE_CANCEL over the WebSocket stops a running skill, and
withdraws a held one. The same behaviour was tested in process through the suite's own bodies
(tests/api/test_invoke_left.py).

What SDK 3.7.0 offers for §19, and what it lacks (its installed source):
- `rcan.message.MessageType` numbers them (INVOKE = 11, INVOKE_RESULT = 12, INVOKE_CANCEL =
  13); nothing else in the package names them: no builder (as `rcan.safety` has for SAFETY),
  no payload type, no parser.
- `RCANMessage(type=MessageType.INVOKE, payload=...)` is accepted (`cmd` may be empty when
  `type` is set), but `to_dict()` writes neither `type` nor `payload`: the message's kind and
  its payload are lost on the way out. `sdk_wire` adds them back: `message_type` (the
  canonical number, as `rcan.safety` writes it), and the payload's fields where §19 puts them
  (INVOKE: `skill_id` beside `params`; INVOKE_CANCEL: §19.4's `payload` object). The rest is
  the SDK's envelope (`rcan_version`, `msg_id`, `target`…); the bridge ignores and records
  what an INVOKE does not use (§3.5).
- `RCANMessage.from_dict` needs `cmd` and `target` and reads no `type`: it cannot parse an
  INVOKE_RESULT. Replies are read with `rcan.message.RCANResponse.from_dict` (`msg_id`,
  `status`, `result`, `duration_ms`), their kind with `MessageType[body["type"]]`; `reply_to`
  and `error` (§19.3, §19.6) have no SDK field and are read from the body.
- `to_dict()` times the envelope by `timestamp` (Unix seconds), and writes an INVOKE_CANCEL's
  own id as `msg_id` (§19.4's `msg_id` is in `payload`, naming the INVOKE): the bridge reads
  both (docs/rcan-profile.md), so a cancel's answer echoes its own id as `RCANResponse.msg_id`
  and the INVOKE's answer the INVOKE's.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
from collections.abc import AsyncIterator
from typing import Any

import aiohttp
import pytest
from rcan.address import RobotURI
from rcan.encoding import canonical_json
from rcan.message import MessageType, RCANMessage, RCANResponse
from waiting import eventually

from tests.interop.test_demo import Demo, wait_status

BY_CLIENT_LEFT = "INVOKE's client left"  # the `why` of what stopped an INVOKE's motion


@pytest.fixture
async def http() -> AsyncIterator[aiohttp.ClientSession]:
    async with aiohttp.ClientSession() as session:
        yield session


def sdk_invoke(robot: RobotURI, skill: str, **params: Any) -> RCANMessage:
    return RCANMessage(type=MessageType.INVOKE, target=robot, params=params,
                       payload={"skill_id": skill})


def sdk_cancel(robot: RobotURI, invoke: RCANMessage, reason: str) -> RCANMessage:
    return RCANMessage(type=MessageType.INVOKE_CANCEL, target=robot,
                       payload={"msg_id": invoke.msg_id, "reason": reason})


def sdk_wire(message: RCANMessage) -> dict[str, Any]:
    """The SDK's message as it goes out, with what `to_dict()` drops put back (see above)."""
    assert message.type is not None
    body = message.to_dict() | {"message_type": int(message.type)}
    if message.type is MessageType.INVOKE_CANCEL:
        return body | {"payload": message.payload}
    return body | message.payload


def invoke_result(body: dict[str, Any]) -> RCANResponse:
    """An INVOKE_RESULT, read with the SDK (its kind by the SDK's own table)."""
    assert MessageType[body["type"]] is MessageType.INVOKE_RESULT, body
    return RCANResponse.from_dict(body)


def entries(demo: Demo) -> list[dict[str, Any]]:
    return [json.loads(line) for line in demo.audit.read_text().splitlines()]


def results_of(demo: Demo, invoke: RCANMessage) -> list[dict[str, Any]]:
    return [e for e in entries(demo) if e["event"] == "INVOKE_RESULT"
            and e["invoke_id"] == invoke.msg_id]


def stream_end(demo: Demo, invoke: RCANMessage) -> dict[str, Any] | None:
    ends = [e for e in entries(demo) if e["event"] == "STREAM_ENDED"
            and e["message_id"] == invoke.msg_id]
    return ends[0] if ends else None


def audit_ids_hold(demo: Demo) -> None:
    """The SDK recomputes every audit id of the run (as tests/interop/test_sdk_client)."""
    for entry in entries(demo):
        unsigned = {k: v for k, v in entry.items() if k not in ("audit_id", "sig")}
        digest = hashlib.sha256(canonical_json(unsigned)).hexdigest()
        assert entry["audit_id"] == "sha256:" + digest, entry["seq"]


async def robot_of(http: aiohttp.ClientSession, demo: Demo) -> RobotURI:
    status = await wait_status(http, demo, lambda s: s["ros"]["connected"] and
                               s["telemetry"]["position"] is not None)
    return RobotURI.parse(status["ruri"])  # the SDK parses the bridge's RURI


def driving(s: dict[str, Any]) -> bool:
    return bool((s["telemetry"]["velocity"] or {}).get("linear_x", 0.0) > 0.05)


def standing(s: dict[str, Any]) -> bool:
    return (s["telemetry"]["velocity"] or {}).get("linear_x") == 0.0


def stopped_by_client_left(demo: Demo, invoke: RCANMessage) -> dict[str, Any] | None:
    """The entry that stopped the INVOKE's motion because its client left: its move's
    STREAM_ENDED, or the cancel of its goal."""
    for entry in entries(demo):
        if entry.get("message_id") != invoke.msg_id or not entry.get("params"):
            continue
        if entry["event"] == "STREAM_ENDED" or entry.get("action_type") == "cancel_goal":
            return entry if entry["params"].get("why") == BY_CLIENT_LEFT else None
    return None


@pytest.mark.parametrize(("skill", "params", "stopped_by"), [
    ("nudge", {}, "its velocity stream ended, zero sent"),  # 0.3 m/s until ended
    ("go_to", {"x": 15.0, "y": 0.0, "yaw": 0.0}, "its goal cancelled (executed)"),
])
async def test_an_sdk_invoke_hung_up_on_over_rest_stops_the_robot(
        sim: Demo, http: aiohttp.ClientSession, skill: str, params: dict[str, Any],
        stopped_by: str) -> None:
    demo = sim
    robot = await robot_of(http, demo)
    invoke = sdk_invoke(robot, skill, **params)
    async with aiohttp.ClientSession() as client:
        call = asyncio.ensure_future(client.post(
            f"{demo.url}/api/command", json=sdk_wire(invoke),
            headers={"Authorization": f"Bearer {demo.user}"}))
        await wait_status(http, demo, driving)
        call.cancel()  # the client hangs up: its connection closes
    await wait_status(http, demo, standing)
    stop = await eventually(lambda: stopped_by_client_left(demo, invoke), timeout=20,
                            what="the entry that stopped it, why: its client left")
    assert stop["principal"] == "operator", stop
    [answer] = await eventually(lambda: results_of(demo, invoke), timeout=20,
                                what="its INVOKE_RESULT entry")
    assert (answer["principal"], answer["status"]) == ("operator", "failure"), answer
    assert answer["deny_reason"] == f"its client left before it was done: {stopped_by}", answer
    audit_ids_hold(demo)


@contextlib.asynccontextmanager
async def user_socket(http: aiohttp.ClientSession,
                      demo: Demo) -> AsyncIterator[aiohttp.ClientWebSocketResponse]:
    """The demo's USER's WebSocket."""
    async with http.ws_connect(demo.url + "/api/ws",
                               headers={"Authorization": f"Bearer {demo.user}"}) as ws:
        yield ws


async def outcome_frames(ws: aiohttp.ClientWebSocketResponse,
                         count: int) -> list[dict[str, Any]]:
    """The next `count` outcome frames' bodies (status and goal frames skipped)."""
    found: list[dict[str, Any]] = []

    async def read() -> None:
        while len(found) < count:
            msg = await ws.receive()
            assert msg.type is aiohttp.WSMsgType.TEXT, msg
            frame = json.loads(msg.data)
            if frame["type"] == "outcome":
                found.append(frame["body"] | {"http_status": frame["http_status"]})

    await asyncio.wait_for(read(), 30)
    return found


async def test_an_sdk_invoke_cancel_over_the_websocket_stops_the_robot(
        sim: Demo, http: aiohttp.ClientSession) -> None:
    demo = sim
    robot = await robot_of(http, demo)
    invoke = sdk_invoke(robot, "nudge")
    async with user_socket(http, demo) as ws:
        await ws.send_json(sdk_wire(invoke))
        await wait_status(http, demo, driving)
        cancel = sdk_cancel(robot, invoke, "enough")
        await ws.send_json(sdk_wire(cancel))
        answers = await outcome_frames(ws, 2)  # the cancel's and the INVOKE's, either first
        await wait_status(http, demo, standing)
    read = [invoke_result(body) for body in answers]
    assert sorted(r.msg_id for r in read) == sorted([cancel.msg_id, invoke.msg_id]), answers
    for body, result in zip(answers, read, strict=True):
        assert (body["http_status"], result.status, body["reply_to"]) == (
            200, "cancelled", invoke.msg_id), body
        assert body["error"]["name"] == "SkillCancelled", body
    end = stream_end(demo, invoke)
    assert end is not None
    assert (end["params"]["reason"], end["params"]["why"]) == ("cancelled", "INVOKE_CANCEL")
    assert [e["status"] for e in results_of(demo, invoke)] == ["cancelled"]
    audit_ids_hold(demo)


async def sent_held(ws: aiohttp.ClientWebSocketResponse, invoke: Any) -> dict[str, Any]:
    """`invoke` (a skill the demo holds for an OWNER) sent: its 202 `pending` frame."""
    await ws.send_json(sdk_wire(invoke))
    [held] = await outcome_frames(ws, 1)
    assert (held["http_status"], RCANResponse.from_dict(held).status) == (202, "pending"), held
    return held


async def test_an_sdk_invoke_cancel_over_the_websocket_withdraws_a_held_skill(
        sim: Demo, http: aiohttp.ClientSession) -> None:
    """raise_elbow is held for an OWNER (the demo's HiTL gate on arm_joint): its INVOKE_CANCEL
    withdraws it, and nobody may approve it after."""
    demo = sim
    robot = await robot_of(http, demo)
    invoke = sdk_invoke(robot, "raise_elbow")
    async with user_socket(http, demo) as ws:
        held = await sent_held(ws, invoke)
        cancel = sdk_cancel(robot, invoke, "changed my mind")
        await ws.send_json(sdk_wire(cancel))
        answers = await outcome_frames(ws, 2)  # the cancel's and the INVOKE's, either first
    read = [invoke_result(body) for body in answers]
    assert sorted(r.msg_id for r in read) == sorted([cancel.msg_id, invoke.msg_id]), answers
    for withdrawn, result in zip(answers, read, strict=True):
        assert (withdrawn["http_status"], withdrawn["reply_to"], result.status) == (
            200, invoke.msg_id, "cancelled"), withdrawn
        assert withdrawn["error"]["message"] == "withdrawn by INVOKE_CANCEL", withdrawn
    async with http.post(f"{demo.url}/api/hitl/authorize", json={"pending_id": held[
            "pending_id"]}, headers={"Authorization": f"Bearer {demo.owner}"}) as response:
        assert response.status == 404, await response.text()
    log = entries(demo)
    assert [e["event"] for e in log if e["message_id"] == invoke.msg_id] == [
        "PENDING_AUTH", "HITL_WITHDRAWN", "INVOKE_RESULT"]
    audit_ids_hold(demo)


async def test_an_sdk_invoke_held_when_the_robot_is_stopped_is_answered(
        sim: Demo, http: aiohttp.ClientSession) -> None:
    """A stop withdraws all held motion: the held skill's INVOKE is answered on its socket
    then (an INVOKE_RESULT the SDK reads, `failure` naming the stop). Before, its client
    waited for ever after its 202 `pending`."""
    demo = sim
    robot = await robot_of(http, demo)
    invoke = sdk_invoke(robot, "raise_elbow")
    async with user_socket(http, demo) as ws:
        await sent_held(ws, invoke)
        async with http.post(f"{demo.url}/api/command", json={"action": "stop"},
                             headers={"Authorization": f"Bearer {demo.owner}"}) as response:
            assert response.status == 200, await response.text()
        [answer] = await outcome_frames(ws, 1)
    read = invoke_result(answer)
    assert (read.msg_id, answer["reply_to"], read.status, answer["reason"]) == (
        invoke.msg_id, invoke.msg_id, "failure", "hitl_withdrawn"), answer
    assert answer["error"]["message"].startswith(
        "withdrawn: the robot was stopped while it was held (a stop by "), answer
    log = entries(demo)
    assert [e["event"] for e in log if e["message_id"] == invoke.msg_id] == [
        "PENDING_AUTH", "HITL_WITHDRAWN", "INVOKE_RESULT"]
    audit_ids_hold(demo)


async def test_an_sdk_invoke_whose_websocket_closes_stops_the_robot(
        sim: Demo, http: aiohttp.ClientSession) -> None:
    demo = sim
    robot = await robot_of(http, demo)
    invoke = sdk_invoke(robot, "nudge")
    async with user_socket(http, demo) as ws:
        await ws.send_json(sdk_wire(invoke))
        await wait_status(http, demo, driving)
    await wait_status(http, demo, standing)
    end = await eventually(lambda: stream_end(demo, invoke), timeout=20,
                           what="the nudge's STREAM_ENDED")
    assert (end["params"]["reason"], end["params"]["why"]) == ("cancelled", BY_CLIENT_LEFT), end
    [answer] = await eventually(lambda: results_of(demo, invoke), timeout=20,
                                what="its INVOKE_RESULT entry")
    assert answer["status"] == "failure", answer
    assert answer["deny_reason"].startswith("its client left before it was done"), answer
    audit_ids_hold(demo)
