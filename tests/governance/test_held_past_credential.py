"""A held command never outlives the credential it was held with (red team 30).

A command held for a human runs, once approved, as its issuer's `Principal` — the one the API
authenticated when it was sent, with its role and its credential's end (`expires_at`: a JWT's
`exp` plus the leeway, a client certificate's notAfter). Over a WebSocket the socket closes at
that end and its held motion is withdrawn; over REST nothing ended it, and an approval after
it ran the command for a principal the bridge no longer accepted. Now the sweep withdraws it at
that end (HITL_WITHDRAWN by its issuer, `CREDENTIAL_EXPIRED`), and an approval that comes
first withdraws it the same way and is refused 409 `issuer_credential_expired`. A configured
token never ends; a fresh credential of the same principal does not keep a held command of the
old one (it belongs to the credential: it would run with the old one's role)."""

from __future__ import annotations

import msgspec
from govhelpers import OPS, Harness, command, principal

from rcan_rtps.governance.clock import ManualClock, latest_wall
from rcan_rtps.governance.governor import Governor
from rcan_rtps.governance.rbac import Principal
from rcan_rtps.governance.review import CREDENTIAL_EXPIRED
from rcan_rtps.rcan import Outcome, Role

ARM = {"joints": ["shoulder", "elbow"], "positions": [0.1, -0.2], "duration_s": 2.0}
LIFE_S = 60.0  # what the issuer's credential has left when its command is held


def _agent(clock: ManualClock, left_s: float | None = LIFE_S) -> Principal:
    """A USER whose credential ends `left_s` from now (None: a configured token)."""
    expires = None if left_s is None else clock.time() + left_s
    return msgspec.structs.replace(principal("agent", Role.USER), expires_at=expires)


async def _held(gov: Governor, who: Principal) -> str:
    held = await gov.decide(command("arm_joint", ARM), who)
    assert held.outcome is Outcome.PENDING_AUTH and held.pending_id, held
    return held.pending_id


def _ends(harness: Harness, pending_id: str) -> list[dict[str, object]]:
    return [e for e in harness.entries if e.get("pending_id") == pending_id
            and e["event"] in ("HITL_AUTHORIZED", "HITL_WITHDRAWN", "HITL_EXPIRED")]


def _withdrawn_for_expiry(gov: Governor, harness: Harness, pending_id: str) -> None:
    """Ended once, as its issuer's withdrawal naming the expiry; out of the list; its issuer
    reads `hitl_withdrawn`; nothing reached the robot."""
    [end] = _ends(harness, pending_id)
    assert (end["event"], end["principal"], end["outcome"]) == (
        "HITL_WITHDRAWN", "agent", "denied"), end
    assert [r["reason"] for r in end["approvals"]] == [CREDENTIAL_EXPIRED]  # type: ignore
    assert pending_id not in {p.pending_id for p in gov.pending()}
    record = gov.pending_record(pending_id)
    assert record is not None and record.state == "resolved"
    assert record.decision is not None and record.decision.reason == "hitl_withdrawn"
    assert harness.dispatcher.calls == []


async def test_an_approval_after_the_issuer_s_credential_ran_out_is_refused(
        harness: Harness, clock: ManualClock) -> None:
    gov = await harness.governor()
    pending_id = await _held(gov, _agent(clock))
    clock.advance(LIFE_S + 1)  # no sweep yet: the approval comes first
    refused = await gov.authorize(pending_id, OPS)
    assert (refused.http_status, refused.outcome, refused.reason) == (
        409, Outcome.DENIED, "issuer_credential_expired"), refused
    _withdrawn_for_expiry(gov, harness, pending_id)
    rejected = harness.entries[-1]
    assert (rejected["event"], rejected["principal"], rejected["action_type"]) == (
        "COMMAND_REJECTED", "ops", "hitl_authorize")
    assert rejected["deny_reason"] == "COMMAND_REJECTED:issuer_credential_expired"
    again = await gov.authorize(pending_id, OPS)  # it is gone
    assert again.reason == "pending_not_found", again


async def test_only_who_may_approve_it_is_told(harness: Harness, clock: ManualClock) -> None:
    """A principal that may not approve it is refused for that, as before the expiry."""
    gov = await harness.governor()
    pending_id = await _held(gov, _agent(clock))
    clock.advance(LIFE_S + 1)
    refused = await gov.authorize(pending_id, principal("lessee", Role.LEASEE))
    assert (refused.http_status, refused.error_code.value) == (403, "INSUFFICIENT_PRIVILEGES")
    assert _ends(harness, pending_id) == []
    assert (await gov.authorize(pending_id, OPS)).reason == "issuer_credential_expired"
    _withdrawn_for_expiry(gov, harness, pending_id)


async def test_the_sweep_withdraws_it_when_the_credential_ends(
        harness: Harness, clock: ManualClock) -> None:
    gov = await harness.governor()
    pending_id = await _held(gov, _agent(clock))
    told: list[set[str]] = []
    gov.events.governance.subscribe(lambda: told.append({p.pending_id for p in gov.pending()}))
    clock.advance(LIFE_S - 1)
    await gov.sweep()
    assert _ends(harness, pending_id) == [] and told == []  # not yet
    clock.advance(1)  # its end, exactly (the API refuses the credential from then on)
    await gov.sweep()
    _withdrawn_for_expiry(gov, harness, pending_id)
    assert told and pending_id not in told[-1]  # the approvers' list was told
    late = await gov.authorize(pending_id, OPS)
    assert late.reason == "pending_not_found", late
    assert harness.dispatcher.calls == []


async def test_a_clock_stepped_back_revives_no_held_command(
        harness: Harness, clock: ManualClock) -> None:
    """Judged by the latest wall time read, as the API judges the credential itself."""
    gov = await harness.governor()
    pending_id = await _held(gov, _agent(clock))
    clock.step(LIFE_S + 1)
    latest_wall(clock).time()  # read (a token checked, a message's time) before the step back
    clock.step(-3600)
    await gov.sweep()
    _withdrawn_for_expiry(gov, harness, pending_id)


async def test_a_fresh_credential_of_the_same_principal_does_not_keep_it(
        harness: Harness, clock: ManualClock) -> None:
    gov = await harness.governor()
    pending_id = await _held(gov, _agent(clock))
    clock.advance(LIFE_S - 5)
    again = await _held(gov, _agent(clock, 3600))  # the same principal, with a new token
    clock.advance(10)
    await gov.sweep()
    _withdrawn_for_expiry(gov, harness, pending_id)
    assert (await gov.authorize(again, OPS)).outcome is Outcome.EXECUTED  # the fresh one's


async def test_a_credential_that_does_not_expire_keeps_it(
        harness: Harness, clock: ManualClock) -> None:
    gov = await harness.governor()
    token = await _held(gov, _agent(clock, None))
    later = await _held(gov, _agent(clock, 10 * LIFE_S))
    clock.advance(2 * LIFE_S)  # within the HiTL timeout (300 s)
    await gov.sweep()
    assert _ends(harness, token) == [] and _ends(harness, later) == []
    for pending_id in (token, later):
        assert (await gov.authorize(pending_id, OPS)).outcome is Outcome.EXECUTED


async def test_approvers_are_shown_when_the_issuer_s_credential_ends(
        harness: Harness, clock: ManualClock) -> None:
    """PENDING_AUTH said only its TTL's end: an approver could not tell that a command held
    with a credential ending sooner would be withdrawn then. It now says that end when it
    comes first (the pending list, a record, the webhook's message), and nothing otherwise:
    a configured token, or a credential outliving the hold (TTL 300 s here)."""
    gov = await harness.governor()
    ends_soon = _agent(clock)
    soon = await _held(gov, ends_soon)
    token = await _held(gov, _agent(clock, None))
    outlives = await _held(gov, _agent(clock, 400.0))
    shown = {p.pending_id: p.issuer_credential_ends_at_ms for p in gov.pending()}
    assert ends_soon.expires_at is not None
    assert shown == {soon: int(ends_soon.expires_at * 1000), token: None, outlives: None}
    record = gov.pending_record(soon)
    assert record is not None
    assert record.held.issuer_credential_ends_at_ms == shown[soon]
    assert shown[soon] < record.held.expires_at_ms  # (sooner than the TTL: why it is shown)
