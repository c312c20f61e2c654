"""Issue 25: GET /api/hitl/pending/{pending_id} — the issuer of a held command (an agent that
waits for a human) and its approvers read it while it waits and learn what came of it; nobody
else sees it (404, as an unknown one)."""

from __future__ import annotations

from typing import Any

from tests.api.apihelpers import Api
from tests.api.test_hitl_reviews import hold, review


async def view(api: Api, who: str, pending_id: str) -> tuple[int, Any]:
    return await api.call("GET", f"/api/hitl/pending/{pending_id}", who)


async def test_the_issuer_reads_its_held_command_then_its_execution(api: Api) -> None:
    pending_id = await hold(api, "planner")
    status, body = await view(api, "planner", pending_id)
    assert (status, body["state"], body["pending_id"]) == (200, "pending", pending_id), body
    assert body["pending"]["original_command"]["action"] == "arm_joint"
    assert body["pending"]["issued_by"] == "planner"
    assert "decision" not in body
    status, done = await review(api, "authorize", "ops", pending_id)
    assert (status, done["outcome"]) == (200, "executed"), done
    status, body = await view(api, "planner", pending_id)
    assert (status, body["state"]) == (200, "resolved"), body
    assert body["decision"]["outcome"] == "executed"
    assert body["decision"]["audit_id"] == done["audit_id"]
    assert body["pending"]["original_command"]["params"]["positions"] == [0.5]  # what ran


async def test_approvers_read_it_strangers_do_not(api: Api) -> None:
    pending_id = await hold(api, "planner")
    assert (await view(api, "ops", pending_id))[0] == 200  # OWNER: the gate's approver
    assert (await view(api, "root", pending_id))[0] == 200
    for stranger in ("slow", "viewer", "lessee"):  # another USER, a GUEST, a LEASEE
        status, body = await view(api, stranger, pending_id)
        assert (status, body["reason"]) == (404, "pending_not_found"), stranger
    status, _ = await review(api, "deny", "ops", pending_id, "not now")
    assert status == 200
    status, body = await view(api, "slow", pending_id)  # resolved: still not theirs
    assert status == 404
    status, body = await view(api, "planner", pending_id)
    assert (body["state"], body["decision"]["outcome"], body["decision"]["reason"]) == (
        "resolved", "denied", "hitl_denied"), body


async def test_a_withdrawn_and_an_expired_command_read_as_such(api: Api) -> None:
    withdrawn, expiring = await hold(api, "planner"), await hold(api, "planner")
    assert (await review(api, "withdraw", "planner", withdrawn))[0] == 200
    body = (await view(api, "planner", withdrawn))[1]
    assert (body["decision"]["outcome"], body["decision"]["reason"]) == (
        "denied", "hitl_withdrawn"), body
    api.clock.advance(301)  # past hitl.timeout_seconds: the read itself expires it
    status, body = await view(api, "planner", expiring)
    assert (status, body["state"], body["decision"]["reason"]) == (
        200, "resolved", "pending_expired"), body
    assert [e["pending_id"] for e in api.entries if e["event"] == "HITL_EXPIRED"] == [expiring]


async def test_unknown_and_unauthenticated(api: Api) -> None:
    status, body = await view(api, "ops", "0" * 32)
    assert (status, body["reason"]) == (404, "pending_not_found")
    pending_id = await hold(api, "planner")
    status, _ = await api.call("GET", f"/api/hitl/pending/{pending_id}")
    assert status == 401


async def test_openapi_lists_it(api: Api) -> None:
    _, document = await api.call("GET", "/api/openapi.json", "viewer")
    operation = document["paths"]["/api/hitl/pending/{pending_id}"]["get"]
    assert operation["responses"]["200"]["content"]["application/json"]["schema"] == {
        "$ref": "#/components/schemas/PendingView"}
    assert "PendingView" in document["components"]["schemas"]
