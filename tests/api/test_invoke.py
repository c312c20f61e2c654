"""Issue 24: INVOKE / INVOKE_CANCEL (§19) of the skills `bridge.skills` declares.

An INVOKE runs its skill's action through the governor (roles, invariants, HiTL, audit); its
reply is an INVOKE_RESULT as rcan-spec's §19 writes it. Shapes: tests/data/rcan-spec/.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from rcan_rtps.api import GoalView
from rcan_rtps.governance import Principal
from rcan_rtps.rcan import MoveParams, Role
from tests.api.apihelpers import ZERO, Api, auth, next_frame

TARGET = "rcan://registry.local/clearpath/husky/v1/a200-0001"
DATA = Path(__file__).parents[1] / "data" / "rcan-spec"
PROSE = json.loads((DATA / "section-19-examples.json").read_text())
SKILLS = ("skills: {go_home: {action: navigate, params: {x: 0, y: 0, yaw: 0}}, "
          "go_to: {action: navigate, allow: [x, y, yaw]}, "
          "nudge: {action: move, params: {linear_x: 0.3}, allow: [duration_s]}, "
          "raise_elbow: {action: arm_joint, params: {joints: [elbow], positions: [0.8], "
          "duration_s: 1}}}")


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[Api]:
    harness = await Api(tmp_path, bridge_extra=SKILLS).start()
    yield harness
    await harness.close()


def invoke(skill: str, msg_id: str, **fields: Any) -> dict[str, Any]:
    return {"type": "INVOKE", "skill": skill, "msg_id": msg_id, **fields}


def cancel(msg_id: str, **fields: Any) -> dict[str, Any]:
    """§19.4's shape (section-19-examples.json `invokeCancel`) for the INVOKE `msg_id`."""
    body: dict[str, Any] = json.loads(json.dumps(PROSE["invokeCancel"]))
    body["payload"]["msg_id"] = msg_id
    return {**body, **fields}


def ended(goal_id: str, state: str, result: dict[str, Any] | None = None) -> GoalView:
    return GoalView(goal_id=goal_id, action="/robot1/navigate_to_pose", command="navigate",
                    state=state, result=result, created_ms=1, updated_ms=2)


async def sent(api: Api, action: str, count: int = 1) -> None:
    """Until the dispatcher has been handed `count` commands of `action`."""
    async def wait() -> None:
        while sum(a == action for a, _ in api.dispatcher.calls) < count:
            await asyncio.sleep(0.01)
    await asyncio.wait_for(wait(), timeout=10)


async def test_an_invoke_runs_its_skill_through_the_governor(api: Api) -> None:
    status, body = await api.command("planner", invoke("nudge", "inv-1",
                                                       params={"duration_s": 1.0}))
    assert (status, body["type"], body["status"], body["skill"]) == (
        200, "INVOKE_RESULT", "success", "nudge"), body
    assert (body["reply_to"], body["outcome"]) == ("inv-1", "executed")
    assert [(a, p["linear_x"]) for a, p in api.dispatcher.calls] == [("move", 0.3)]
    entry = api.entry(body["audit_id"])
    assert (entry["event"], entry["action_type"], entry["message_id"]) == (
        "COMMAND_DISPATCHED", "move", "inv-1")
    assert entry["params"] == {"linear_x": 0.3, "duration_s": 1.0}
    assert entry["rcan"] == {"skill": "nudge"}


@pytest.mark.parametrize(("who", "body", "http", "status", "code"), [
    ("planner", invoke("fly", "i-1"), 404, "not_found", 7001),  # not declared
    ("planner", invoke("nudge", "i-2", params={"linear_x": 0.9}), 400, "invalid_params",
     7004),  # fixed by the skill
    ("planner", invoke("go_to", "i-3", params={"x": "far", "y": 0, "yaw": 0}), 400,
     "invalid_params", 7004),
    ("viewer", invoke("nudge", "i-4"), 403, "unauthorized", 7003),  # GUEST: no motion
    ("planner", invoke("go_to", "i-5", params={"x": 50, "y": 0, "yaw": 0}), 409, "failure",
     7006),  # outside the workspace: the invariant refuses it
])
async def test_a_refused_invoke_says_why_and_is_audited(api: Api, who: str,
                                                         body: dict[str, Any], http: int,
                                                         status: str, code: int) -> None:
    got, reply = await api.command(who, body)
    assert (got, reply["type"], reply["status"], reply["error"]["code"]) == (
        http, "INVOKE_RESULT", status, code), reply
    assert reply["reply_to"] == body["msg_id"] and reply["error"]["message"]
    assert api.dispatcher.calls == []
    entry = api.entry(reply["audit_id"])
    assert (entry["event"], entry["message_id"]) == ("COMMAND_REJECTED", body["msg_id"])
    assert entry["rcan"]["skill"] == body["skill"]


async def test_an_undeclared_skill_names_the_declared_ones(api: Api) -> None:
    _, reply = await api.command("planner", PROSE["invokeMessage"])  # pick_and_place
    assert reply["error"]["name"] == "SkillNotFound"
    assert "go_home" in reply["error"]["message"], reply


async def test_a_goal_skill_is_answered_when_the_goal_ends(api: Api) -> None:
    reply = asyncio.create_task(api.command("planner", invoke("go_home", "inv-nav")))
    await sent(api, "navigate")
    assert not reply.done()  # §19: one INVOKE_RESULT, the final one
    api.robot.goal_changed(ended("goal-1", "succeeded", {"error_code": 0}))
    status, body = await asyncio.wait_for(reply, 10)
    assert (status, body["status"], body["goal_id"], body["result"]) == (
        200, "success", "goal-1", {"error_code": 0}), body


async def test_a_failed_goal_is_a_failed_skill(api: Api) -> None:
    reply = asyncio.create_task(api.command("planner", invoke("go_home", "inv-nav")))
    await sent(api, "navigate")
    api.robot.goal_changed(ended("goal-1", "aborted"))
    _, body = await asyncio.wait_for(reply, 10)
    assert (body["status"], body["error"]["name"]) == ("failure", "SkillFailed"), body


async def _goal_cancel_sent(api: Api, goal_id: str) -> None:
    async def cancelling() -> None:
        while api.dispatcher.cancelled != [goal_id]:
            await asyncio.sleep(0.01)
    await asyncio.wait_for(cancelling(), 10)


async def test_invoke_cancel_cancels_the_goal_through_the_governor(api: Api) -> None:
    reply = asyncio.create_task(api.command("planner", invoke("go_home", "inv-nav")))
    await sent(api, "navigate")
    cancelled = asyncio.create_task(api.command("planner", cancel("inv-nav")))
    await _goal_cancel_sent(api, "goal-1")
    entry = [e for e in api.entries if e.get("action_type") == "cancel_goal"][-1]
    assert (entry["event"], entry["principal"], entry["params"]["goal_id"]) == (
        "COMMAND_DISPATCHED", "planner", "goal-1")
    api.robot.goal_changed(ended("goal-1", "canceled"))
    for task in (reply, cancelled):
        status, body = await asyncio.wait_for(task, 10)
        assert (status, body["status"], body["reply_to"], body["error"]["code"]) == (
            200, "cancelled", "inv-nav", 7007), body


async def test_an_invoke_past_its_timeout_is_cancelled(api: Api) -> None:
    status, body = await api.command("planner", invoke("go_home", "inv-t", timeout_ms=50))
    assert (status, body["status"], body["error"]["code"]) == (200, "timeout", 7002), body
    assert api.dispatcher.cancelled == ["goal-1"]


async def test_a_cancel_of_nothing_running_says_why(api: Api) -> None:
    status, body = await api.command("planner", cancel("never-sent"))
    assert (status, body["status"], body["error"]["code"]) == (404, "not_found", 7001), body
    assert api.entry(body["audit_id"])["event"] == "COMMAND_REJECTED"
    status, _ = await api.command("planner", invoke("nudge", "inv-done",
                                                    params={"duration_s": 1.0}))
    assert status == 200
    status, body = await api.command("planner", cancel("inv-done"))
    assert (status, body["reason"], body["status"]) == (409, "invoke_finished", "success"), body
    # §19.4: only its invoker cancels an INVOKE
    reply = asyncio.create_task(api.command("planner", invoke("go_home", "inv-nav")))
    await sent(api, "navigate")
    status, body = await api.command("ops", cancel("inv-nav"))
    assert (status, body["status"]) == (404, "not_found"), body
    assert api.dispatcher.cancelled == []
    api.robot.goal_changed(ended("goal-1", "succeeded"))
    assert (await reply)[1]["status"] == "success"


async def test_a_held_invoke_is_pending_and_its_cancel_withdraws_it(api: Api) -> None:
    status, body = await api.command("planner", invoke("raise_elbow", "inv-arm"))
    assert (status, body["outcome"], body["status"], body["msg_id"]) == (
        202, "pending_auth", "pending", "inv-arm"), body
    flat = {**json.loads((DATA / "invoke-cancel.json").read_text())["examples"][0],
            "message_type": 13, "ruri": TARGET, "principal_id": "planner",
            "cancel_msg_id": "inv-arm"}
    status, body = await api.command("planner", flat)
    assert (status, body["status"], body["reason"]) == (200, "cancelled", "hitl_withdrawn"), body
    assert api.gov.pending() == [] and api.dispatcher.calls == []
    assert [e["event"] for e in api.entries[-2:]] == ["HITL_WITHDRAWN", "INVOKE_RESULT"]


async def test_the_websocket_takes_them_and_is_not_held_up(api: Api) -> None:
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        await ws.send_str(json.dumps(invoke("go_home", "inv-ws")))
        await sent(api, "navigate")
        await ws.send_str(json.dumps(invoke("fly", "inv-no")))  # answered while it runs
        frame = await next_frame(ws, "outcome")
        assert (frame["http_status"], frame["body"]["reply_to"]) == (404, "inv-no"), frame
        api.robot.goal_changed(ended("goal-1", "succeeded"))
        frame = await next_frame(ws, "outcome")
        assert (frame["body"]["reply_to"], frame["body"]["status"]) == (
            "inv-ws", "success"), frame


def results(api: Api, invoke_id: str) -> list[dict[str, Any]]:
    return [e for e in api.entries if e["event"] == "INVOKE_RESULT"
            and e.get("invoke_id") == invoke_id]


async def test_each_answer_carries_the_suites_names_and_is_audited_first(api: Api) -> None:
    """rcan-spec's conformance suite: an INVOKE_RESULT has invoke_id, status and payload
    (L1-INVOKE-003), and its audit entry invoke_id, status and outcome (L3-INVOKE-001); the
    entry is on disk when the answer is sent."""
    status, body = await api.command("planner", invoke("nudge", "inv-1",
                                                       params={"duration_s": 1.0}))
    assert (status, body["invoke_id"], body["reply_to"], body["payload"]) == (
        200, "inv-1", "inv-1", {}), body
    [entry] = results(api, "inv-1")
    assert (entry["status"], entry["outcome"], entry["message_id"], entry["principal"],
            entry["role"]) == ("success", "executed", "inv-1", "planner", "USER"), entry
    assert entry["params"]["skill"] == "nudge" and entry["params"]["duration_ms"] >= 0
    assert "deny_reason" not in entry or entry["deny_reason"] is None
    # the lifecycle, from the log alone: the command the skill ran, the end of the stream it
    # started (its move is done then, not when it is sent), then its result
    lifecycle = [e["event"] for e in api.entries if e.get("message_id") == "inv-1"]
    assert lifecycle == ["COMMAND_DISPATCHED", "STREAM_ENDED", "INVOKE_RESULT"]


async def test_a_goal_skills_result_is_audited_when_the_goal_ends(api: Api) -> None:
    reply = asyncio.create_task(api.command("planner", invoke("go_home", "inv-nav")))
    await sent(api, "navigate")
    assert results(api, "inv-nav") == []  # no result yet: the goal runs
    api.robot.goal_changed(ended("goal-1", "succeeded", {"error_code": 0}))
    _, body = await asyncio.wait_for(reply, 10)
    assert body["payload"] == body["result"] == {"error_code": 0}, body
    [entry] = results(api, "inv-nav")
    assert (entry["status"], entry["outcome"], entry["params"]["goal_id"],
            entry["params"]["result"]) == ("success", "executed", "goal-1", {"error_code": 0})

    _, body = await api.command("planner", invoke("go_home", "inv-t", timeout_ms=50))
    assert body["status"] == "timeout"
    [entry] = results(api, "inv-t")
    assert (entry["status"], entry["params"]["error"]) == (
        "timeout", {"code": 7002, "name": "SkillTimeout"}), entry
    assert "not done within 50 ms" in entry["deny_reason"]


@pytest.mark.parametrize(("who", "body", "status", "outcome"), [
    ("planner", invoke("fly", "i-1"), "not_found", "denied"),  # before it became a command
    ("planner", invoke("nudge", "i-2", params={"linear_x": 0.9}), "invalid_params", "denied"),
    ("viewer", invoke("nudge", "i-4"), "unauthorized", "denied"),  # the governor's refusal
    ("planner", invoke("go_to", "i-5", params={"x": 50, "y": 0, "yaw": 0}), "failure",
     "safety_violation"),
])
async def test_a_refused_invokes_result_is_audited(api: Api, who: str, body: dict[str, Any],
                                                   status: str, outcome: str) -> None:
    _, reply = await api.command(who, body)
    assert (reply["invoke_id"], reply["payload"]) == (body["msg_id"], {}), reply
    [entry] = results(api, body["msg_id"])
    assert (entry["status"], entry["outcome"], entry["params"]["error"]["code"]) == (
        status, outcome, reply["error"]["code"]), entry
    assert entry["deny_reason"] == reply["error"]["message"]
    refused = api.entry(reply["audit_id"])  # the refusal's own entry comes first
    assert (refused["event"], refused["seq"] < entry["seq"]) == ("COMMAND_REJECTED", True)


async def test_a_cancelled_invokes_result_is_audited_once(api: Api) -> None:
    reply = asyncio.create_task(api.command("planner", invoke("go_home", "inv-nav")))
    await sent(api, "navigate")
    cancelled = asyncio.create_task(api.command("planner", cancel("inv-nav")))
    await _goal_cancel_sent(api, "goal-1")
    api.robot.goal_changed(ended("goal-1", "canceled"))
    await asyncio.wait_for(asyncio.gather(reply, cancelled), 10)
    [entry] = results(api, "inv-nav")  # one INVOKE, one INVOKE_RESULT (§19.1)
    assert entry["status"] == "cancelled"
    status, body = await api.command("planner", cancel("inv-nav"))  # answered: repeated
    assert (status, body["reason"], body["invoke_id"]) == (409, "invoke_finished", "inv-nav")
    assert len(results(api, "inv-nav")) == 1


async def test_the_skills_are_listed_as_a_capability_with_their_declarations(
        api: Api) -> None:
    """§18/§19.7: the `invoke` capability lists every skill an INVOKE may name; beside it,
    what each runs and who may run it (any principal reads it)."""
    status, body = await api.call("GET", "/api/skills", "viewer")
    assert status == 200, body
    assert body["caps"] == {"invoke": {"version": "1.0", "required": False, "params": {
        "skills": ["go_home", "go_to", "nudge", "raise_elbow"]}}}
    assert body["skills"]["nudge"] == {"action": "move", "role": "USER",
                                       "params": {"linear_x": 0.3}, "allow": ["duration_s"],
                                       "description": ""}
    assert body["skills"]["go_to"]["allow"] == ["x", "y", "yaw"]
    assert body["skills"]["raise_elbow"]["action"] == "arm_joint"
    status, _ = await api.call("GET", "/api/skills", None)
    assert status == 401
    _, document = await api.call("GET", "/api/openapi.json", "viewer")
    assert "SkillList" in document["components"]["schemas"]
    assert "/api/skills" in document["paths"]


async def test_a_bridge_without_skills_lists_none(tmp_path: Path) -> None:
    harness = await Api(tmp_path).start()
    try:
        status, body = await harness.call("GET", "/api/skills", "viewer")
    finally:
        await harness.close()
    assert (status, body) == (200, {"caps": {"invoke": {"version": "1.0", "required": False,
                                                        "params": {"skills": []}}},
                                    "skills": {}})


async def test_no_invoke_result_is_audited_after_the_bridge_stopped(api: Api) -> None:
    """BRIDGE_STOPPED is the last entry: a goal skill answered after it is only logged."""
    await api.gov.stop()
    await api.gov.invoke_result(Principal("planner", Role.USER), invoke_id="inv-late",
                                status="success", outcome="executed", facts={})
    assert api.entries[-1]["event"] == "BRIDGE_STOPPED"


# -- an arm's skill: its trajectory runs on after it is sent ---------------------------------
ARM_SKILLS = ("skills: {wave: {action: arm_joint, params: {joints: [elbow], positions: [0.8]}, "
              "allow: [duration_s]}}")


@pytest.fixture
async def arm_api(tmp_path: Path) -> AsyncIterator[Api]:
    harness = await Api(tmp_path, bridge_extra=ARM_SKILLS, gates="[]").start()
    yield harness
    await harness.close()


def wave(msg_id: str, duration_s: float, **fields: Any) -> dict[str, Any]:
    return invoke("wave", msg_id, params={"duration_s": duration_s}, **fields)


async def test_an_arm_skill_is_answered_when_its_trajectory_s_time_is_up(arm_api: Api
                                                                         ) -> None:
    """Not when it is sent: the skill is done when the arm is (a topic reports no end)."""
    reply = asyncio.create_task(arm_api.command("planner", wave("inv-w", 0.3)))
    await sent(arm_api, "arm_joint")
    assert not reply.done()
    status, body = await asyncio.wait_for(reply, 10)
    assert (status, body["status"], body["outcome"]) == (200, "success", "executed"), body
    assert arm_api.dispatcher.holds == []


async def test_invoke_cancel_holds_an_arm_skill_where_it_is(arm_api: Api) -> None:
    reply = asyncio.create_task(arm_api.command("planner", wave("inv-w", 60.0)))
    await sent(arm_api, "arm_joint")
    status, body = await arm_api.command("planner", cancel("inv-w"))
    assert (status, body["status"], body["reply_to"]) == (200, "cancelled", "inv-w"), body
    assert arm_api.dispatcher.holds == [["inv-w"]] and arm_api.dispatcher.running == []
    assert (await asyncio.wait_for(reply, 10))[1]["status"] == "cancelled"
    [entry] = [e for e in arm_api.entries if e.get("action_type") == "hold_trajectory"]
    assert (entry["event"], entry["principal"], entry["params"]["sent_by"],
            entry["params"]["why"], entry["sent_first"]) == (
        "COMMAND_DISPATCHED", "planner", "inv-w", "INVOKE_CANCEL", True)


async def test_a_cancels_answer_echoes_its_own_id_and_names_the_invoke(arm_api: Api) -> None:
    """Both answers are the INVOKE_RESULT; each has the id of the message it answers as
    `msg_id` (RCANResponse's echo), `reply_to` the INVOKE. Before, the cancel's answer had the
    INVOKE's msg_id: a client could not tell the two apart."""
    reply = asyncio.create_task(arm_api.command("planner", wave("inv-e", 60.0)))
    await sent(arm_api, "arm_joint")
    status, body = await arm_api.command("planner", cancel("inv-e", message_id="cancel-e"))
    assert (status, body["msg_id"], body["reply_to"]) == (200, "cancel-e", "inv-e"), body
    status, body = await asyncio.wait_for(reply, 10)
    assert (status, body["msg_id"], body["reply_to"]) == (200, "inv-e", "inv-e"), body


async def test_an_arm_skill_past_its_timeout_is_held(arm_api: Api) -> None:
    status, body = await arm_api.command("planner", wave("inv-t", 60.0, timeout_ms=50))
    assert (status, body["status"], body["error"]["code"]) == (200, "timeout", 7002), body
    assert arm_api.dispatcher.holds == [["inv-t"]]


async def test_an_arm_skill_a_stop_held_is_not_a_success(arm_api: Api) -> None:
    reply = asyncio.create_task(arm_api.command("planner", wave("inv-s", 0.5)))
    await sent(arm_api, "arm_joint")
    status, _ = await arm_api.command("planner", {"action": "stop"})
    assert status == 200
    status, body = await asyncio.wait_for(reply, 10)
    assert (status, body["status"]) == (200, "failure"), body
    assert "a stop held the arm" in body["error"]["message"], body


async def test_an_arm_skill_a_stop_held_is_no_success_for_another_principals_of_its_id(
        arm_api: Api) -> None:
    """Message ids are unique per principal only. The planner's arm skill is held by its stop;
    the OWNER's skill of the same msg_id then runs on that arm. The planner's INVOKE, its time
    up, is a failure: before, `trajectory_running` asked by id alone, and it reported success
    on the OWNER's trajectory."""
    api = arm_api
    mine = asyncio.create_task(api.command("planner", wave("inv-same", 0.5)))
    await sent(api, "arm_joint")
    assert (await api.command("planner", {"action": "stop"}))[0] == 200
    theirs = asyncio.create_task(api.command("ops", wave("inv-same", 60.0)))
    await sent(api, "arm_joint", 2)
    status, body = await asyncio.wait_for(mine, 10)
    assert (status, body["status"]) == (200, "failure"), body
    assert "a stop held the arm" in body["error"]["message"], body
    assert api.dispatcher.running == ["inv-same"]  # the OWNER's, untouched
    status, body = await api.command("ops", cancel("inv-same"))  # its own id: its own arm
    assert (status, body["status"]) == (200, "cancelled"), body
    assert (await asyncio.wait_for(theirs, 10))[1]["status"] == "cancelled"
    assert [e["principal"] for e in results(api, "inv-same")] == ["planner", "ops"]


async def test_a_cancel_that_cannot_hold_the_arm_says_so_and_the_skill_runs_on(
        arm_api: Api) -> None:
    arm_api.dispatcher.unheard_arms = True  # no joint_states: no hold at a guess
    reply = asyncio.create_task(arm_api.command("planner", wave("inv-u", 0.5)))
    await sent(arm_api, "arm_joint")
    status, body = await arm_api.command("planner", cancel("inv-u"))
    assert (status, body["outcome"], body["error_code"]) == (
        503, "failed", "ROBOT_UNAVAILABLE"), body
    assert "no joint_states heard" in body["reason"], body
    [entry] = [e for e in arm_api.entries if e.get("action_type") == "hold_trajectory"]
    assert entry["event"] == "COMMAND_FAILED", entry
    # The arm ran on: its INVOKE is answered when its time is up, as it was.
    assert (await asyncio.wait_for(reply, 10))[1]["status"] == "success"


async def cancelled_while_decided(api: Api, body: dict[str, Any]) -> None:
    """The INVOKE `body` is cancelled while its command waits for the robot (`ready`); both
    the INVOKE and its cancel are answered `cancelled`."""
    api.dispatcher.hold_ready = asyncio.Event()  # its command waits for the robot
    reply = asyncio.create_task(api.command("planner", body))
    await asyncio.wait_for(api.dispatcher.ready_entered.wait(), 10)
    cancelled = asyncio.create_task(api.command("planner", cancel(body["msg_id"])))
    await asyncio.sleep(0.05)
    api.dispatcher.hold_ready.set()
    for task in (reply, cancelled):
        status, answer = await asyncio.wait_for(task, 10)
        assert (status, answer["status"]) == (200, "cancelled"), answer


async def test_a_cancel_while_the_arm_skill_is_decided_holds_it_once_sent(
        arm_api: Api) -> None:
    await cancelled_while_decided(arm_api, wave("inv-d", 60.0))
    assert arm_api.dispatcher.holds == [["inv-d"]]


# -- a move's skill: its velocity stream drives on after it is sent ---------------------------
MOVE_SKILLS = SKILLS + "\n  motion: {principal_priorities: {ops: 100}}"  # ops preempts


@pytest.fixture
async def move_api(tmp_path: Path) -> AsyncIterator[Api]:
    harness = await Api(tmp_path, bridge_extra=MOVE_SKILLS).start()
    yield harness
    await harness.close()


def nudge(msg_id: str, duration_s: float | None = None, **fields: Any) -> dict[str, Any]:
    """The skill `nudge` (linear_x 0.3): for `duration_s`, else until something ends it."""
    params = {} if duration_s is None else {"duration_s": duration_s}
    return invoke("nudge", msg_id, params=params, **fields)


def stream_ends(api: Api, message_id: str) -> list[dict[str, Any]]:
    return [e for e in api.entries if e["event"] == "STREAM_ENDED"
            and e["message_id"] == message_id]


async def test_a_move_skill_is_answered_when_its_stream_ends(move_api: Api) -> None:
    """Not when it is sent: the skill is done when its duration is (STREAM_ENDED `completed`
    first, then INVOKE_RESULT `success`)."""
    api = move_api
    reply = asyncio.create_task(api.command("planner", nudge("inv-m", 0.5)))
    await sent(api, "move")
    assert not reply.done()
    status, body = await asyncio.wait_for(reply, 10)
    assert (status, body["status"], body["outcome"]) == (200, "success", "executed"), body
    [end] = stream_ends(api, "inv-m")
    [result] = results(api, "inv-m")
    assert (end["params"]["reason"], end["seq"] < result["seq"]) == ("completed", True), end
    assert api.dispatcher.samples[-1] == ZERO and api.gov.streams.active is None


async def test_invoke_cancel_ends_a_move_skills_stream(move_api: Api) -> None:
    api = move_api
    reply = asyncio.create_task(api.command("planner", nudge("inv-c")))  # until ended
    await sent(api, "move")
    status, body = await api.command("planner", cancel("inv-c"))
    assert (status, body["status"], body["reply_to"], body["error"]["code"]) == (
        200, "cancelled", "inv-c", 7007), body
    assert (await asyncio.wait_for(reply, 10))[1]["status"] == "cancelled"
    assert api.gov.streams.active is None and api.dispatcher.samples[-1] == ZERO
    [end] = stream_ends(api, "inv-c")
    assert (end["params"]["reason"], end["params"]["ended_by"], end["params"]["why"],
            end["applied"]["zero_sent"]) == ("cancelled", "planner", "INVOKE_CANCEL", True), end
    [result] = results(api, "inv-c")  # one INVOKE_RESULT, after the stream's end
    assert (result["status"], end["seq"] < result["seq"]) == ("cancelled", True), result


async def test_a_move_skill_a_stop_ended_is_a_failure(move_api: Api) -> None:
    api = move_api
    reply = asyncio.create_task(api.command("planner", nudge("inv-s")))
    await sent(api, "move")
    status, _ = await api.command("ops", {"action": "stop"})
    assert status == 200
    status, body = await asyncio.wait_for(reply, 10)
    assert (status, body["status"], body["error"]["code"]) == (200, "failure", 7006), body
    assert body["error"]["message"] == "the move ended before it was done: a stop ended it (ops)"
    assert stream_ends(api, "inv-s")[0]["params"]["reason"] == "stopped"


async def test_a_move_skill_another_principals_higher_move_preempted_is_a_failure(
        move_api: Api) -> None:
    api = move_api
    reply = asyncio.create_task(api.command("planner", nudge("inv-p")))
    await sent(api, "move")
    status, taken = await api.command("ops", {"action": "move", "params": {"linear_x": 0.1}})
    assert (status, taken["outcome"]) == (200, "executed"), taken
    status, body = await asyncio.wait_for(reply, 10)
    assert (status, body["status"]) == (200, "failure"), body
    assert "preempted it (ops)" in body["error"]["message"], body
    active = api.gov.streams.active  # ops's move drives on
    assert active is not None and active.owner == "ops"
    status, body = await api.command("planner", cancel("inv-p"))  # answered: it stands
    assert (status, body["reason"], body["status"]) == (409, "invoke_finished", "failure"), body
    assert api.gov.streams.active is active


async def test_a_move_skill_past_its_timeout_is_ended_with_zero(move_api: Api) -> None:
    api = move_api
    status, body = await api.command("planner", nudge("inv-t", timeout_ms=50))
    assert (status, body["status"], body["error"]["code"]) == (200, "timeout", 7002), body
    assert "not done within 50 ms" in body["error"]["message"], body
    assert api.gov.streams.active is None and api.dispatcher.samples[-1] == ZERO
    [end] = stream_ends(api, "inv-t")
    assert (end["params"]["reason"], end["params"]["why"], end["applied"]["zero_sent"]) == (
        "cancelled", "INVOKE timeout", True), end


async def test_a_cancel_while_the_move_skill_is_decided_ends_its_stream_once_started(
        move_api: Api) -> None:
    api = move_api
    await cancelled_while_decided(api, nudge("inv-d"))
    assert api.gov.streams.active is None and api.dispatcher.samples[-1] == ZERO
    assert stream_ends(api, "inv-d")[0]["params"]["why"] == "INVOKE_CANCEL"


async def test_a_cancel_of_a_move_its_sender_replaced_leaves_the_new_stream(
        move_api: Api) -> None:
    """The planner's next move replaced the skill's stream; its INVOKE_CANCEL, arriving while
    that end is being answered, must not end the move that drives now."""
    api = move_api
    release, answering = asyncio.Event(), asyncio.Event()
    invoke_result = api.gov.invoke_result

    async def held_result(principal: Principal, **fields: Any) -> None:
        if fields["invoke_id"] == "inv-r":  # the INVOKE's answer waits (a busy disk)
            answering.set()
            await release.wait()
        await invoke_result(principal, **fields)

    api.gov.invoke_result = held_result  # type: ignore[method-assign]
    reply = asyncio.create_task(api.command("planner", nudge("inv-r")))
    await sent(api, "move")
    status, taken = await api.command("planner", {"action": "move",
                                                  "params": {"linear_x": 0.2}})
    assert (status, taken["outcome"]) == (200, "executed"), taken
    await asyncio.wait_for(answering.wait(), 10)
    cancelled = asyncio.create_task(api.command("planner", cancel("inv-r")))
    await asyncio.sleep(0.05)
    release.set()
    for task in (reply, cancelled):
        status, body = await asyncio.wait_for(task, 10)
        assert (status, body["status"]) == (200, "failure"), body
        assert "another move of its sender's replaced it" in body["error"]["message"], body
    active = api.gov.streams.active
    assert active is not None and active.message_id == taken["message_id"]
    assert ZERO not in api.dispatcher.samples
    assert MoveParams(linear_x=0.2, linear_y=0.0, angular_z=0.0) in api.dispatcher.samples


async def test_a_cancel_while_a_held_invoke_is_decided_withdraws_it_once_held(
        api: Api) -> None:
    """Red team 13: an INVOKE_CANCEL that came while the INVOKE was being held (its
    PENDING_AUTH entry on its way to the disk) left it held: a reviewer's approval later
    moved the arm its invoker had cancelled."""
    release, entered = api.hold_decisions(lambda c: c.action == "arm_joint", decided=True)
    reply = asyncio.create_task(api.command("planner", invoke("raise_elbow", "inv-h")))
    await asyncio.wait_for(entered.wait(), 10)
    cancelled = asyncio.create_task(api.command("planner", cancel("inv-h")))
    await asyncio.sleep(0.05)
    release.set()
    for task in (reply, cancelled):
        status, body = await asyncio.wait_for(task, 10)
        assert (status, body["status"]) == (200, "cancelled"), body
    assert api.gov.pending() == [] and api.dispatcher.calls == []
    assert len(results(api, "inv-h")) == 1


async def test_two_cancels_while_the_arm_skill_is_decided_hold_it_and_answer_both(
        arm_api: Api) -> None:
    """Red team 13: a second INVOKE_CANCEL (a client retrying) that came while the first's
    hold, made as the trajectory was sent, was being audited held the arm again and set the
    hold's result first: the INVOKE's own setting then raised (InvalidStateError), its reply
    was a 500 and it stayed `running` for ever."""
    api = arm_api
    api.dispatcher.hold_ready = asyncio.Event()  # its command waits for the robot
    release, holding = asyncio.Event(), asyncio.Event()
    hold_trajectory = api.gov.hold_trajectory

    async def slow_hold(sent_by: str, principal: Principal, **fields: Any) -> Any:
        if not holding.is_set():  # the first hold's entry waits (a busy disk)
            holding.set()
            await release.wait()
        return await hold_trajectory(sent_by, principal, **fields)

    api.gov.hold_trajectory = slow_hold  # type: ignore[method-assign]
    reply = asyncio.create_task(api.command("planner", wave("inv-2", 60.0)))
    await asyncio.wait_for(api.dispatcher.ready_entered.wait(), 10)
    first = asyncio.create_task(api.command("planner", cancel("inv-2")))
    await asyncio.sleep(0.05)
    api.dispatcher.hold_ready.set()
    await asyncio.wait_for(holding.wait(), 10)
    second = asyncio.create_task(api.command("planner", cancel("inv-2")))
    await asyncio.sleep(0.05)
    release.set()
    for task in (reply, first, second):
        status, body = await asyncio.wait_for(task, 10)
        assert (status, body["status"]) == (200, "cancelled"), body
    assert api.dispatcher.holds == [["inv-2"]]
    assert len(results(api, "inv-2")) == 1


async def test_two_cancels_of_a_held_invoke_answer_it_once(api: Api) -> None:
    """Red team 13: a second INVOKE_CANCEL that came while the first's withdrawal was being
    audited withdrew it again (refused: no longer held) and answered the INVOKE a second time,
    a `failure` after its `cancelled` (§19.1: one INVOKE_RESULT)."""
    status, body = await api.command("planner", invoke("raise_elbow", "inv-w2"))
    assert (status, body["status"]) == (202, "pending"), body
    release, withdrawing = asyncio.Event(), asyncio.Event()
    withdraw = api.gov.withdraw

    async def slow_withdraw(pending_id: str, principal: Principal, *args: Any,
                            **fields: Any) -> Any:
        withdrawing.set()  # its entry waits (a busy disk)
        await release.wait()
        return await withdraw(pending_id, principal, *args, **fields)

    api.gov.withdraw = slow_withdraw  # type: ignore[method-assign]
    first = asyncio.create_task(api.command("planner", cancel("inv-w2")))
    await asyncio.wait_for(withdrawing.wait(), 10)
    second = asyncio.create_task(api.command("planner", cancel("inv-w2")))
    await asyncio.sleep(0.05)
    release.set()
    for task in (first, second):
        status, body = await asyncio.wait_for(task, 10)
        assert (status, body["status"]) == (200, "cancelled"), body
    assert [e["status"] for e in results(api, "inv-w2")] == ["cancelled"]


async def test_an_invoke_whose_websocket_closed_is_still_answered_in_the_log(api: Api) -> None:
    """Red team 13: the socket's close cancelled the INVOKE's wait for its goal (nobody left
    to answer), and no INVOKE_RESULT was ever audited: its lifecycle had no end in the log."""
    async with api.http.ws_connect("/api/ws", headers=auth("planner")) as ws:
        await ws.send_str(json.dumps(invoke("go_home", "inv-gone")))
        await sent(api, "navigate")

    async def answered() -> list[dict[str, Any]]:
        while not (found := results(api, "inv-gone")):
            await asyncio.sleep(0.01)
        return found

    [entry] = await asyncio.wait_for(answered(), 10)
    assert (entry["status"], entry["params"]["error"]["name"]) == ("failure", "SkillFailed"), entry
    api.robot.goal_changed(ended("goal-1", "canceled"))  # its end, heard later, adds nothing
    await asyncio.sleep(0.05)
    assert len(results(api, "inv-gone")) == 1
    status, body = await api.command("planner", cancel("inv-gone"))
    assert (status, body["status"]) == (409, "failure"), body  # §19.4: the earlier one stands


async def test_an_arm_skill_whose_time_is_up_while_its_cancel_is_audited_is_cancelled(
        arm_api: Api) -> None:
    """Red team 13: the trajectory's time came up while its INVOKE_CANCEL's hold (made at
    once) was being audited: the arm no longer ran, so the INVOKE and the cancel were both
    answered `failure`, 'a stop held the arm', of an arm its own client's cancel held."""
    api = arm_api
    release, auditing = asyncio.Event(), asyncio.Event()
    write_ahead = api.gov._steps.write_ahead

    async def slow_write(entry: Any, *, urgent: bool = False) -> Any:
        if entry.action_type == "hold_trajectory":  # the hold's entry waits (a busy disk)
            auditing.set()
            await release.wait()
        return await write_ahead(entry, urgent=urgent)

    api.gov._steps.write_ahead = slow_write  # type: ignore[method-assign]
    reply = asyncio.create_task(api.command("planner", wave("inv-x", 0.3)))
    await sent(api, "arm_joint")
    cancelled = asyncio.create_task(api.command("planner", cancel("inv-x")))
    await asyncio.wait_for(auditing.wait(), 10)
    await asyncio.wait({reply}, timeout=1.0)  # past the trajectory's 0.3 s
    release.set()
    for task in (reply, cancelled):
        status, body = await asyncio.wait_for(task, 10)
        assert (status, body["status"]) == (200, "cancelled"), body
    assert api.dispatcher.holds == [["inv-x"]]


@pytest.mark.parametrize("id_field", ["msg_id", "message_id"])
async def test_a_replayed_versioned_invoke_is_refused_whichever_field_names_it(
        api: Api, id_field: str) -> None:
    """Red team 16: §8.3's replay window holds for an INVOKE named by the envelope's
    `message_id` as by §19's `msg_id` (INVOKE_CANCEL and AUTHORIZE took both). Before, an
    INVOKE's `message_id` was ignored as an unknown envelope field: each copy got an id of its
    own, and a replay ran the skill again."""
    body = invoke("nudge", "unused", params={"duration_s": 1.0}, rcan_version="3.2",
                  timestamp_ms=int(api.clock.time() * 1000))
    del body["msg_id"]
    body[id_field] = "inv-replayed"
    status, first = await api.command("planner", body)
    assert (status, first["status"], first["reply_to"]) == (200, "success",
                                                           "inv-replayed"), first
    api.clock.advance(1)
    status, again = await api.command("planner", body)
    assert (status, again["error_code"]) == (409, "REPLAY_DETECTED"), again
    assert [a for a, _ in api.dispatcher.calls] == ["move"]


async def test_an_invoke_a_higher_move_holds_the_base_from_is_a_skill_conflict(
        move_api: Api) -> None:
    """§19.3's 7005 SkillConflict: the arbiter refuses the skill's move because a higher
    principal's stream holds the base; told apart from any other refusal (7006)."""
    api = move_api
    status, held = await api.command("ops", {"action": "move", "params": {"linear_x": 0.1}})
    assert (status, held["outcome"]) == (200, "executed"), held
    status, body = await api.command("planner", nudge("inv-x", 0.5))
    assert (status, body["status"], body["error"]["code"], body["error"]["name"]) == (
        409, "failure", 7005, "SkillConflict"), body
    [result] = results(api, "inv-x")
    assert result["params"]["error"] == {"code": 7005, "name": "SkillConflict"}, result
    active = api.gov.streams.active  # ops's move drives on
    assert active is not None and active.owner == "ops"


async def test_a_cancel_naming_another_principal_as_its_sender_is_refused(api: Api) -> None:
    """rcan-spec's INVOKE_CANCEL `principal_id` must be the authenticated principal: a cancel
    that claims to be someone else's cancels nothing (403, audited)."""
    status, body = await api.command("planner", invoke("raise_elbow", "inv-who"))
    assert (status, body["status"]) == (202, "pending"), body
    flat = {**json.loads((DATA / "invoke-cancel.json").read_text())["examples"][0],
            "message_type": 13, "ruri": TARGET, "principal_id": "ops",
            "cancel_msg_id": "inv-who"}
    status, body = await api.command("planner", flat)
    assert (status, body["reason"]) == (403, "principal_id_not_yours"), body
    assert api.entry(body["audit_id"])["event"] == "COMMAND_REJECTED"
    assert len(api.gov.pending()) == 1  # still held for its reviewer


async def test_an_invoke_sent_again_is_answered_from_its_first_decision(move_api: Api) -> None:
    """An unversioned INVOKE retried with its msg_id (no replay window: the idempotent retry)
    runs its skill once; the retry's answer is the first one, and is audited again."""
    api = move_api
    first = await api.command("planner", nudge("inv-r", 0.2))
    assert (first[0], first[1]["status"]) == (200, "success"), first
    again = await api.command("planner", nudge("inv-r", 0.2))
    assert (again[0], again[1]["status"], again[1]["audit_id"]) == (
        200, "success", first[1]["audit_id"]), again
    assert [a for a, _ in api.dispatcher.calls] == ["move"]  # run once
    assert [e["status"] for e in results(api, "inv-r")] == ["success", "success"]


async def test_a_cancel_whose_goal_does_not_wind_down_in_time_is_answered_cancelling(
        api: Api) -> None:
    """§19.4 `cancel_timeout_ms`: the cancel is answered 202 `cancelling` when the goal has not
    ended in time; the INVOKE's own answer follows once it does."""
    reply = asyncio.create_task(api.command("planner", invoke("go_home", "inv-slow")))
    await sent(api, "navigate")
    slow = cancel("inv-slow")
    slow["payload"]["cancel_timeout_ms"] = 50  # the goal below never ends on its own
    status, body = await api.command("planner", slow)
    assert (status, body["status"], body["reason"], body["reply_to"]) == (
        202, "cancelled", "cancelling", "inv-slow"), body
    assert api.dispatcher.cancelled == ["goal-1"] and not reply.done()
    api.robot.goal_changed(ended("goal-1", "canceled"))
    status, body = await asyncio.wait_for(reply, 10)
    assert (status, body["status"], body["error"]["code"]) == (200, "cancelled", 7007), body
