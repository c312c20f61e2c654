"""§9 HiTL: approve, deny, expire, wrong role, self-approval, approval-time re-check, webhook;
withdrawal by the issuer; n-of-m approval; approvers and their reasons in the audit."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Any

import msgspec
import pytest
from aiohttp import web
from govhelpers import (
    ADMIN,
    OPS,
    PLANNER,
    Harness,
    command,
    principal,
    withdrawals_missed,
)
from local_http import serve_post
from waiting import eventually

from rcan_rtps.governance.governor import Decision, Governor
from rcan_rtps.governance.hitl import WebhookNotifier
from rcan_rtps.rcan import ErrorCode, Outcome, PendingAuth, Role

ARM = {"joints": ["shoulder", "elbow"], "positions": [0.1, -0.2], "duration_s": 2.0}


async def hold(gov: Governor, who: Any = PLANNER) -> Decision:
    d = await gov.decide(command("arm_joint", ARM), who)
    assert d.outcome is Outcome.PENDING_AUTH and d.pending_id
    return d


async def test_approve_dispatches_and_audits(harness: Harness, gov: Governor) -> None:
    held = await hold(gov)
    assert [p.pending_id for p in gov.pending()] == [held.pending_id]
    assert gov.pending()[0].requires_auth_from_role == "OWNER"
    d = await gov.authorize(held.pending_id or "", OPS)
    assert (d.http_status, d.outcome) == (200, Outcome.EXECUTED)
    assert harness.dispatcher.calls == [("arm_joint", {"joints": ["shoulder", "elbow"],
                                                      "positions": [0.1, -0.2],
                                                      "duration_s": 2.0})]
    events = [(e["event"], e["outcome"], e["principal"]) for e in harness.entries]
    assert events == [("PENDING_AUTH", "pending_auth", "planner"),
                      ("HITL_AUTHORIZED", "executed", "ops")]
    assert harness.entries[1]["pending_id"] == held.pending_id
    assert gov.pending() == []
    again = await gov.authorize(held.pending_id or "", OPS)  # one approval, one execution
    assert (again.http_status, again.reason) == (404, "pending_not_found")
    assert len(harness.dispatcher.calls) == 1


async def test_deny_discards(harness: Harness, gov: Governor) -> None:
    held = await hold(gov)
    d = await gov.deny(held.pending_id or "", OPS)
    assert (d.http_status, d.outcome, d.reason) == (200, Outcome.DENIED, "hitl_denied")
    assert harness.entries[-1]["event"] == "HITL_DENIED"
    assert harness.entries[-1]["outcome"] == "denied"  # bridge spec §3.1 flow 3 step 6
    assert harness.dispatcher.calls == [] and gov.pending() == []


async def test_expiry_is_swept_and_audited(harness: Harness, gov: Governor) -> None:
    held = await hold(gov)
    harness.clock.advance(299)
    assert await gov.expire_pending() == []
    harness.clock.advance(1)
    [expired] = await gov.expire_pending()
    assert expired.reason == "pending_expired"
    entry = harness.entries[-1]
    assert (entry["event"], entry["pending_id"]) == ("HITL_EXPIRED", held.pending_id)
    assert entry["outcome"] == "denied"  # bridge spec §3.1 flow 3 step 6: timeout is a deny
    d = await gov.authorize(held.pending_id or "", OPS)
    assert d.reason == "pending_not_found"
    assert harness.dispatcher.calls == []


async def test_the_timeout_is_the_configs(harness: Harness) -> None:
    """Bridge spec §10.3: "the §9 HiTL gate with configurable timeout"."""
    gov = await harness.governor(hitl_timeout=45)
    held = await hold(gov)
    assert held.expires_at_ms == int(harness.clock.time() * 1000) + 45_000
    harness.clock.advance(44)
    assert await gov.expire_pending() == []
    harness.clock.advance(1)
    [expired] = await gov.expire_pending()
    assert (expired.reason, harness.entries[-1]["event"]) == ("pending_expired", "HITL_EXPIRED")


async def test_late_authorize_expires_it_first(harness: Harness, gov: Governor) -> None:
    held = await hold(gov)
    harness.clock.advance(301)  # the sweep has not run yet
    d = await gov.authorize(held.pending_id or "", OPS)
    assert (d.http_status, d.reason) == (404, "pending_expired")
    assert [e["event"] for e in harness.entries][-2:] == ["HITL_EXPIRED", "COMMAND_REJECTED"]
    assert harness.dispatcher.calls == []


async def test_wrong_role_cannot_approve_or_deny(harness: Harness, gov: Governor) -> None:
    held = await hold(gov)
    for verb, said in ((gov.authorize, "approve"), (gov.deny, "deny")):
        d = await verb(held.pending_id or "", principal("lease", Role.LEASEE))
        assert (d.http_status, d.error_code) == (403, ErrorCode.INSUFFICIENT_PRIVILEGES)
        assert d.reason == f"to {said} it needs OWNER or higher", d.reason  # what was needed
    assert len(gov.pending()) == 1  # still waiting
    assert (await gov.authorize(held.pending_id or "", ADMIN)).outcome is Outcome.EXECUTED


async def test_self_approval_refused_when_distinct_required(harness: Harness) -> None:
    gov = await harness.governor("require_distinct_approver: true")
    held = await hold(gov, OPS)
    d = await gov.authorize(held.pending_id or "", OPS)
    assert (d.http_status, d.reason) == (403, "self_approval")
    assert harness.dispatcher.calls == []
    assert (await gov.authorize(held.pending_id or "", ADMIN)).outcome is Outcome.EXECUTED


async def test_self_approval_allowed_by_default(gov: Governor) -> None:
    held = await hold(gov, OPS)
    assert (await gov.authorize(held.pending_id or "", OPS)).outcome is Outcome.EXECUTED


async def test_authorize_rechecks_invariants_at_approval_time(
    harness: Harness, gov: Governor
) -> None:
    withdrawals_missed(gov)  # the e-stop withdraws held motion: the recheck is its backstop
    held = await hold(gov)
    await gov.decide(command("estop"), PLANNER)  # latched while the request waited
    d = await gov.authorize(held.pending_id or "", OPS)
    assert (d.http_status, d.outcome, d.reason) == (409, Outcome.DENIED, "estop_active")
    entry = harness.entries[-1]
    assert (entry["event"], entry["outcome"]) == ("HITL_AUTHORIZED", "denied")
    assert [c[0] for c in harness.dispatcher.calls] == ["estop"]


async def test_concurrent_approvals_execute_once(harness: Harness, gov: Governor) -> None:
    held = await hold(gov)
    results = await asyncio.gather(*(gov.authorize(held.pending_id or "", OPS)
                                     for _ in range(5)))
    assert sum(r.outcome is Outcome.EXECUTED for r in results) == 1
    assert len(harness.dispatcher.calls) == 1


# -- withdrawal -----------------------------------------------------------------------------


def reviews(entry: dict[str, Any]) -> list[tuple[str, str, str | None]]:
    """(principal, decision, reason) of each review an audit entry names."""
    return [(r["principal"], r["decision"], r.get("reason")) for r in entry["approvals"]]


async def test_the_issuer_withdraws_its_pending_command(harness: Harness, gov: Governor) -> None:
    held = await hold(gov)
    d = await gov.withdraw(held.pending_id or "", PLANNER, "wrong arm")
    assert (d.http_status, d.outcome, d.reason) == (200, Outcome.DENIED, "hitl_withdrawn")
    entry = harness.entries[-1]
    assert (entry["event"], entry["principal"], entry["pending_id"], entry["audit_id"]) == (
        "HITL_WITHDRAWN", "planner", held.pending_id, d.audit_id)
    assert entry["deny_reason"] == "COMMAND_REJECTED:hitl_withdrawn"
    assert reviews(entry) == [("planner", "withdraw", "wrong arm")]
    assert gov.pending() == []
    late = await gov.authorize(held.pending_id or "", OPS)  # gone: it can never run now
    assert (late.http_status, late.reason) == (404, "pending_not_found")
    assert harness.dispatcher.calls == []


async def test_a_stranger_cannot_withdraw_but_an_approver_may(
    harness: Harness, gov: Governor
) -> None:
    held = await hold(gov)
    for stranger in (principal("other", Role.USER), principal("lease", Role.LEASEE)):
        d = await gov.withdraw(held.pending_id or "", stranger)
        assert (d.http_status, d.error_code) == (403, ErrorCode.INSUFFICIENT_PRIVILEGES)
        entry = harness.entries[-1]
        assert (entry["event"], entry["action_type"], entry["principal"], entry["pending_id"]) \
            == ("COMMAND_REJECTED", "hitl_withdraw", stranger.name, held.pending_id)
    assert len(gov.pending()) == 1  # still waiting
    d = await gov.withdraw(held.pending_id or "", OPS, "not today")
    assert (d.http_status, d.reason) == (200, "hitl_withdrawn")
    assert reviews(harness.entries[-1]) == [("ops", "withdraw", "not today")]
    assert harness.dispatcher.calls == []


# -- n-of-m approval ------------------------------------------------------------------------

TWO_OWNERS = "[{action: arm_joint, require_auth: true, approvals: 2, authorized_roles: [OWNER]}]"
OPS2 = principal("ops2", Role.OWNER)


async def test_two_of_three_approvers(harness: Harness) -> None:
    gov = await harness.governor(gates=TWO_OWNERS)
    held = await hold(gov)
    pending_id = held.pending_id or ""
    assert gov.pending()[0].approvals_required == 2

    first = await gov.authorize(pending_id, OPS, "checked the cell")
    assert (first.http_status, first.outcome, first.pending_id) == (
        202, Outcome.PENDING_AUTH, pending_id)
    assert harness.dispatcher.calls == []
    entry = harness.entries[-1]
    assert (entry["event"], entry["principal"], entry["outcome"], entry["audit_id"]) == (
        "HITL_APPROVAL", "ops", "pending_auth", first.audit_id)
    assert reviews(entry) == [("ops", "approve", "checked the cell")]
    [waiting] = gov.pending()
    assert [(a.principal, a.reason) for a in waiting.approvals] == [("ops", "checked the cell")]

    again = await gov.authorize(pending_id, OPS, "really")  # the same approver counts once
    assert (again.http_status, again.reason) == (409, "already_approved")
    assert harness.dispatcher.calls == [] and len(gov.pending()) == 1

    second = await gov.authorize(pending_id, ADMIN, "clear of people")
    assert (second.http_status, second.outcome) == (200, Outcome.EXECUTED)
    assert [c[0] for c in harness.dispatcher.calls] == ["arm_joint"]
    entry = harness.entries[-1]
    assert (entry["event"], entry["principal"], entry["audit_id"]) == (
        "HITL_AUTHORIZED", "root", second.audit_id)
    assert reviews(entry) == [("ops", "approve", "checked the cell"),
                              ("root", "approve", "clear of people")]
    assert [r["role"] for r in entry["approvals"]] == ["OWNER", "CREATOR"]
    assert gov.pending() == []
    third = await gov.authorize(pending_id, OPS2)
    assert third.http_status == 404 and len(harness.dispatcher.calls) == 1


async def test_the_issuer_is_never_one_of_several_approvers(harness: Harness) -> None:
    gov = await harness.governor(gates=TWO_OWNERS)  # require_distinct_approver is off
    held = await hold(gov, OPS)
    d = await gov.authorize(held.pending_id or "", OPS)
    assert (d.http_status, d.reason) == (403, "self_approval")
    assert (await gov.authorize(held.pending_id or "", OPS2)).http_status == 202
    assert (await gov.authorize(held.pending_id or "", ADMIN)).outcome is Outcome.EXECUTED
    assert [r[0] for r in reviews(harness.entries[-1])] == ["ops2", "root"]


async def test_a_deny_by_any_approver_ends_it(harness: Harness) -> None:
    gov = await harness.governor(gates=TWO_OWNERS)
    held = await hold(gov)
    assert (await gov.authorize(held.pending_id or "", OPS, "fine")).http_status == 202
    d = await gov.deny(held.pending_id or "", ADMIN, "cell door open")
    assert (d.http_status, d.outcome, d.reason) == (200, Outcome.DENIED, "hitl_denied")
    entry = harness.entries[-1]
    assert (entry["event"], entry["principal"]) == ("HITL_DENIED", "root")
    assert reviews(entry) == [("ops", "approve", "fine"), ("root", "deny", "cell door open")]
    assert gov.pending() == [] and harness.dispatcher.calls == []
    assert (await gov.authorize(held.pending_id or "", OPS2)).http_status == 404


async def test_the_final_approval_rechecks_the_invariants(harness: Harness) -> None:
    gov = await harness.governor(gates=TWO_OWNERS)
    withdrawals_missed(gov)  # the e-stop withdraws held motion: the recheck is its backstop
    held = await hold(gov)
    assert (await gov.authorize(held.pending_id or "", OPS)).http_status == 202
    await gov.decide(command("estop"), PLANNER)
    d = await gov.authorize(held.pending_id or "", ADMIN)
    assert (d.http_status, d.reason) == (409, "estop_active")
    entry = harness.entries[-1]
    assert (entry["event"], entry["outcome"]) == ("HITL_AUTHORIZED", "denied")
    assert [r[0] for r in reviews(entry)] == ["ops", "root"]
    assert [c[0] for c in harness.dispatcher.calls] == ["estop"]


async def test_expiry_names_the_approvals_it_had(harness: Harness) -> None:
    gov = await harness.governor(gates=TWO_OWNERS)
    held = await hold(gov)
    assert (await gov.authorize(held.pending_id or "", OPS, "ok")).http_status == 202
    harness.clock.advance(301)
    await gov.expire_pending()
    entry = harness.entries[-1]
    assert (entry["event"], entry["pending_id"]) == ("HITL_EXPIRED", held.pending_id)
    assert reviews(entry) == [("ops", "approve", "ok")]
    assert harness.dispatcher.calls == []


async def test_racing_approvals_execute_exactly_once(harness: Harness) -> None:
    gov = await harness.governor(gates=TWO_OWNERS)
    # Two distinct approvers at once: one counts, the other releases it; it runs once.
    held = await hold(gov)
    both = await asyncio.gather(gov.authorize(held.pending_id or "", OPS),
                                gov.authorize(held.pending_id or "", OPS2))
    assert sorted(d.http_status for d in both) == [200, 202]
    assert len(harness.dispatcher.calls) == 1
    # Three at once: one counts, one releases, one finds it gone.
    held = await hold(gov)
    three = await asyncio.gather(*(gov.authorize(held.pending_id or "", who)
                                   for who in (OPS, OPS2, ADMIN)))
    assert sorted(d.http_status for d in three) == [200, 202, 404]
    assert len(harness.dispatcher.calls) == 2
    # The same approver twice at once counts once: still pending, nothing ran.
    held = await hold(gov)
    twice = await asyncio.gather(gov.authorize(held.pending_id or "", OPS),
                                 gov.authorize(held.pending_id or "", OPS))
    assert sorted((d.http_status, d.reason) for d in twice) == [
        (202, None), (409, "already_approved")]
    assert len(harness.dispatcher.calls) == 2 and len(gov.pending()) == 1
    # An approval racing a withdrawal: one of them wins, and it never runs twice.
    both = await asyncio.gather(gov.authorize(held.pending_id or "", OPS2),
                                gov.withdraw(held.pending_id or "", PLANNER))
    assert sorted(d.http_status for d in both) == [200, 404]
    ends = [e["event"] for e in harness.entries if e.get("pending_id") == held.pending_id
            and e["event"] in ("HITL_AUTHORIZED", "HITL_WITHDRAWN")]
    assert len(ends) == 1 and gov.pending() == []
    assert len(harness.dispatcher.calls) == (3 if ends == ["HITL_AUTHORIZED"] else 2)


async def test_one_approval_records_its_reason(harness: Harness, gov: Governor) -> None:
    held = await hold(gov)
    d = await gov.authorize(held.pending_id or "", OPS, "seen on camera")
    assert d.outcome is Outcome.EXECUTED
    assert reviews(harness.entries[-1]) == [("ops", "approve", "seen on camera")]
    held = await hold(gov)
    await gov.deny(held.pending_id or "", OPS, "too close to the wall")
    assert reviews(harness.entries[-1]) == [("ops", "deny", "too close to the wall")]
    held = await hold(gov)
    await gov.authorize(held.pending_id or "", OPS)  # no reason given: none recorded
    assert reviews(harness.entries[-1]) == [("ops", "approve", None)]


# -- webhook --------------------------------------------------------------------------------


class Hook:
    """A local webhook receiver on 127.0.0.1 that can fail, or hold a request open."""

    def __init__(self) -> None:
        self.received: list[dict[str, Any]] = []
        self.fail_first = 0
        self.release = asyncio.Event()
        self.release.set()

    async def handle(self, request: web.Request) -> web.Response:
        self.received.append(msgspec.json.decode(await request.read()))
        await self.release.wait()
        if self.fail_first > 0:
            self.fail_first -= 1
            return web.Response(status=500)
        return web.Response(status=204)


@pytest.fixture
async def hook() -> AsyncIterator[tuple[Hook, str]]:
    hook = Hook()
    runner, url = await serve_post("/hitl", hook.handle)
    yield hook, url
    hook.release.set()
    await runner.cleanup()


async def test_webhook_gets_pending_auth_and_never_blocks(
    harness: Harness, hook: tuple[Hook, str]
) -> None:
    receiver, url = hook
    receiver.release.clear()  # the webhook hangs until we let it go
    gov = await harness.governor(notifier=WebhookNotifier(url, attempts=1, timeout_s=30))
    d = await hold(gov)  # returned while the webhook is still held open
    await eventually(lambda: receiver.received, what="the webhook is called")
    assert not receiver.release.is_set()
    message = receiver.received[0]
    assert message["pending_id"] == d.pending_id
    assert message["requires_auth_from_role"] == "OWNER"
    assert message["expires_at_ms"] == d.expires_at_ms
    assert message["original_command"]["action"] == "arm_joint"
    assert set(message) >= {"pending_id", "original_command", "confidence", "ai_model",
                            "requires_auth_from_role", "expires_at_ms"}
    receiver.release.set()
    await asyncio.gather(*gov._tasks)


async def test_webhook_retries(hook: tuple[Hook, str]) -> None:
    receiver, url = hook
    receiver.fail_first = 2
    message = PendingAuth(pending_id="p", original_command={}, confidence=None, ai_model=None,
                          requires_auth_from_role="OWNER", expires_at_ms=1, issued_by="x")
    await WebhookNotifier(url, attempts=3, backoff_s=0.01).notify(message)
    assert len(receiver.received) == 3


async def test_webhook_gives_up_quietly_when_unreachable() -> None:
    message = PendingAuth(pending_id="p", original_command={}, confidence=None, ai_model=None,
                          requires_auth_from_role="OWNER", expires_at_ms=1, issued_by="x")
    notifier = WebhookNotifier("http://127.0.0.1:9/none", attempts=2, backoff_s=0.01,
                               timeout_s=1)
    await notifier.notify(message)  # logs, does not raise
