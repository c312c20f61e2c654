"""HiTL through HTTP with a real webhook receiver; the audit endpoints; AI identity in the
audit; the OpenAPI document."""

from __future__ import annotations

import json
import uuid
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from waiting import eventually

from rcan_rtps.governance import WebhookNotifier, verify
from tests.api.apihelpers import RURI, Api, webhook_receiver

ARM = {"action": "arm_joint", "params": {"joints": ["shoulder", "elbow"],
                                         "positions": [0.5, -0.25], "duration_s": 2.0},
       "ai_provider": "anthropic", "ai_model": "claude", "confidence": 0.9,
       "thought_id": "t-1"}


class Hitl:
    def __init__(self, api: Api, received: list[dict[str, Any]]) -> None:
        self.api = api
        self.received = received

    async def webhook_message(self, pending_id: str) -> dict[str, Any]:
        def arrived() -> dict[str, Any] | None:
            return next((m for m in self.received if m["pending_id"] == pending_id), None)

        message: dict[str, Any] = await eventually(
            arrived, timeout=30, what=f"the webhook message for {pending_id}")
        return message

    async def hold(self) -> str:
        status, body = await self.api.command("planner", ARM)
        assert (status, body["outcome"]) == (202, "pending_auth")
        assert self.api.entry(body["audit_id"])["event"] == "PENDING_AUTH"
        return str(body["pending_id"])


@pytest.fixture
async def hitl(tmp_path: Path) -> AsyncIterator[Hitl]:
    runner, url, received = await webhook_receiver()
    api = await Api(tmp_path, notifier=WebhookNotifier(url, attempts=1)).start()
    yield Hitl(api, received)
    await api.close()
    await runner.cleanup()


async def test_webhook_gets_pending_auth_and_approval_dispatches(hitl: Hitl) -> None:
    api = hitl.api
    pending_id = await hitl.hold()
    message = await hitl.webhook_message(pending_id)
    assert message["message_type"] == "PENDING_AUTH"
    assert message["original_command"]["action"] == "arm_joint"
    assert (message["confidence"], message["ai_model"]) == (0.9, "claude")
    assert message["requires_auth_from_role"] == "OWNER"
    assert message["expires_at_ms"] > 0
    assert api.dispatcher.calls == []

    status, listing = await api.call("GET", "/api/hitl/pending", "ops")
    assert [p["pending_id"] for p in listing["pending"]] == [pending_id]
    assert (await api.call("GET", "/api/hitl/pending", "planner"))[0] == 403

    # The issuer cannot approve (role too low): refused and audited, still pending.
    status, body = await api.call("POST", "/api/hitl/authorize", "planner",
                                  body={"pending_id": pending_id})
    assert (status, body["error_code"]) == (403, "INSUFFICIENT_PRIVILEGES")
    assert api.entry(body["audit_id"])["principal"] == "planner"

    status, body = await api.call("POST", "/api/hitl/authorize", "ops",
                                  body={"pending_id": pending_id})
    assert (status, body["outcome"]) == (200, "executed")
    assert api.dispatcher.calls == [("arm_joint", {"joints": ["shoulder", "elbow"],
                                                   "positions": [0.5, -0.25],
                                                   "duration_s": 2.0})]
    entry = api.entry(body["audit_id"])
    assert (entry["event"], entry["principal"], entry["pending_id"]) == (
        "HITL_AUTHORIZED", "ops", pending_id)
    assert entry["ai"] == {"provider": "anthropic", "model": "claude", "confidence": 0.9,
                           "thought_id": "t-1"}
    # One approval executes once.
    status, body = await api.call("POST", "/api/hitl/authorize", "ops",
                                  body={"pending_id": pending_id})
    assert status == 404
    assert len(api.dispatcher.calls) == 1


async def test_deny_discards(hitl: Hitl) -> None:
    api = hitl.api
    pending_id = await hitl.hold()
    await hitl.webhook_message(pending_id)
    status, body = await api.call("POST", "/api/hitl/deny", "ops",
                                  body={"pending_id": pending_id})
    assert (status, body["outcome"], body["reason"]) == (200, "denied", "hitl_denied")
    assert api.entry(body["audit_id"])["event"] == "HITL_DENIED"
    assert (await api.call("GET", "/api/hitl/pending", "ops"))[1]["pending"] == []
    assert api.dispatcher.calls == []


async def test_timeout_discards_and_is_audited(hitl: Hitl) -> None:
    api = hitl.api
    pending_id = await hitl.hold()
    await hitl.webhook_message(pending_id)
    api.clock.advance(301)  # past hitl.timeout_seconds
    status, body = await api.call("POST", "/api/hitl/authorize", "ops",
                                  body={"pending_id": pending_id})
    assert (status, body["reason"]) == (404, "pending_expired")
    expired = [e for e in api.entries if e["event"] == "HITL_EXPIRED"]
    assert [e["pending_id"] for e in expired] == [pending_id]
    assert (await api.call("GET", "/api/hitl/pending", "ops"))[1]["pending"] == []
    assert api.dispatcher.calls == []


async def test_listing_pending_expires_what_timed_out(hitl: Hitl) -> None:
    api = hitl.api
    pending_id = await hitl.hold()
    api.clock.advance(301)
    assert (await api.call("GET", "/api/hitl/pending", "ops"))[1]["pending"] == []
    assert [e["pending_id"] for e in api.entries if e["event"] == "HITL_EXPIRED"] == [
        pending_id]


async def test_approval_rechecks_invariants_now(hitl: Hitl) -> None:
    api = hitl.api
    # The e-stop withdraws held motion itself (test_held_motion_withdrawn.py): taken out
    # here, as a fault would, the approval's recheck is what refuses it (the backstop).
    api.gov._desk.withdrawing = lambda issuer, which: []  # type: ignore[method-assign]
    low = {"action": "move", "params": {"linear_x": 0.2}, "ai_model": "m", "confidence": 0.1}
    status, body = await api.command("planner", low)  # confidence gate escalates
    assert status == 202
    pending_id = body["pending_id"]
    assert (await api.command("viewer", {"action": "estop"}))[0] == 200
    status, body = await api.call("POST", "/api/hitl/authorize", "ops",
                                  body={"pending_id": pending_id})
    assert (status, body["reason"]) == (409, "estop_active")
    assert [a for a, _ in api.dispatcher.calls] == ["estop"]


# -- audit ----------------------------------------------------------------------------------


async def test_every_command_is_audited_with_ai_identity(api: Api) -> None:
    ai = {"ai_provider": "openai", "ai_model": "gpt-4o", "confidence": 0.94,
          "thought_id": "chatcmpl-abc123"}
    sent = [
        ("planner", {"action": "move", "params": {"linear_x": 0.5}, **ai}, 200),
        ("planner", {"action": "move", "params": {"linear_x": 9.0}, **ai}, 409),
        ("viewer", {"action": "move", **ai}, 403),
        ("planner", {"action": "arm_joint", "params": {"joints": ["j"], "positions": [0.0],
                                                       "duration_s": 1}, **ai}, 202),
        ("planner", {"message_type": 1, "ruri": RURI, "action": "move",
                     "message_id": str(uuid.uuid4()), "timestamp_ms": 1,
                     "parameters": {"angular_z": 0.1},
                     "ai": {"provider": "openai", "model": "gpt-4o", "confidence": 0.94,
                            "thought_id": "chatcmpl-abc123"}}, 200),
    ]
    for who, body, expected in sent:
        status, answer = await api.command(who, body)
        assert status == expected, answer
        entry = api.entry(answer["audit_id"])
        assert entry["ai"] == {"provider": "openai", "model": "gpt-4o", "confidence": 0.94,
                               "thought_id": "chatcmpl-abc123"}
        assert (entry["ruri"], entry["bridge"], entry["principal"]) == (RURI, "ros2", who)
        assert entry["action_type"] in ("move", "arm_joint")
    status, answer = await api.command("planner", {"action": "stop"})
    assert "ai" not in api.entry(answer["audit_id"])  # only when given


async def test_audit_endpoint_pages_entries_verbatim(api: Api) -> None:
    for _ in range(5):
        await api.command("planner", {"action": "stop"})
    assert (await api.call("GET", "/api/audit", "planner"))[0] == 403
    status, page = await api.call("GET", "/api/audit?since=0&limit=2", "lessee")
    assert status == 200
    assert [e["seq"] for e in page["entries"]] == [1, 2]
    assert page["next_since"] == 2
    status, rest = await api.call("GET", f"/api/audit?since={page['next_since']}", "lessee")
    on_disk = (api.tmp / "audit.jsonl").read_text().splitlines()
    got = page["entries"] + rest["entries"]
    assert [json.loads(line) for line in on_disk] == got
    assert rest["head_seq"] == len(on_disk) == rest["next_since"]
    status, empty = await api.call("GET", f"/api/audit?since={len(on_disk)}", "lessee")
    assert (empty["entries"], empty["next_since"]) == ([], len(on_disk))


async def test_audit_verify_endpoint(api: Api) -> None:
    for _ in range(3):
        await api.command("planner", {"action": "stop"})
    assert (await api.call("GET", "/api/audit/verify", "viewer"))[0] == 403
    status, report = await api.call("GET", "/api/audit/verify", "lessee")
    assert (status, report["ok"], report["count"]) == (200, True, 3)
    assert report["last_audit_id"] == verify(api.tmp / "audit.jsonl").last_audit_id
    # Tamper with entry 2 (same length, so the file stays line-aligned).
    path = api.tmp / "audit.jsonl"
    lines = path.read_bytes().split(b"\n")
    lines[1] = lines[1].replace(b'"outcome":"executed"', b'"outcome":"exeCuted"')
    path.write_bytes(b"\n".join(lines))
    status, report = await api.call("GET", "/api/audit/verify", "lessee")
    assert (status, report["ok"], report["bad_seq"]) == (200, False, 2)


async def test_audit_verify_endpoint_checks_the_tree_heads_too(api: Api) -> None:
    """A log cut back to an earlier, internally valid prefix passes the chain check alone:
    the signed tree heads beside it still name the entries it lost."""
    for _ in range(3):
        await api.command("planner", {"action": "stop"})
    status, report = await api.call("GET", "/api/audit/verify", "lessee")
    assert (status, report["ok"]) == (200, True)
    assert report["tree_heads"] >= 1 and report["tree_size"] == report["count"] == 3
    path = api.tmp / "audit.jsonl"
    lines = path.read_bytes().splitlines(keepends=True)
    path.write_bytes(b"".join(lines[:2]))  # the last entry gone, cut at a line end
    assert verify(path).count == 2  # the chain alone sees nothing wrong
    status, report = await api.call("GET", "/api/audit/verify", "lessee")
    assert (status, report["ok"], report["count"]) == (200, False, 2)
    assert any("tree head" in p for p in report["problems"]), report


async def test_audit_read_role_comes_from_config(tmp_path: Path) -> None:
    api = await Api(tmp_path, bridge_extra="rbac: {audit_read_role: OWNER}").start()
    try:
        assert (await api.call("GET", "/api/audit", "lessee"))[0] == 403
        assert (await api.call("GET", "/api/audit/verify", "lessee"))[0] == 403
        assert (await api.call("GET", "/api/audit/verify", "ops"))[0] == 200
    finally:
        await api.close()


# -- OpenAPI --------------------------------------------------------------------------------


def _refs(node: Any) -> list[str]:
    if isinstance(node, dict):
        found = [node["$ref"]] if isinstance(node.get("$ref"), str) else []
        return found + [r for v in node.values() for r in _refs(v)]
    if isinstance(node, list):
        return [r for v in node for r in _refs(v)]
    return []


async def test_openapi_lists_every_route_and_resolves(api: Api) -> None:
    status, doc = await api.call("GET", "/api/openapi.json", "viewer")
    assert status == 200
    assert doc["openapi"] == "3.1.0"
    assert doc["info"]["title"] and doc["info"]["version"]
    assert api.app is not None
    for route in api.app.router.routes():
        assert route.resource is not None
        operations = doc["paths"][route.resource.canonical]
        assert route.method.lower() in operations, route
    for path, operations in doc["paths"].items():
        for method, op in operations.items():
            assert op["responses"], (path, method)
            # every route needs a credential but the node manifest, which says so
            assert ("401" in op["responses"]) == (op.get("security") != []), (path, method)
    schemas = doc["components"]["schemas"]
    for ref in _refs(doc):
        assert ref.startswith("#/components/schemas/")
        assert ref.rsplit("/", 1)[1] in schemas, ref
    for name in ("ShortCommand", "EnvelopeCommand", "Status", "DecisionBody", "PendingAuth",
                 "Authorize", "GoalView", "ApiError", "MoveParams"):
        assert name in schemas
    assert schemas["MoveParams"]["properties"]["linear_x"]["maximum"] == 1e9


async def test_openapi_passes_a_validator(api: Api) -> None:
    validator = pytest.importorskip("openapi_spec_validator")
    status, doc = await api.call("GET", "/api/openapi.json", "viewer")
    assert status == 200
    validator.validate(doc)
