"""Errors of the governance core.

    GovernanceError
    ├── AuthenticationError      no or invalid credentials (UNAUTHENTICATED)
    ├── AuthConfigError          principals cannot be set up (e.g. a token env var is unset)
    ├── EstopStateError          the e-stop state file cannot be written
    ├── EmptyPolicyError         a policy combinator built with nothing to check (a ValueError)
    ├── Violation                a command breaks a §8 safety invariant (`invariants`)
    └── AuditError
        ├── AuditIntegrityError  the chain is broken; names the first bad `seq`
        ├── AuditKeyError        the signing key is missing, unreadable or too open
        └── AuditWriteError      an append could not be made durable; the log refuses more
"""

from __future__ import annotations


class GovernanceError(Exception):
    """Base of every error raised by `rcan_rtps.governance`."""


class AuthenticationError(GovernanceError):
    """`reason`: a code a caller may be told (why a JWT is refused); None for a bad token,
    of which nothing is said."""

    error_code = "UNAUTHENTICATED"

    def __init__(self, message: str, *, reason: str | None = None) -> None:
        super().__init__(message)
        self.reason = reason


class AuthConfigError(GovernanceError):
    pass


class EstopStateError(GovernanceError):
    pass


class EmptyPolicyError(GovernanceError, ValueError):
    """A combinator with nothing in it: `AllOf()` would pass any command, `PerAction({})`
    refuse every one. Refused when built."""


class AuditError(GovernanceError):
    pass


class AuditIntegrityError(AuditError):
    def __init__(self, seq: int, detail: str, *, path: str = "") -> None:
        where = f"{path}: " if path else ""
        super().__init__(f"{where}audit chain broken at seq {seq}: {detail}")
        self.seq = seq
        self.detail = detail
        self.path = path


class AuditKeyError(AuditError):
    pass


class AuditWriteError(AuditError):
    pass
