"""HiTL reviews through the real aiohttp app: the issuer withdraws, strangers may not, n-of-m
approval (racing requests included), approvers and their reasons in the audit."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from rcan_rtps.governance import AuditEvent, AuditRecord
from tests.api.apihelpers import Api

ARM = {"action": "arm_joint", "params": {"joints": ["elbow"], "positions": [0.5],
                                         "duration_s": 1.0}}
TWO_OWNERS = ("[{action: arm_joint, require_auth: true, approvals: 2, "
              "authorized_roles: [OWNER]}]")


async def hold(api: Api, who: str = "planner") -> str:
    status, body = await api.command(who, ARM)
    assert (status, body["outcome"]) == (202, "pending_auth"), body
    return str(body["pending_id"])


async def review(api: Api, verb: str, who: str, pending_id: str,
                 reason: str | None = None) -> tuple[int, Any]:
    body: dict[str, Any] = {"pending_id": pending_id}
    if reason is not None:
        body["reason"] = reason
    return await api.call("POST", f"/api/hitl/{verb}", who, body=body)


def reviews(entry: dict[str, Any]) -> list[tuple[str, str, str | None]]:
    return [(r["principal"], r["decision"], r.get("reason")) for r in entry["approvals"]]


@pytest.fixture
async def two_of_three(tmp_path: Path) -> AsyncIterator[Api]:
    """arm_joint needs two distinct OWNER+ approvers: ops, ops2 and root can approve."""
    api = await Api(tmp_path, gates=TWO_OWNERS).start()
    yield api
    await api.close()


async def test_the_issuer_withdraws_over_http(api: Api) -> None:
    pending_id = await hold(api)
    status, body = await review(api, "withdraw", "planner", pending_id, "typo in the target")
    assert (status, body["outcome"], body["reason"]) == (200, "denied", "hitl_withdrawn")
    entry = api.entry(body["audit_id"])
    assert (entry["event"], entry["principal"], entry["pending_id"]) == (
        "HITL_WITHDRAWN", "planner", pending_id)
    assert reviews(entry) == [("planner", "withdraw", "typo in the target")]
    assert (await api.call("GET", "/api/hitl/pending", "ops"))[1]["pending"] == []
    status, body = await review(api, "authorize", "ops", pending_id)
    assert (status, body["reason"]) == (404, "pending_not_found")
    assert api.dispatcher.calls == []  # the command never executed


async def test_a_stranger_cannot_withdraw_over_http(api: Api) -> None:
    pending_id = await hold(api)
    for stranger in ("slow", "viewer", "lessee"):  # not its issuer, not an approver
        status, body = await review(api, "withdraw", stranger, pending_id)
        assert (status, body["error_code"]) == (403, "INSUFFICIENT_PRIVILEGES")
        entry = api.entry(body["audit_id"])
        assert (entry["event"], entry["action_type"], entry["principal"]) == (
            "COMMAND_REJECTED", "hitl_withdraw", stranger)
    assert len((await api.call("GET", "/api/hitl/pending", "ops"))[1]["pending"]) == 1
    status, body = await review(api, "withdraw", "ops", pending_id)  # an approver may
    assert (status, body["reason"]) == (200, "hitl_withdrawn")
    assert api.dispatcher.calls == []


async def test_two_of_three_over_http(two_of_three: Api) -> None:
    api = two_of_three
    pending_id = await hold(api)
    status, body = await review(api, "authorize", "ops", pending_id, "cell is clear")
    assert (status, body["outcome"], body["pending_id"]) == (202, "pending_auth", pending_id)
    entry = api.entry(body["audit_id"])
    assert (entry["event"], reviews(entry)) == (
        "HITL_APPROVAL", [("ops", "approve", "cell is clear")])
    [listed] = (await api.call("GET", "/api/hitl/pending", "ops"))[1]["pending"]
    assert listed["approvals_required"] == 2
    assert [a["principal"] for a in listed["approvals"]] == ["ops"]
    assert api.dispatcher.calls == []

    status, body = await review(api, "authorize", "ops", pending_id)  # counts once
    assert (status, body["reason"]) == (409, "already_approved")
    assert api.dispatcher.calls == []

    status, body = await review(api, "authorize", "ops2", pending_id, "arm is homed")
    assert (status, body["outcome"]) == (200, "executed")
    assert [a for a, _ in api.dispatcher.calls] == ["arm_joint"]
    entry = api.entry(body["audit_id"])
    assert (entry["event"], entry["principal"]) == ("HITL_AUTHORIZED", "ops2")
    assert reviews(entry) == [("ops", "approve", "cell is clear"),
                              ("ops2", "approve", "arm is homed")]


async def test_a_deny_ends_an_n_of_m_approval(two_of_three: Api) -> None:
    api = two_of_three
    pending_id = await hold(api)
    assert (await review(api, "authorize", "ops", pending_id))[0] == 202
    status, body = await review(api, "deny", "root", pending_id, "someone in the cell")
    assert (status, body["reason"]) == (200, "hitl_denied")
    entry = api.entry(body["audit_id"])
    assert (entry["event"], reviews(entry)) == (
        "HITL_DENIED", [("ops", "approve", None), ("root", "deny", "someone in the cell")])
    assert (await review(api, "authorize", "ops2", pending_id))[0] == 404
    assert api.dispatcher.calls == []


async def test_racing_approvals_over_http_execute_once(
    two_of_three: Api, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two approvals in flight at once: the first one's audit entry is held until the second
    request is inside the governor, so both are deciding at the same time."""
    api = two_of_three
    gov = api.gov
    both_in = asyncio.Event()
    calls = 0
    authorize, append = gov.authorize, gov.audit.append

    async def counted_authorize(*args: Any, **kwargs: Any) -> Any:
        nonlocal calls
        calls += 1
        if calls == 2:
            both_in.set()
        return await authorize(*args, **kwargs)

    async def held_append(record: AuditRecord, **kwargs: Any) -> Any:
        if record.event is AuditEvent.HITL_APPROVAL:
            await asyncio.wait_for(both_in.wait(), timeout=10)
        return await append(record, **kwargs)

    monkeypatch.setattr(gov, "authorize", counted_authorize)
    monkeypatch.setattr(gov.audit, "append", held_append)
    pending_id = await hold(api)
    answers = await asyncio.gather(review(api, "authorize", "ops", pending_id),
                                   review(api, "authorize", "ops2", pending_id))
    assert calls == 2
    assert sorted(status for status, _ in answers) == [200, 202], answers
    assert len(api.dispatcher.calls) == 1
    [authorized] = [e for e in api.entries if e["event"] == "HITL_AUTHORIZED"]
    assert sorted(r[0] for r in reviews(authorized)) == ["ops", "ops2"]


async def test_reasons_of_one_approver_are_audited(api: Api) -> None:
    """The `reason` of an Authorize body was accepted and dropped before."""
    pending_id = await hold(api)
    status, body = await review(api, "authorize", "ops", pending_id, "watched it on camera")
    assert (status, body["outcome"]) == (200, "executed")
    assert reviews(api.entry(body["audit_id"])) == [("ops", "approve", "watched it on camera")]
    pending_id = await hold(api)
    status, body = await review(api, "deny", "ops", pending_id, "battery low")
    assert reviews(api.entry(body["audit_id"])) == [("ops", "deny", "battery low")]
