"""The app's skeleton: authentication on every route, commands, status, heartbeat, goals."""

from __future__ import annotations

import subprocess
import sys
import uuid

import pytest

import rcan_rtps.api as api_pkg
from rcan_rtps.api import GoalView
from tests.api.apihelpers import RURI, TOKENS, Api

ROUTES = [("POST", "/api/command"), ("POST", "/api/command/cancel"),
          ("GET", "/api/status"), ("POST", "/api/heartbeat"),
          ("GET", "/api/skills"),
          ("GET", "/api/goals"), ("GET", "/api/goals/g1"), ("GET", "/api/thoughts/t1"),
          ("GET", "/api/hitl/pending"), ("GET", "/api/hitl/pending/p1"),
          ("POST", "/api/hitl/authorize"), ("POST", "/api/hitl/deny"),
          ("POST", "/api/hitl/withdraw"), ("GET", "/api/audit"),
          ("GET", "/api/audit/verify"), ("GET", "/api/audit/mine"),
          ("GET", "/api/openapi.json"), ("GET", "/api/ws"),
          ("GET", "/api/metrics"), ("GET", "/api/safety/manifest"), ("GET", "/api/v1/audit"),
          ("POST", "/mcp"), ("GET", "/mcp"), ("DELETE", "/mcp"),
          ("GET", "/api/images"), ("GET", "/api/images/front"),
          ("GET", "/api/whoami"), ("POST", "/api/ws-ticket")]
PUBLIC = [("GET", "/.well-known/rcan-node.json"),  # §17.3: no authentication
          # the operator console's static files (tests/console)
          ("GET", "/"), ("GET", "/console"), ("GET", "/console/"), ("GET", "/console/{name}")]


def test_public_api_is_sorted_and_complete() -> None:
    assert api_pkg.__all__ == sorted(api_pkg.__all__)
    for name in api_pkg.__all__:
        assert getattr(api_pkg, name) is not None


def test_every_route_is_in_the_test_list(api: Api) -> None:
    assert api.app is not None
    served = {(r.method, r.resource.canonical) for r in api.app.router.routes()
              if r.resource is not None}
    assert served == {(m, p.replace("g1", "{goal_id}").replace("t1", "{thought_id}")
                       .replace("p1", "{pending_id}").replace("front", "{name}"))
                      for m, p in ROUTES + PUBLIC}


@pytest.mark.parametrize("headers", [
    {}, {"Authorization": "Bearer not-a-token-of-anyone-at-all"}, {"Authorization": "Bearer "},
], ids=["missing", "invalid", "empty"])
async def test_the_node_manifest_needs_no_credential(api: Api, headers: dict[str, str]
                                                     ) -> None:
    before = len(api.entries)
    status, body = await api.call("GET", "/.well-known/rcan-node.json", headers=headers)
    assert status == 200 and body["ruri"] == RURI, body
    assert len(api.entries) == before
    # only GET: anything else on that path is no public way in
    status, body = await api.call("POST", "/.well-known/rcan-node.json", headers=headers,
                                  body={"action": "move"})
    assert status == 401, body


@pytest.mark.parametrize(("method", "path"), ROUTES)
@pytest.mark.parametrize("headers", [
    {}, {"Authorization": "Bearer not-a-token-of-anyone-at-all"},
    {"Authorization": f"Basic {TOKENS['ops']}"}, {"Authorization": "Bearer "},
], ids=["missing", "invalid", "wrong-scheme", "empty"])
async def test_every_route_needs_credentials(api: Api, method: str, path: str,
                                             headers: dict[str, str]) -> None:
    before = len(api.entries)
    status, body = await api.call(method, path, headers=headers,
                                  body={"action": "estop"} if method == "POST" else None)
    assert (status, body["outcome"], body["error_code"]) == (401, "denied", "UNAUTHENTICATED")
    assert "audit_id" not in body
    assert len(api.entries) == before  # unauthenticated requests are not audited
    assert api.dispatcher.calls == []


async def test_unauthenticated_response_challenges(api: Api) -> None:
    async with api.http.get("/api/status") as resp:
        assert resp.status == 401
        assert resp.headers["WWW-Authenticate"].startswith("Bearer")


async def test_two_authorization_headers_are_refused(api: Api) -> None:
    headers = [("Authorization", f"Bearer {TOKENS['viewer']}"),
               ("Authorization", f"Bearer {TOKENS['ops']}")]
    async with api.http.get("/api/status", headers=headers) as resp:
        assert resp.status == 401


async def test_move_is_executed_and_audited(api: Api) -> None:
    mid = str(uuid.uuid4())
    status, body = await api.command("planner", {"action": "move", "message_id": mid,
                                                 "params": {"linear_x": 0.5, "angular_z": 0.1}})
    assert status == 200
    assert body["outcome"] == "executed"
    assert body["message_id"] == mid
    velocity = {"linear_x": 0.5, "linear_y": 0.0, "angular_z": 0.1}
    assert body["applied"] == {**velocity, "duration_s": None,  # held, no ramp configured
                               "ramp_from": [0.0, 0.0, 0.0], "ramp_s": 0.0}
    assert api.dispatcher.calls == [("move", {**velocity, "duration_s": None})]
    entry = api.entry(body["audit_id"])
    assert (entry["event"], entry["principal"], entry["role"]) == (
        "COMMAND_DISPATCHED", "planner", "USER")
    assert entry["params"] == {"linear_x": 0.5, "angular_z": 0.1}


async def test_clamped_within_ten_percent_and_denied_beyond(api: Api) -> None:
    status, body = await api.command("planner", {"action": "move",
                                                 "params": {"linear_x": 1.05}})
    assert (status, body["applied"]["linear_x"]) == (200, 1.0)
    status, body = await api.command("planner", {"action": "move",
                                                 "params": {"linear_x": 1.2}})
    assert (status, body["outcome"], body["reason"]) == (409, "safety_violation",
                                                         "velocity_limit")
    assert api.entry(body["audit_id"])["outcome"] == "safety_violation"
    assert len(api.dispatcher.calls) == 1


async def test_guest_move_is_forbidden_and_nothing_dispatched(api: Api) -> None:
    status, body = await api.command("viewer", {"action": "move", "params": {"linear_x": 0.1}})
    assert (status, body["error_code"]) == (403, "INSUFFICIENT_PRIVILEGES")
    # What was needed, said (before: the bare code, while the GET routes said the role).
    assert body["reason"] == "move needs USER or higher", body
    assert api.entry(body["audit_id"])["deny_reason"] == (
        "INSUFFICIENT_PRIVILEGES:move needs USER or higher")
    assert api.dispatcher.calls == []


@pytest.mark.parametrize("claim", [{"role": "OWNER"}, {"role_level": 5}, {"role": "GOD"},
                                   {"role_level": "x"}])
async def test_claimed_higher_role_is_refused_and_audited(api: Api,
                                                          claim: dict[str, object]) -> None:
    status, body = await api.command("planner", {"action": "move", **claim})
    assert (status, body["error_code"]) == (403, "INSUFFICIENT_PRIVILEGES")
    assert body["reason"] == "the message claims a role above USER, the credential's", body
    entry = api.entry(body["audit_id"])
    assert (entry["principal"], entry["role"], entry["outcome"]) == ("planner", "USER",
                                                                     "denied")
    assert api.dispatcher.calls == []


async def test_envelope_form_for_another_robot_is_refused(api: Api) -> None:
    other = "rcan://registry.local/clearpath/husky/zz99-9999"
    move = {"message_type": 1, "action": "move", "parameters": {"linear_x": 0.1}}
    status, body = await api.command("planner", {**move, "ruri": other})
    assert (status, body["error_code"], body["reason"]) == (400, "INVALID_RURI",
                                                            "not_this_robot")
    status, body = await api.command("planner", {**move, "ruri": "http://x"})
    assert (status, body["error_code"]) == (400, "INVALID_RURI")
    assert api.entry(body["audit_id"])["deny_reason"].startswith("INVALID_RURI")
    status, body = await api.command("planner", {**move, "ruri": RURI})
    assert status == 200
    # A stop is the exception: it stops, and says what was wrong.
    status, body = await api.command("planner", {"message_type": 1, "ruri": other,
                                                 "action": "stop"})
    assert (status, body["warnings"]) == (200, [f"addressed to {other}, not this robot "
                                                f"({RURI})"])


async def test_rate_limit_is_429(api: Api) -> None:
    codes = [(await api.command("slow", {"action": "move"}))[0] for _ in range(101)]
    assert codes[:100] == [200] * 100
    assert codes[100] == 429
    # stop and estop form the e-stop lane: never rate-limited
    assert (await api.command("slow", {"action": "stop"}))[0] == 200
    assert (await api.command("slow", {"action": "estop"}))[0] == 200


async def test_robot_unavailable_is_503(api: Api) -> None:
    api.dispatcher.available = False
    status, body = await api.command("planner", {"action": "move"})
    assert (status, body["outcome"], body["error_code"]) == (503, "failed", "ROBOT_UNAVAILABLE")


async def test_status_for_any_principal(api: Api) -> None:
    api.robot.x = 3.25
    status, body = await api.call("GET", "/api/status", "viewer")
    assert status == 200
    assert body["ruri"] == RURI
    assert body["telemetry"]["position"]["x"] == 3.25
    assert body["pending_auth"] == 0


async def test_status_counts_pending_approvals(api: Api) -> None:
    await api.command("planner", {"action": "arm_joint", "params": {
        "joints": ["j1"], "positions": [0.1], "duration_s": 1.0}})
    assert (await api.call("GET", "/api/status", "viewer"))[1]["pending_auth"] == 1


async def test_heartbeat(api: Api) -> None:
    status, body = await api.call("POST", "/api/heartbeat", "planner")
    assert (status, body["ok"], body["principal"]) == (200, True, "planner")


async def test_goals(api: Api) -> None:
    goal = GoalView(goal_id="g1", action="navigate", state="executing",
                    feedback={"distance_remaining": 2.0}, created_ms=1, updated_ms=2)
    api.robot.goal_views["g1"] = goal
    status, body = await api.call("GET", "/api/goals/g1", "viewer")
    assert (status, body["state"], body["feedback"]) == (200, "executing",
                                                          {"distance_remaining": 2.0})
    status, body = await api.call("GET", "/api/goals/nope", "viewer")
    assert (status, body["error_code"]) == (404, "NOT_FOUND")
    status, body = await api.call("GET", "/api/goals", "viewer")
    assert [g["goal_id"] for g in body["goals"]] == ["g1"]


async def test_unknown_route_and_method_are_json(api: Api) -> None:
    status, body = await api.call("GET", "/api/nothing", "viewer")
    assert (status, body["error_code"]) == (404, "NOT_FOUND")
    status, body = await api.call("DELETE", "/api/status", "viewer")
    assert (status, body["error_code"]) == (405, "METHOD_NOT_ALLOWED")


async def test_estop_from_guest_latches_and_blocks_motion(api: Api) -> None:
    status, body = await api.command("viewer", {"action": "estop"})
    assert (status, body["outcome"]) == (200, "executed")
    status, body = await api.command("planner", {"action": "move"})
    assert (status, body["reason"]) == (409, "estop_active")
    status, body = await api.command("ops", {"action": "clear_estop"})
    assert status == 200
    assert (await api.command("planner", {"action": "move"}))[0] == 200


@pytest.mark.logs_traceback  # (a fault injected on purpose)
async def test_broken_robot_view_is_503_not_500(api: Api) -> None:
    def broken(*, pending_auth: int) -> object:
        raise RuntimeError("bridge bug")

    api.robot.status = broken  # type: ignore[assignment, method-assign]
    status, body = await api.call("GET", "/api/status", "viewer")
    assert (status, body["outcome"], body["reason"]) == (503, "failed", "internal_error")



def test_the_api_imports_no_dds() -> None:
    code = ("import sys, rcan_rtps.api; "
            "bad = sorted(m for m in sys.modules if m.split('.')[0] == 'cyclonedds' "
            "or m.startswith(('rcan_rtps.ros', 'rcan_rtps.bridge'))); print(bad)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=60)
    assert out.stdout.strip() == "[]"
