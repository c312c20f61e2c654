"""The governance core: §12 RBAC, §8 invariants, §9 HiTL, §6 signed audit chain.

Imports no DDS. The bridge plugs in through `Dispatcher`; everything reaches the robot through
`Governor.decide`, which leaves exactly one decisive audit entry per command.
"""

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
    EstopStateError,
    GovernanceError,
)
from .estop import EstopMachine, LatchFile
from .governor import Decision, Dispatcher, DispatchResult, Governor
from .hitl import HitlPolicy, Notifier, PendingCommand, WebhookNotifier
from .idempotency import Idempotency
from .invariants import AllOf, Violation, safety_policy
from .outcomes import Rejection
from .rbac import (
    DEFAULT_ACTION_ROLES,
    DEFAULT_RATE_LIMITS,
    SCOPES,
    JwtVerifier,
    Principal,
    RateLimiter,
    RolePolicy,
    TokenAuthenticator,
    has_scope,
)

__all__ = [
    "DEFAULT_ACTION_ROLES",
    "DEFAULT_RATE_LIMITS",
    "GENESIS",
    "SCOPES",
    "AllOf",
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
    "Clock",
    "Decision",
    "DispatchResult",
    "Dispatcher",
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
    "Principal",
    "RateLimiter",
    "Rejection",
    "RolePolicy",
    "SystemClock",
    "TokenAuthenticator",
    "Violation",
    "WebhookNotifier",
    "has_scope",
    "load_or_create_key",
    "load_private_key",
    "load_public_key",
    "public_key_pem",
    "safety_policy",
    "verify",
    "verify_bytes",
]
