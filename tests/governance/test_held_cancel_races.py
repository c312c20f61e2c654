"""Seeded random interleavings of a cancelled motion call's withdrawal of held motion
(`Governor.command_cancelled`) with holds, approvals (n-of-m, and an issuer approving its
own), denials, withdrawals, TTLs passing, expiry sweeps and an e-stop.

What must hold whatever the order: a held motion command of the cancelling principal's that
still waited (not past its TTL) when the cancel came never runs; nobody else's held command,
and none that is not motion, is withdrawn by it; each held command ends once; nothing ends
in an error or a 5xx; no motion reaches the robot once the e-stop latched; the signed audit
chain verifies."""

from __future__ import annotations

import asyncio
import random
from collections.abc import Awaitable, Callable
from typing import Any

import pytest
from govhelpers import ADMIN, OPS, PLANNER, Harness, command, principal

from rcan_rtps.governance.audit import verify
from rcan_rtps.governance.governor import CANCELLED_BY_CLIENT, Governor
from rcan_rtps.governance.rbac import Principal
from rcan_rtps.rcan import Role
from rcan_rtps.rcan.actions import specs

OTHER = principal("other", Role.USER)
OPS2 = principal("ops2", Role.OWNER)
ISSUERS = (PLANNER, OTHER)
REVIEWERS = (OPS, OPS2, ADMIN, PLANNER, OTHER)
# arm_joint: two distinct OWNER approvals; navigate: one USER's, its issuer's own counts;
# lock: held too, and no motion.
GATES = ("[{action: arm_joint, require_auth: true, approvals: 2, authorized_roles: [OWNER]}, "
         "{action: navigate, require_auth: true, authorized_roles: [USER]}, "
         "{action: lock, require_auth: true, authorized_roles: [OWNER]}]")
HELD = {"arm_joint": {"joints": ["shoulder"], "positions": [0.1], "duration_s": 2.0},
        "navigate": {"x": 1.0, "y": 2.0, "yaw": 0.0},
        "lock": {"name": "teleop"}}
MOTION = frozenset(s.name for s in specs() if s.motion)
TTL_S = 300
ENDS = {"HITL_AUTHORIZED", "HITL_DENIED", "HITL_WITHDRAWN", "HITL_EXPIRED"}


class Trial:
    """One interleaving: the operations it started, and what each cancel found held."""

    def __init__(self, gov: Governor, harness: Harness, rng: random.Random) -> None:
        self.gov, self.harness, self.rng = gov, harness, rng
        self.ids: list[str] = []
        self.issuer: dict[str, str] = {}
        self.action: dict[str, str] = {}
        self.must_not_run: set[str] = set()
        self.estopped_at: int | None = None  # dispatcher calls before the e-stop latched

    async def hold(self, who: Principal, action: str) -> Any:
        decided = await self.gov.decide(command(action, HELD[action]), who)
        if decided.pending_id is not None:
            self.ids.append(decided.pending_id)
            self.issuer[decided.pending_id] = who.name
            self.action[decided.pending_id] = action
        return decided

    def some_id(self) -> str:
        return self.rng.choice(self.ids) if self.ids else "0" * 32

    async def cancel(self, who: Principal) -> Any:
        # What waits for a human now, its and motion, not past its TTL, must never run.
        now = int(self.harness.clock.time() * 1000)
        self.must_not_run |= {p.pending_id for p in self.gov.pending()
                              if p.issued_by == who.name and p.expires_at_ms > now
                              and p.original_command["action"] in MOTION}
        return await self.gov.command_cancelled(who)

    async def estop(self) -> Any:
        stopping = self.gov.decide(command("estop", {"reason": "race"}), ADMIN)
        decided = await stopping
        if self.estopped_at is None:
            self.estopped_at = len(self.harness.dispatcher.calls)
        return decided

    async def age(self) -> Any:
        self.harness.clock.advance(self.rng.choice((1, TTL_S / 2, TTL_S)))
        return await self.gov.expire_pending()

    def operation(self) -> Callable[[], Awaitable[Any]]:
        rng = self.rng
        kind = rng.choices(["hold", "approve", "deny", "withdraw", "cancel", "age", "estop"],
                           weights=[4, 6, 1, 1, 3, 1, 0.1])[0]
        if kind == "hold":
            who, action = rng.choice(ISSUERS), rng.choice(sorted(HELD))
            return lambda: self.hold(who, action)
        if kind == "approve":
            approver = rng.choice(REVIEWERS)
            return lambda: self.gov.authorize(self.some_id(), approver)
        if kind == "deny":
            return lambda: self.gov.deny(self.some_id(), rng.choice((OPS, ADMIN)))
        if kind == "withdraw":
            return lambda: self.gov.withdraw(self.some_id(), rng.choice(ISSUERS))
        if kind == "cancel":
            who = rng.choice(ISSUERS)
            return lambda: self.cancel(who)
        if kind == "age":
            return self.age
        return self.estop

    async def run(self, rounds: int) -> list[Any]:
        async def later(op: Callable[[], Awaitable[Any]], yields: int) -> Any:
            for _ in range(yields):
                await asyncio.sleep(0)
            return await op()

        outcomes: list[Any] = []
        for _ in range(rounds):
            batch = [asyncio.ensure_future(later(self.operation(), self.rng.randrange(6)))
                     for _ in range(self.rng.randrange(1, 6))]
            outcomes += await asyncio.gather(*batch, return_exceptions=True)
        return outcomes


def _ended(entries: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    ends: dict[str, list[dict[str, Any]]] = {}
    for e in entries:
        if e["event"] in ENDS and e.get("pending_id"):
            ends.setdefault(e["pending_id"], []).append(e)
    return ends


@pytest.mark.parametrize("seed", range(40))
async def test_withdrawals_of_cancelled_motion_race_reviews_safely(harness: Harness,
                                                                  seed: int) -> None:
    gov = await harness.governor(gates=GATES)
    trial = Trial(gov, harness, random.Random(seed))
    outcomes = await trial.run(rounds=16)
    harness.clock.advance(TTL_S + 1)  # what still waits expires: every held command ends
    outcomes += await gov.expire_pending()
    await asyncio.gather(*gov._tasks)
    errors = [o for o in outcomes if isinstance(o, BaseException)]
    assert errors == [], errors
    decisions = [d for o in outcomes for d in (o if isinstance(o, list) else [o])
                 if d is not None]
    assert [d for d in decisions if d.http_status >= 500] == []
    entries = harness.entries
    ends = _ended(entries)
    for pending_id in trial.ids:
        assert len(ends.get(pending_id, [])) == 1, (pending_id, ends.get(pending_id))
        assert gov.pending_record(pending_id).state == "resolved"  # type: ignore[union-attr]
    ran = {p for p, (e,) in ends.items()
           if e["event"] == "HITL_AUTHORIZED" and e["outcome"] == "executed"}
    assert ran & trial.must_not_run == set(), seed
    for pending_id, (end,) in ends.items():
        reasons = [a.get("reason") for a in end.get("approvals") or ()]
        if CANCELLED_BY_CLIENT in reasons:
            assert end["event"] == "HITL_WITHDRAWN"
            assert end["principal"] == trial.issuer[pending_id]
            assert trial.action[pending_id] in MOTION
    if trial.estopped_at is not None:
        after = [a for a, _ in harness.dispatcher.calls[trial.estopped_at:]]
        assert [a for a in after if a in MOTION] == []
    await gov.stop()
    verify(harness.tmp / "audit.jsonl", gov.audit.public_key)
