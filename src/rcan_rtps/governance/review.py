"""The HiTL desk (§9): holding a gated command, and its reviews — approve, deny, withdraw.

`hitl.py` holds the policy (which commands are gated, by whom, how many approvals) and the
store of pending commands. This module is what happens to them: a held command is on record
(PENDING_AUTH) before it can be reviewed; each review is checked and counted once, under the
command's own lock; an approval of several is on record (HITL_APPROVAL) before it counts; a
denial or a withdrawal ends it; an expired one is discarded and audited. The command the last
approval releases goes back to the governor, which runs it through the pipeline as it is *now*.
A stop withdraws the held motion it is a stop for (`withdrawing` picks it in the stop's step,
each withdrawn as its issuer would, by `resolve`).

A held command belongs to the credential it was held with, not to its principal's name: it
runs as that `Principal` (its role), so it never outlives that credential — a JWT's `exp`
(plus the leeway), a client certificate's notAfter (`Principal.expires_at`; a configured
token's never ends). The governor's sweep withdraws it once that has passed (`credentials_ended`
picks it; HITL_WITHDRAWN, `CREDENTIAL_EXPIRED`), and an approval that comes first withdraws it
so itself and is refused `issuer_credential_expired`. A fresh token of the same principal does not
keep it: that token may state another role, and REST tells the bridge of no renewal between
requests; its issuer asks again.

A review said by an RCAN message (an AUTHORIZE, §16.4) comes with that message's facts
(`ReviewMessage`): its id and audit facts (the signature's alg, kid and whether it verified,
recorded with the review and with a refusal of it), and — in the SDK's envelope — the held
command's `message_id` it names: a review of any other command is refused (signed:
`signed_for_another_command`; unsigned: `not_the_held_command`). Whether a review had to be
signed is the transport's check, before it gets here (`signatures.Signatures.check_review`).

What came of a held command stays readable for a while (`KEPT_RESOLVED` of them, the oldest let
go first): its issuer — an agent waiting for a human — learns it was executed, denied, withdrawn
or expired without the approvers' list or the audit log (GET /api/hitl/pending/{pending_id}).
Whoever must answer for it once it ends (a held INVOKE's INVOKE_RESULT, §19) awaits that end
(`ended`): the decision, and the review that made it.
"""

from __future__ import annotations

import asyncio
import uuid
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from typing import Any, Literal, cast

import msgspec

from rcan_rtps.rcan import Approval, NormalizedCommand, Outcome, PendingAuth, Role, RoleName
from rcan_rtps.rcan._v3 import normal_id

from . import outcomes
from .audit import AuditEvent, AuditRecord
from .clock import Clock, latest_wall, now_ms
from .hitl import Held, HitlPolicy, Notifier, PendingCommand, PendingStore, Verdict
from .outcomes import Rejection
from .rbac import Principal
from .steps import Decision, Steps, decision, record

# Runs an approved command (taken from the store, with every review) for its last approver.
RunApproved = Callable[[NormalizedCommand, Principal, PendingCommand], Awaitable[Decision]]
KEPT_RESOLVED = 1024
# The reason of the withdrawal of a held command whose issuer's credential ran out.
CREDENTIAL_EXPIRED = ("withdrawn: its issuer's credential (a JWT's exp, a client certificate's "
                      "notAfter) expired while it was held")
PendingState = Literal["pending", "resolving", "resolved"]


class PendingRecord(msgspec.Struct, frozen=True):
    """A held command as its issuer or an approver may read it: its PENDING_AUTH (`held`),
    and whether it still waits (`waiting`), is being decided (neither) or was (`decision`)."""

    held: PendingAuth
    issuer: str
    approver_role: Role
    waiting: bool = False
    decision: Decision | None = None
    review: Approval | None = None  # the review that ended it (None: it expired)

    def may_read(self, reader: Principal) -> bool:
        return may_read(reader, self.issuer, self.approver_role)

    @property
    def state(self) -> PendingState:
        if self.waiting:
            return "pending"
        return "resolving" if self.decision is None else "resolved"


class ReviewMessage(msgspec.Struct, frozen=True, kw_only=True):
    """The RCAN message (AUTHORIZE) that said a review, as the desk checks and records it."""

    message_id: str | None = None
    rcan: dict[str, Any] | None = None  # its envelope's audit facts (`Envelope.audit_facts`)
    command_message_id: str | None = None  # the held command's message_id it was signed for


NO_MESSAGE = ReviewMessage()


class Ended(msgspec.Struct, frozen=True):
    """What ended a held command: its decision, and the review that made it — the last
    approval, the denial or the withdrawal (who, and why) — or None when it expired."""

    decision: Decision
    review: Approval | None = None


def may_read(reader: Principal, issuer: str, approver_role: Role) -> bool:
    """Whether `reader` may read a held command: its issuer, or a role that could approve it
    (its record by id and the held-command lists, `api._approvals.readable`, alike)."""
    return reader.name == issuer or reader.role >= approver_role


class HitlDesk:
    def __init__(self, steps: Steps, policy: HitlPolicy, clock: Clock, *,
                 timeout_s: float, require_distinct_approver: bool,
                 notifier: Notifier | None, changed: Callable[[], None],
                 run_approved: RunApproved) -> None:
        self._steps = steps
        self._policy = policy
        self._clock = clock
        # Credentials are judged by the latest wall time read, as the API judges them
        # (`api._keys.credential_left`): a clock stepped back revives none.
        self._latest = latest_wall(clock)
        self._ttl_ms = int(timeout_s * 1000)
        self._distinct = require_distinct_approver
        self._notifier = notifier
        self._changed = changed  # what STATUS shows (the pending count) changed
        self._run_approved = run_approved
        self._pending = PendingStore()
        self._resolved: OrderedDict[str, PendingRecord] = OrderedDict()
        # The thought id of each resolved command still kept: one that named another held
        # command (withdrawn, denied, expired) is ambiguous for an AUTHORIZE that names it.
        self._resolved_thoughts: dict[str, str] = {}
        # The ends awaited of held commands not ended yet (`ended`), by pending id.
        self._awaited: dict[str, asyncio.Future[Ended]] = {}

    def pending(self) -> list[PendingAuth]:
        return [held.message() for held in self._pending.list()]

    def record(self, pending_id: str) -> PendingRecord | None:
        """One held command, waiting or resolved (or being decided), or None if unknown."""
        held = self._pending.get(pending_id)
        if held is not None:
            p = held.pending
            return PendingRecord(held.message(), p.issuer.name, p.approver_role, waiting=True)
        return self._resolved.get(pending_id)

    def ended(self, pending_id: str) -> asyncio.Future[Ended] | None:
        """What ends the held command `pending_id`: a future, done once its decision is
        (at once if it is, and still kept), cancelled if its review raised; None if it is
        unknown. The caller must not cancel it (others may await the same one)."""
        kept = self._resolved.get(pending_id)
        if kept is not None and kept.decision is not None:
            done: asyncio.Future[Ended] = asyncio.get_running_loop().create_future()
            done.set_result(Ended(kept.decision, kept.review))
            return done
        if kept is None and self._pending.get(pending_id) is None:
            return None
        awaited = self._awaited.get(pending_id)
        if awaited is None:
            awaited = self._awaited[pending_id] = asyncio.get_running_loop().create_future()
        return awaited

    def _resolving(self, held: Held, decided: Decision | None = None,
                   review: Approval | None = None) -> None:
        pending = held.pending
        self._resolved[pending.pending_id] = PendingRecord(
            held.message(), pending.issuer.name, pending.approver_role, decision=decided,
            review=review)
        self._resolved.move_to_end(pending.pending_id)
        if decided is not None:
            awaited = self._awaited.pop(pending.pending_id, None)
            if awaited is not None and not awaited.done():
                awaited.set_result(Ended(decided, review))
        thought = _thought_of(pending.command)
        if thought is not None:
            self._resolved_thoughts[pending.pending_id] = thought
        while len(self._resolved) > KEPT_RESOLVED:
            gone, _ = self._resolved.popitem(last=False)
            self._resolved_thoughts.pop(gone, None)

    def for_thought(self, thought_id: str) -> str | None:
        """The held command whose AI `thought_id` this is (an AUTHORIZE names it so, §16.4),
        or None when none or more than one has it — or one resolved had it: the issuer could
        withdraw what an approver reviewed and hold another command under the same id (a
        pending_id, made here, is never reused)."""
        found = [held.pending.pending_id for held in self._pending.list()
                 if _thought_of(held.pending.command) == thought_id]
        if thought_id in self._resolved_thoughts.values():
            return None
        return found[0] if len(found) == 1 else None

    def withdrawing(self, issuer: str | None, which: Callable[[NormalizedCommand], bool]
                    ) -> list[PendingCommand]:
        """The held commands of `issuer` (None: of everyone) that `which` picks, to be
        withdrawn by the caller (`resolve`, each by its issuer), and no longer approved from
        this step on: an approval that comes before its withdrawal is refused
        `pending_not_found`, as one after it is. One past its TTL is left to expire; one
        being withdrawn already is not picked again (a second withdrawal would only be
        refused, and audited so, once the first took it)."""
        now, mono = now_ms(self._clock), self._clock.monotonic()
        picked = []
        for held in self._pending.list():
            pending = held.pending
            if (issuer is None or pending.issuer.name == issuer) and not held.withdrawing \
                    and not held.expired(now, mono) and which(pending.command):
                held.withdrawing = True
                picked.append(pending)
        return picked

    def credentials_ended(self) -> list[PendingCommand]:
        """The held commands whose issuer's credential has run out (`Held.credential_ended`),
        to be withdrawn by the caller as `withdrawing`'s are (`resolve`, by its issuer, with
        `CREDENTIAL_EXPIRED`), and no longer approved from this step on. One past its TTL is
        left to expire; one being withdrawn already is not picked again."""
        now, mono, wall = now_ms(self._clock), self._clock.monotonic(), self._latest.time()
        picked = []
        for held in self._pending.list():
            if not held.withdrawing and not held.expired(now, mono) \
                    and held.credential_ended(wall):
                held.withdrawing = True
                picked.append(held.pending)
        return picked

    async def hold(self, command: NormalizedCommand, principal: Principal,
                   approver_role: Role, stops: int | None = None,
                   estops: int | None = None) -> Decision:
        """`stops`: motion's robot-wide stops so far (`PendingCommand.stops`); `estops`: a
        clear's e-stops so far (`PendingCommand.estops`)."""
        due_mono = self._clock.monotonic() + self._ttl_ms / 1000
        pending = PendingCommand(
            pending_id=uuid.uuid4().hex, command=command, issuer=principal,
            approver_role=approver_role,
            expires_at_ms=now_ms(self._clock) + self._ttl_ms,
            approvals_required=self._policy.approvals(command.action), stops=stops,
            estops=estops,
        )
        entry = record(AuditEvent.PENDING_AUTH, command, principal, Outcome.PENDING_AUTH,
                       pending_id=pending.pending_id)
        receipt = await self._steps.audit.append(entry)
        # Only once its PENDING_AUTH entry is durable; its TTL counts from when it was held.
        self._pending.put(pending, due_mono)
        self._changed()
        if self._notifier is not None:
            self._steps.spawn(self._notifier.notify(pending.message()))  # never awaited here
        return Decision(outcome=Outcome.PENDING_AUTH, http_status=202,
                        audit_id=receipt.audit_id, message_id=command.message_id,
                        pending_id=pending.pending_id, expires_at_ms=pending.expires_at_ms)

    async def resolve(self, pending_id: str, reviewer: Principal, verdict: Verdict,
                      reason: str | None, said_by: ReviewMessage = NO_MESSAGE) -> Decision:
        """`said_by`: the AUTHORIZE message (§16.4) that said it, if one did: recorded with
        the review (and with a refusal of it)."""
        held = self._pending.get(pending_id)
        if held is None:
            return await self._refuse(verdict, reviewer, outcomes.PENDING_NOT_FOUND, pending_id,
                                      said_by)
        async with held.lock:  # one review at a time: each counted once, released once
            reviewed = await self._review(held, reviewer, verdict, reason, said_by)
        if isinstance(reviewed, Decision):
            return reviewed
        return await self._end(held, reviewed, reviewer, verdict)

    async def _end(self, held: Held, command: NormalizedCommand, reviewer: Principal,
                   verdict: Verdict) -> Decision:
        """Decides `held`, out of the store, as its last review says: `command` is it with
        every review so far."""
        pending = held.pending
        self._changed()
        self._resolving(held)  # readable as being decided, not as unknown, meanwhile
        try:
            decided = await self._decide(command, reviewer, pending, verdict)
        except BaseException:
            self._resolved.pop(pending.pending_id, None)  # never "being decided" for good
            self._resolved_thoughts.pop(pending.pending_id, None)
            self._never_ends(pending.pending_id)
            raise
        self._resolving(held, decided, command.approvals[-1] if command.approvals else None)
        return decided

    def _never_ends(self, pending_id: str) -> None:
        """Its review raised: what awaits its end is told so (its future cancelled)."""
        awaited = self._awaited.pop(pending_id, None)
        if awaited is not None:
            awaited.cancel()

    async def _decide(self, command: NormalizedCommand, reviewer: Principal,
                      pending: PendingCommand, verdict: Verdict) -> Decision:
        if verdict == "approve":
            return await self._run_approved(command, reviewer, pending)
        denied = verdict == "deny"
        return await self._steps.refuse(
            command, reviewer, outcomes.HITL_DENIED if denied else outcomes.HITL_WITHDRAWN,
            event=AuditEvent.HITL_DENIED if denied else AuditEvent.HITL_WITHDRAWN,
            pending_id=pending.pending_id)

    async def _review(self, held: Held, reviewer: Principal, verdict: Verdict,
                      reason: str | None, said_by: ReviewMessage
                      ) -> Decision | NormalizedCommand:
        """Under `held.lock`: refused, or counted (an approval of several: still pending), or
        taken from the store and returned with every review so far, to run or discard."""
        pending = held.pending
        if self._pending.get(pending.pending_id) is not held:  # resolved while this waited
            return await self._refuse(verdict, reviewer, outcomes.PENDING_NOT_FOUND,
                                      pending.pending_id, said_by)
        if held.withdrawing and verdict == "approve":  # its issuer withdraws it (`withdrawing`)
            return await self._refuse(verdict, reviewer, outcomes.PENDING_NOT_FOUND,
                                      pending.pending_id, said_by)
        if held.expired(now_ms(self._clock), self._clock.monotonic()):
            await self.expire()
            return await self._refuse(verdict, reviewer, outcomes.PENDING_EXPIRED,
                                      pending.pending_id, said_by)
        refused = self._may_review(held, reviewer, verdict)
        if refused is None:
            refused = _signed_for(held, said_by)
        if refused is not None:
            return await self._refuse(verdict, reviewer, refused, pending.pending_id, said_by)
        if verdict == "approve" and held.credential_ended(self._latest.time()):
            # An approver's, before the sweep came to it (a denial or a withdrawal ends it as
            # asked: nothing runs either way).
            await self._credential_expired(held)
            return await self._refuse(verdict, reviewer, outcomes.ISSUER_CREDENTIAL_EXPIRED,
                                      pending.pending_id, said_by)
        sig = None if said_by.rcan is None else said_by.rcan.get("sig")
        review = Approval(principal=reviewer.name, role=cast(RoleName, reviewer.role.name),
                          decision=verdict, at_ms=now_ms(self._clock), reason=reason,
                          message_id=said_by.message_id, sig=sig)
        if verdict == "approve" and held.missing > 1:
            return await self._count_approval(held, reviewer, review)
        self._pending.take(pending.pending_id)
        return held.reviewed(review)

    async def _credential_expired(self, held: Held) -> Decision:
        """Under `held.lock`: its issuer's credential ran out — withdrawn now, as its issuer's
        (HITL_WITHDRAWN, `CREDENTIAL_EXPIRED`), as the sweep would have."""
        issuer = held.pending.issuer
        review = Approval(principal=issuer.name, role=cast(RoleName, issuer.role.name),
                          decision="withdraw", at_ms=now_ms(self._clock),
                          reason=CREDENTIAL_EXPIRED)
        self._pending.take(held.pending.pending_id)
        return await self._end(held, held.reviewed(review), issuer, "withdraw")

    def _may_review(self, held: Held, reviewer: Principal, verdict: Verdict
                    ) -> Rejection | None:
        pending = held.pending
        issuer = reviewer.name == pending.issuer.name
        if reviewer.role < pending.approver_role and not (verdict == "withdraw" and issuer):
            return outcomes.privileges(f"to {verdict} it needs {pending.approver_role.name} or "
                                       "higher")
        if verdict != "approve":
            return None
        if issuer and (self._distinct or pending.approvals_required > 1):
            return outcomes.SELF_APPROVAL  # n-of-m: the issuer is never one of the n
        if held.approved_by(reviewer.name):
            return outcomes.ALREADY_APPROVED
        return None

    async def _count_approval(self, held: Held, approver: Principal,
                              review: Approval) -> Decision:
        """An approval while more are needed: on record (HITL_APPROVAL) before it counts."""
        pending = held.pending
        entry = record(AuditEvent.HITL_APPROVAL, held.reviewed(review), approver,
                       Outcome.PENDING_AUTH, pending_id=pending.pending_id)
        receipt = await self._steps.write_ahead(entry)
        if receipt is None:  # an approval that is not on record does not count
            return decision(outcomes.AUDIT_UNAVAILABLE, message_id=pending.command.message_id)
        held.approvals.append(review)
        self._changed()
        return Decision(outcome=Outcome.PENDING_AUTH, http_status=202,
                        audit_id=receipt.audit_id, message_id=pending.command.message_id,
                        pending_id=pending.pending_id, expires_at_ms=pending.expires_at_ms)

    async def refuse(self, verdict: Verdict, reviewer: Principal, rejection: Rejection,
                     pending_id: str, said_by: ReviewMessage = NO_MESSAGE) -> Decision:
        """A review refused before it reached the desk (its signature, say): audited as the
        desk's own refusals are."""
        return await self._refuse(verdict, reviewer, rejection, pending_id, said_by)

    async def _refuse(self, verdict: Verdict, reviewer: Principal, rejection: Rejection,
                      pending_id: str, said_by: ReviewMessage = NO_MESSAGE) -> Decision:
        verb = "hitl_authorize" if verdict == "approve" else f"hitl_{verdict}"
        entry = AuditRecord(event=AuditEvent.COMMAND_REJECTED, principal=reviewer.name,
                            role=reviewer.role.name, action_type=verb, pending_id=pending_id,
                            message_id=said_by.message_id, outcome=rejection.outcome.value,
                            deny_reason=rejection.deny_reason, rcan=said_by.rcan)
        return decision(rejection, await self._steps.audit.append(entry),
                        message_id=said_by.message_id)

    async def expire(self) -> list[Decision]:
        """Discard and audit (HITL_EXPIRED, with any approvals it had) every pending command
        past its TTL."""
        decisions = []
        expired = self._pending.take_expired(now_ms(self._clock), self._clock.monotonic())
        if expired:
            self._changed()
        for i, held in enumerate(expired):
            p = held.pending
            self._resolving(held)
            try:
                decisions.append(await self._steps.refuse(
                    held.reviewed(), p.issuer, outcomes.PENDING_EXPIRED,
                    event=AuditEvent.HITL_EXPIRED, pending_id=p.pending_id))
            except BaseException:  # (the sweeper cancelled as the bridge stops, say)
                for taken in expired[i:]:  # out of the store: nothing else would end them
                    self._never_ends(taken.pending.pending_id)
                raise
            self._resolving(held, decisions[-1])
        return decisions


def _signed_for(held: Held, said_by: ReviewMessage) -> Rejection | None:
    """A review in the SDK's envelope names the held command by its message_id as well as
    its pending_id: one that names another command reviews nothing (signed, its signer did
    not review this one)."""
    named = said_by.command_message_id
    # (a UUID in any spelling is that UUID, as the replay window reads ids; a command's own
    # message_id is kept in the canonical spelling)
    if named is None or normal_id(named) == held.pending.command.message_id:
        return None
    signed = said_by.rcan is not None and "sig" in said_by.rcan
    return outcomes.SIGNED_FOR_ANOTHER_COMMAND if signed else outcomes.NOT_THE_HELD_COMMAND


def _thought_of(command: NormalizedCommand) -> str | None:
    return command.ai.thought_id if command.ai is not None else None
