"""`bridge.ai.agents` end to end (issue 24, item 8): the config binds a principal to its
models, and the API refuses (and audits) what it sends outside them."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from tests.api.apihelpers import Api

MOVE = {"action": "move", "params": {"linear_x": 0.1, "duration_s": 0.5}}


@pytest.fixture
async def bound(tmp_path: Path) -> AsyncIterator[Api]:
    api = await Api(tmp_path, bridge_extra="ai: {agents: {planner: [planner-7b]}}").start()
    yield api
    await api.close()


@pytest.mark.parametrize(("extra", "http", "code", "reason"), [
    ({}, 400, "AUDIT_INCOMPLETE_AI_IDENTITY", "ai_model_required"),  # an agent names its model
    ({"ai_model": "gpt-4o", "confidence": 0.9}, 403, "INSUFFICIENT_PRIVILEGES",
     "ai_model_not_allowed"),
])
async def test_an_agent_outside_its_models_is_refused_and_audited(
        bound: Api, extra: dict[str, object], http: int, code: str, reason: str) -> None:
    status, body = await bound.command("planner", MOVE | extra)
    assert (status, body["error_code"], body["reason"]) == (http, code, reason), body
    entry = bound.entry(body["audit_id"])
    assert (entry["event"], entry["principal"], entry["deny_reason"]) == (
        "COMMAND_REJECTED", "planner", f"{code}:{reason}")
    assert bound.dispatcher.calls == []


async def test_an_agent_with_its_model_and_others_unbound(bound: Api) -> None:
    status, body = await bound.command("planner", MOVE | {"ai_model": "planner-7b",
                                                          "confidence": 0.9})
    assert (status, body["outcome"]) == (200, "executed"), body
    assert bound.entry(body["audit_id"])["ai"]["model"] == "planner-7b"
    status, body = await bound.command("ops", MOVE)  # not an agent: a human's command
    assert status == 200, body
    status, body = await bound.command("planner", {"action": "stop"})  # a stop still stops
    assert status == 200 and "ai_model_required" in body["warnings"][-1], body
