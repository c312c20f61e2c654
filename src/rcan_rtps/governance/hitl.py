"""§9 human in the loop: gates, the pending store with TTL, and webhook notification.

A held command waits in the store (`Held`) with the reviews it has so far; its reviews are
decided one at a time (`Held.lock`), so approvals racing for the same command count once each
and release it once.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Mapping
from typing import Literal, Protocol, cast

import aiohttp
import msgspec

from rcan_rtps.config import HitlConfig, RbacConfig, issuer_roles
from rcan_rtps.rcan import Approval, NormalizedCommand, PendingAuth, Role, RoleName
from rcan_rtps.rcan.actions import specs

from . import outcomes
from .outcomes import Rejection
from .rbac import Principal

log = logging.getLogger(__name__)
# A human must never be needed to stop the robot: these actions are never gated.
NEVER_GATED = frozenset(s.name for s in specs() if not s.hitl.gateable)
Verdict = Literal["approve", "deny", "withdraw"]


class PendingCommand(msgspec.Struct, frozen=True, kw_only=True):
    pending_id: str
    command: NormalizedCommand
    issuer: Principal
    approver_role: Role
    expires_at_ms: int
    approvals_required: int = 1  # distinct approvers (`hitl.gates[].approvals`)
    # Motion only: the robot-wide stops so far (`VelocityStreams.stops`) when it was held. A
    # stop after that was a stop for it too: approved later, it is refused `stopped`.
    stops: int | None = None
    # clear_estop only: the e-stops that had arrived (`EstopMachine.arrived`) when it was held.
    # One after that is one it was not asked for: approved later, it is refused `estop_active`.
    estops: int | None = None

    def message(self, approvals: list[Approval] | None = None) -> PendingAuth:
        ai = self.command.ai
        return PendingAuth(
            pending_id=self.pending_id,
            original_command={"action": self.command.action, "params": self.command.requested,
                              "message_id": self.command.message_id},
            confidence=ai.confidence if ai else None,
            ai_model=ai.model if ai else None,
            requires_auth_from_role=cast(RoleName, self.approver_role.name),
            expires_at_ms=self.expires_at_ms,
            issued_by=self.issuer.name,
            approvals_required=self.approvals_required,
            approvals=list(approvals or ()),
            issuer_credential_ends_at_ms=self.credential_ends_at_ms(),
        )

    def credential_ends_at_ms(self) -> int | None:
        """When the issuer's credential ends (ms), if it does before the hold's TTL."""
        expires = self.issuer.expires_at
        if expires is None or expires * 1000 >= self.expires_at_ms:
            return None
        return math.floor(expires * 1000)


class Held:
    """A pending command in the store, with the approvals counted so far.

    `lock`: one review at a time (checked, audited, counted, maybe released), so two approvals
    racing cannot both count as the last one, nor one approver count twice."""

    def __init__(self, pending: PendingCommand, due_mono: float) -> None:
        self.pending = pending
        # Its TTL on the monotonic clock: a wall clock stepped back keeps no approval alive
        # past it (and one stepped forward past `expires_at_ms` expires it, as it says).
        self.due_mono = due_mono
        self.approvals: list[Approval] = []
        self.lock = asyncio.Lock()
        self.withdrawing = False  # its withdrawal is under way: no approval counts any more

    @property
    def missing(self) -> int:
        """Approvals still needed before it may run."""
        return self.pending.approvals_required - len(self.approvals)

    def expired(self, now_ms: int, now_mono: float) -> bool:
        """Past its TTL by either clock."""
        return self.pending.expires_at_ms <= now_ms or self.due_mono <= now_mono

    def credential_ended(self, wall_s: float) -> bool:
        """Whether its issuer's credential — the one it was held with: a JWT's `exp` plus the
        leeway, a client certificate's notAfter (`Principal.expires_at`) — has run out by
        `wall_s` (the latest wall time read, as the API judges it). A configured token's
        never does."""
        expires = self.pending.issuer.expires_at
        return expires is not None and expires <= wall_s

    def approved_by(self, name: str) -> bool:
        return any(a.principal == name for a in self.approvals)

    def reviewed(self, review: Approval | None = None) -> NormalizedCommand:
        """The command with its reviews so far (and `review`), as its audit entries show it."""
        reviews = (*self.approvals, review) if review is not None else tuple(self.approvals)
        return msgspec.structs.replace(self.pending.command, approvals=reviews)

    def message(self) -> PendingAuth:
        return self.pending.message(self.approvals)


class Escalate(msgspec.Struct, frozen=True):
    """The gate's answer: a human of at least `approver_role` must authorize."""

    approver_role: Role


class HitlPolicy:
    """Decides, per command, whether it passes, is refused, or waits for a human."""

    def __init__(self, config: HitlConfig, default_approver: Role = Role.OWNER,
                 roles_to_issue: Mapping[str, Role] | None = None) -> None:
        self._gate = config.confidence_gate
        self._default = default_approver
        # The role each action needs to be issued: no approver is below it (config refuses
        # a gate's role below it; the default approver is raised to it, per action).
        self._issuer_roles = dict(roles_to_issue or {})
        # Distinct approvers per action; whatever holds the command (a gate, the confidence gate).
        self._approvals = {g.action: g.approvals for g in config.gates}
        # The registry's defaults first; a configured gate for an action replaces its default.
        configured = {g.action for g in config.gates}
        self._actions: dict[str, Role] = {
            s.name: default_approver for s in specs()
            if s.hitl.gateable and s.hitl.required and s.name not in configured
        }
        self._actions.update({
            g.action: min((Role[r] for r in g.authorized_roles), default=default_approver)
            for g in config.gates if g.require_auth and g.action not in NEVER_GATED
        })

    @classmethod
    def from_config(cls, config: HitlConfig, rbac: RbacConfig) -> HitlPolicy:
        return cls(config, Role[rbac.hitl_approver_role], issuer_roles(rbac))

    def approver_role(self, action: str) -> Role:
        """Who may approve a held `action`: its gate's lowest authorized role, else the
        default approver; never below the role that may issue it — a lower one would release
        motion it may not command (a viewer approving an AI's arm move)."""
        configured = self._actions.get(action, self._default)
        issuer = self._issuer_roles.get(action, Role.GUEST)
        return issuer if issuer > configured else configured

    def approvals(self, action: str) -> int:
        """How many distinct approvers a held `action` needs."""
        return self._approvals.get(action, 1)

    def gate(self, command: NormalizedCommand) -> Rejection | Escalate | None:
        if command.action in NEVER_GATED:
            return None
        if self._gate is not None and command.ai is not None:
            # An AI command that states no confidence is treated as confidence 0.
            confidence = command.ai.confidence if command.ai.confidence is not None else 0.0
            if confidence < self._gate.min_confidence:
                if self._gate.on_fail == "block":
                    return outcomes.CONFIDENCE_BELOW_GATE
                return Escalate(self.approver_role(command.action))
        if command.action in self._actions:
            return Escalate(self.approver_role(command.action))
        return None


class PendingStore:
    """Commands waiting for a human; `take` removes, so one approval cannot run twice."""

    def __init__(self) -> None:
        self._pending: dict[str, Held] = {}

    def put(self, pending: PendingCommand, due_mono: float) -> Held:
        held = self._pending[pending.pending_id] = Held(pending, due_mono)
        return held

    def get(self, pending_id: str) -> Held | None:
        return self._pending.get(pending_id)

    def take(self, pending_id: str) -> Held | None:
        return self._pending.pop(pending_id, None)

    def take_expired(self, now_ms: int, now_mono: float) -> list[Held]:
        gone = [h for h in self._pending.values() if h.expired(now_ms, now_mono)]
        for h in gone:
            del self._pending[h.pending.pending_id]
        return gone

    def list(self) -> list[Held]:
        return sorted(self._pending.values(), key=lambda h: h.pending.expires_at_ms)

    def __len__(self) -> int:
        return len(self._pending)


class Notifier(Protocol):
    async def notify(self, message: PendingAuth) -> None: ...


class WebhookNotifier:
    """POSTs PENDING_AUTH as JSON; retries with backoff; each attempt has a timeout."""

    def __init__(self, url: str, *, attempts: int = 3, timeout_s: float = 5.0,
                 backoff_s: float = 0.5) -> None:
        self.url = url
        self.attempts = attempts
        self.timeout = aiohttp.ClientTimeout(total=timeout_s)
        self.backoff_s = backoff_s

    async def notify(self, message: PendingAuth) -> None:
        body = msgspec.json.encode(message)
        headers = {"Content-Type": "application/json"}
        async with aiohttp.ClientSession(timeout=self.timeout) as session:
            for attempt in range(1, self.attempts + 1):
                try:
                    async with session.post(self.url, data=body, headers=headers) as resp:
                        if resp.status < 300:
                            return
                        problem = f"HTTP {resp.status}"
                except (aiohttp.ClientError, asyncio.TimeoutError) as exc:
                    problem = repr(exc)
                log.warning("HiTL webhook attempt %d/%d failed: %s", attempt, self.attempts,
                            problem)
                if attempt < self.attempts:
                    await asyncio.sleep(self.backoff_s * 2 ** (attempt - 1))
        log.error("HiTL webhook gave up on pending %s", message.pending_id)
