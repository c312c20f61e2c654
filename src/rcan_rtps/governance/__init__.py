"""The governance core: §12 RBAC, §8 invariants, §9 HiTL, §6 signed audit chain.

Imports no DDS. The bridge plugs in through `Dispatcher`; everything reaches the robot through
`Governor.decide`, which leaves exactly one decisive audit entry per command.

Public API: the governor (`Governor`, `Dispatcher`, `Decision`); policies (`RolePolicy`,
`RateLimiter`, `HitlPolicy`, and the safety checks `AllOf`, `PerAction`, `EstopGuard`,
`VelocityLimit`, `Workspace`, `finite_numbers`, built from config by `safety_policy`); the audit log
(`AuditLog`) and its verification (`verify`, `verify_bytes`); `GovernanceError` and its tree
(see `errors`).
"""

import typing as _typing

from .audit import (
    GENESIS,
    AuditEvent,
    AuditLog,
    AuditReceipt,
    AuditRecord,
    ChainHead,
    load_or_create_key,
    load_private_key,
    load_public_key,
    public_key_pem,
    verify,
    verify_bytes,
)
from .clock import Clock, ManualClock, SystemClock
from .errors import (
    AuditError,
    AuditIntegrityError,
    AuditKeyError,
    AuditWriteError,
    AuthConfigError,
    AuthenticationError,
    EmptyPolicyError,
    EstopStateError,
    GovernanceError,
)
from .estop import EstopMachine, LatchFile
from .governor import ArmsHeld, Decision, Dispatcher, DispatchResult, Governor
from .hitl import HitlPolicy, Notifier, PendingCommand, WebhookNotifier
from .idempotency import Idempotency
from .invariants import (
    AllOf,
    Check,
    EstopGuard,
    PerAction,
    VelocityLimit,
    Violation,
    Workspace,
    finite_numbers,
    safety_policy,
)
from .outcomes import Rejection
from .rbac import (
    DEFAULT_ACTION_ROLES,
    DEFAULT_RATE_LIMITS,
    SCOPES,
    Principal,
    RateLimiter,
    RolePolicy,
    TokenAuthenticator,
    has_scope,
)

if _typing.TYPE_CHECKING:
    from .jwt import JwtVerifier


def __getattr__(name: str) -> _typing.Any:
    # JwtVerifier, with its module, only when asked for: a bridge without `bridge.api.jwt`
    # never needs it (issue 27: idle memory).
    if name == "JwtVerifier":
        from .jwt import JwtVerifier

        return JwtVerifier
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "DEFAULT_ACTION_ROLES",
    "DEFAULT_RATE_LIMITS",
    "GENESIS",
    "SCOPES",
    "AllOf",
    "ArmsHeld",
    "AuditError",
    "AuditEvent",
    "AuditIntegrityError",
    "AuditKeyError",
    "AuditLog",
    "AuditReceipt",
    "AuditRecord",
    "AuditWriteError",
    "AuthConfigError",
    "AuthenticationError",
    "ChainHead",
    "Check",
    "Clock",
    "Decision",
    "DispatchResult",
    "Dispatcher",
    "EmptyPolicyError",
    "EstopGuard",
    "EstopMachine",
    "EstopStateError",
    "GovernanceError",
    "Governor",
    "HitlPolicy",
    "Idempotency",
    "JwtVerifier",
    "LatchFile",
    "ManualClock",
    "Notifier",
    "PendingCommand",
    "PerAction",
    "Principal",
    "RateLimiter",
    "Rejection",
    "RolePolicy",
    "SystemClock",
    "TokenAuthenticator",
    "VelocityLimit",
    "Violation",
    "WebhookNotifier",
    "Workspace",
    "finite_numbers",
    "has_scope",
    "load_or_create_key",
    "load_private_key",
    "load_public_key",
    "public_key_pem",
    "safety_policy",
    "verify",
    "verify_bytes",
]
