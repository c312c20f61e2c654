"""An e-stop withdraws a clear_estop held for a human (red team 30).

A clear_estop can be held for a human (a gate on it, or an AI's clear below the confidence
gate). Approved after a later e-stop, it released that e-stop: a clear asked for to end one
e-stop (cleared since by someone else, or still latched and pressed again) ended another that
nobody had asked it to — while a clear under way that an e-stop overtakes is refused
(`EstopMachine.overtaken`). Now every e-stop, a repeat while latched too, withdraws the held
clears in its step (HITL_WITHDRAWN, `withdrawn: an e-stop came while it was held`); a clear
the withdrawal misses (held as the e-stop came) is refused 409 `estop_active` when approved.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from rcan_rtps.governance.governor import ESTOPPED_WHILE_HELD
from tests.api.apihelpers import Api

CLEAR_GATE = "[{action: clear_estop, authorized_roles: [CREATOR]}]"
AI_CLEAR = {"action": "clear_estop", "ai_model": "planner-llm", "confidence": 0.1}


@pytest.fixture
async def gated(tmp_path: Path) -> AsyncIterator[Api]:
    harness = await Api(tmp_path, gates=CLEAR_GATE).start()
    yield harness
    await harness.close()


async def _held(api: Api, body: dict[str, Any]) -> str:
    status, held = await api.command("ops", body)
    assert (status, held["outcome"]) == (202, "pending_auth"), held
    pending_id: str = held["pending_id"]
    return pending_id


async def _approve(api: Api, pending_id: str) -> tuple[int, Any]:
    return await api.call("POST", "/api/hitl/authorize", "root", body={"pending_id": pending_id})


def _clears_sent(api: Api) -> list[str]:
    return [action for action, _ in api.dispatcher.calls if action == "clear_estop"]


async def _withdrawn(api: Api, pending_id: str) -> dict[str, Any]:
    """The HITL_WITHDRAWN entry of `pending_id` (written by a task of its own)."""
    for _ in range(200):
        found = [e for e in api.entries
                 if e["event"] == "HITL_WITHDRAWN" and e["pending_id"] == pending_id]
        if found:
            return found[0]
        await asyncio.sleep(0.01)
    raise AssertionError(f"no HITL_WITHDRAWN of {pending_id}")


async def test_an_estop_pressed_again_withdraws_the_clear_held_for_the_first(
        gated: Api) -> None:
    api = gated
    assert (await api.command("viewer", {"action": "estop"}))[0] == 200
    pending_id = await _held(api, {"action": "clear_estop"})
    status, again = await api.command("viewer", {"action": "estop"})
    assert (status, again["reason"]) == (200, "already_latched"), again
    assert [p.pending_id for p in api.gov.pending()] == []
    entry = await _withdrawn(api, pending_id)
    assert (entry["principal"], entry["approvals"][-1]["reason"]) == ("ops", ESTOPPED_WHILE_HELD)
    status, approved = await _approve(api, pending_id)
    assert (status, approved["reason"]) == (404, "pending_not_found"), approved
    assert api.gov.latch.latched
    assert _clears_sent(api) == []


async def test_a_clear_held_for_an_earlier_estop_does_not_release_a_later_one(
        tmp_path: Path) -> None:
    """An AI's clear, held below the confidence gate; a human clears the e-stop meanwhile;
    someone e-stops again: the held clear was never asked to end that e-stop."""
    api = await Api(tmp_path).start()
    try:
        await api.command("viewer", {"action": "estop"})
        pending_id = await _held(api, AI_CLEAR)
        assert (await api.command("root", {"action": "clear_estop"}))[0] == 200
        assert (await api.command("viewer", {"action": "estop"}))[0] == 200
        await _withdrawn(api, pending_id)
        status, approved = await _approve(api, pending_id)
        assert (status, approved["reason"]) == (404, "pending_not_found"), approved
        assert api.gov.latch.latched
        assert _clears_sent(api) == ["clear_estop"]  # the human's, before the second e-stop
    finally:
        await api.close()


async def test_a_clear_held_before_nothing_was_latched_releases_no_later_estop(
        gated: Api) -> None:
    pending_id = await _held(gated, {"action": "clear_estop"})
    await gated.command("viewer", {"action": "estop"})
    status, approved = await _approve(gated, pending_id)
    assert (status, approved["reason"]) == (404, "pending_not_found"), approved
    assert gated.gov.latch.latched and _clears_sent(gated) == []


async def test_an_estop_as_the_clear_is_being_held_gets_it_refused_when_approved(
        gated: Api) -> None:
    """The e-stop comes while the clear's PENDING_AUTH is written (not in the store yet, so
    the e-stop's withdrawal cannot take it): approved, it is refused `estop_active`."""
    api = gated
    await api.command("viewer", {"action": "estop"})
    append = api.gov.audit.append
    writing, release = asyncio.Event(), asyncio.Event()

    async def slow_pending(entry: Any, **kwargs: Any) -> Any:
        if getattr(entry, "event", None) == "PENDING_AUTH":
            writing.set()
            await release.wait()
        return await append(entry, **kwargs)

    api.gov.audit.append = slow_pending  # type: ignore[method-assign]
    holding = asyncio.ensure_future(api.command("ops", {"action": "clear_estop"}))
    await asyncio.wait_for(writing.wait(), 30)
    await api.command("viewer", {"action": "estop"})
    release.set()
    status, held = await holding
    assert status == 202, held
    status, approved = await _approve(api, held["pending_id"])
    assert (status, approved["reason"]) == (409, "estop_active"), approved
    assert api.entry(approved["audit_id"])["event"] == "HITL_AUTHORIZED"
    assert api.gov.latch.latched and _clears_sent(api) == []


async def test_a_clear_held_after_the_last_estop_still_clears_it(gated: Api) -> None:
    await gated.command("viewer", {"action": "estop"})
    pending_id = await _held(gated, {"action": "clear_estop"})
    status, approved = await _approve(gated, pending_id)
    assert (status, approved["outcome"]) == (200, "executed"), approved
    assert not gated.gov.latch.latched and _clears_sent(gated) == ["clear_estop"]
