"""Issue 25: an AI command may name the client that relayed the model's call (`ai_client`,
`ai.client`): the audit entry's `ai` block records it, and only when given (older entries'
bytes stay as they were)."""

from __future__ import annotations

from tests.api.apihelpers import Api

MOVE = {"action": "move", "params": {"linear_x": 0.1, "duration_s": 0.5}, "confidence": 0.9}


async def test_the_short_forms_ai_client_is_audited(api: Api) -> None:
    status, body = await api.command("planner", {
        **MOVE, "ai_provider": "acme", "ai_model": "planner-7b",
        "ai_client": "claude-desktop/1.2.3", "thought_id": "t-1"})
    assert (status, body["outcome"]) == (200, "executed"), body
    ai = api.entry(body["audit_id"])["ai"]
    assert (ai["client"], ai["model"], ai["thought_id"]) == (
        "claude-desktop/1.2.3", "planner-7b", "t-1")
    status, body = await api.command("planner", {**MOVE, "ai_model": "planner-7b"})
    assert status == 200, body
    assert "client" not in api.entry(body["audit_id"])["ai"]  # none given: no field at all


async def test_the_envelopes_ai_client_is_audited(api: Api) -> None:
    status, body = await api.command("planner", {
        "message_type": 1, "ruri": "rcan://registry.local/clearpath/husky/a200-0001",
        "action": "move", "parameters": {"linear_x": 0.1, "duration_s": 0.5},
        "ai": {"model": "planner-7b", "confidence": 0.9, "client": "an-ide/0.1"}})
    assert (status, body["outcome"]) == (200, "executed"), body
    assert api.entry(body["audit_id"])["ai"]["client"] == "an-ide/0.1"


async def test_an_overlong_client_is_a_schema_error(api: Api) -> None:
    status, body = await api.command("planner", {**MOVE, "ai_model": "m",
                                                 "ai_client": "x" * 257})
    assert (status, body["error_code"], body["path"]) == (
        400, "SCHEMA_VALIDATION_FAILED", "$.ai_client"), body
