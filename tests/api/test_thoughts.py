"""RCAN §16.5, the Thought log: GET /api/thoughts/{thought_id} says what an AI's thought led
to; its reasoning is kept out of the audit (its digest is in) and shown to OWNER+ only."""

from __future__ import annotations

import hashlib
import json
import uuid

from tests.api.apihelpers import Api

REASONING = "The doorway is clear; move toward it slowly."


def _ai_move(thought: str, **extra: object) -> dict[str, object]:
    return {"action": "move", "params": {"linear_x": 0.1, "duration_s": 0.5},
            "message_id": str(uuid.uuid4()), "ai_provider": "anthropic",
            "ai_model": "claude-sonnet-4-6", "confidence": 0.87, "thought_id": thought,
            **extra}


async def test_a_thought_shows_its_model_confidence_and_commands(api: Api) -> None:
    sent = _ai_move("th-1", ai_reasoning=REASONING)
    status, decided = await api.command("planner", sent)
    assert (status, decided["outcome"]) == (200, "executed"), decided
    status, thought = await api.call("GET", "/api/thoughts/th-1", "viewer")
    assert status == 200, thought
    assert (thought["id"], thought["provider"], thought["model"], thought["confidence"]) == (
        "th-1", "anthropic", "claude-sonnet-4-6", 0.87)
    assert thought["action"]["type"] == "move"
    assert thought["action"]["message_id"] == sent["message_id"]
    assert thought["action"]["audit_id"] == decided["audit_id"]
    assert thought["action"]["outcome"] == "executed"


async def test_reasoning_needs_the_config_scope_and_stays_out_of_the_audit(api: Api) -> None:
    await api.command("planner", _ai_move("th-2", ai_reasoning=REASONING))
    digest = hashlib.sha256(REASONING.encode()).hexdigest()
    for reader in ("viewer", "planner", "lessee"):  # operational access, no config scope
        status, thought = await api.call("GET", "/api/thoughts/th-2", reader)
        assert status == 200 and "reasoning" not in thought, (reader, thought)
        assert thought["reasoning_sha256"] == digest  # that there was one is no secret
    for reader in ("ops", "root"):
        status, thought = await api.call("GET", "/api/thoughts/th-2", reader)
        assert thought["reasoning"] == REASONING, (reader, thought)
    log = (api.tmp / "audit.jsonl").read_text()
    assert REASONING not in log  # the audit, readable by LEASEE, holds the digest only
    [entry] = [json.loads(line) for line in log.splitlines() if "th-2" in line]
    assert entry["ai"]["reasoning_sha256"] == digest and "reasoning" not in entry["ai"]


async def test_every_command_of_a_thought_refused_or_not(api: Api) -> None:
    await api.command("planner", _ai_move("th-3"))
    too_fast = {**_ai_move("th-3"), "params": {"linear_x": 99.0, "duration_s": 0.5}}
    await api.command("planner", too_fast)
    status, thought = await api.call("GET", "/api/thoughts/th-3", "planner")
    assert [c["outcome"] for c in thought["commands"]] == ["executed", "safety_violation"]
    assert thought["action"]["outcome"] == "safety_violation"  # the latest
    assert thought["action"]["reason"] == "velocity_limit"


async def test_an_unknown_thought_is_a_404_and_the_route_needs_credentials(api: Api) -> None:
    status, body = await api.call("GET", "/api/thoughts/never", "viewer")
    assert (status, body["reason"]) == (404, "thought_not_found")
    status, _ = await api.call("GET", "/api/thoughts/never", None)
    assert status == 401
