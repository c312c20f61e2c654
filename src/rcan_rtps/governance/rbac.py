"""§12 RBAC: principals, authentication (tokens; EdDSA JWTs in `jwt`), required roles, rate
limits."""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Mapping
from typing import TYPE_CHECKING

import msgspec

from rcan_rtps.config import ApiConfig, RbacConfig, issuer_roles
from rcan_rtps.rcan import Effect, Role
from rcan_rtps.rcan.actions import specs, with_effect

from .clock import Clock
from .errors import AuthConfigError, AuthenticationError

if TYPE_CHECKING:
    from .jwt import JwtVerifier

SCOPES: Mapping[str, Role] = {
    "status": Role.GUEST,
    "control": Role.USER,
    "config": Role.LEASEE,
    "training": Role.OWNER,
    "admin": Role.CREATOR,
}
DEFAULT_ACTION_ROLES: Mapping[str, Role] = {s.name: s.default_role for s in specs()}
DEFAULT_RATE_LIMITS: Mapping[Role, int | None] = {
    Role.GUEST: 10,
    Role.USER: 100,
    Role.LEASEE: 500,
    Role.OWNER: 1000,
    Role.CREATOR: None,
}
MIN_TOKEN_BYTES = 16


class Principal(msgspec.Struct, frozen=True):
    """An authenticated caller; its role comes from authentication only."""

    name: str
    role: Role
    rate_limit_per_min: int | None = None  # None: unlimited
    # Wall time (Unix s) from which its credential is refused — a JWT's `exp` plus the leeway,
    # a client certificate's notAfter — or None (a configured token). What outlives one
    # request (a WebSocket, a kept-alive TLS connection) must not outlive it.
    expires_at: float | None = None


def has_scope(role: Role, scope: str) -> bool:
    return role >= SCOPES[scope]


class RolePolicy:
    """Which role an action needs: the profile's table, with per-action overrides."""

    def __init__(self, overrides: Mapping[str, Role] | None = None) -> None:
        self._required = {**DEFAULT_ACTION_ROLES, **(overrides or {})}
        # Even a config cannot take the e-stop away from any authenticated principal.
        self._required[with_effect(Effect.ESTOP).name] = Role.GUEST

    @classmethod
    def from_config(cls, rbac: RbacConfig) -> RolePolicy:
        return cls(issuer_roles(rbac))

    def required(self, action: str) -> Role:
        return self._required[action]

    def allows(self, role: Role, action: str) -> bool:
        return role >= self._required[action]

    def refuses(self, role: Role, action: str) -> bool:
        """Whether `role` certainly may not issue `action`: False for an action this policy
        does not know (`allows` cannot say, so nothing is certain)."""
        required = self._required.get(action)
        return required is not None and role < required


# -- authentication -------------------------------------------------------------------------


def _bytes(token: str) -> bytes:
    """The token's bytes as sent: aiohttp (and os.environ) keep bytes that are not UTF-8 as
    surrogate escapes, which plain UTF-8 cannot encode (a 500 with a traceback, not a 401)."""
    return token.encode("utf-8", "surrogateescape")


def _digest(token: str) -> bytes:
    return hashlib.sha256(_bytes(token)).digest()


class TokenAuthenticator:
    """Bearer tokens, compared as SHA-256 digests in constant time against every principal."""

    def __init__(self, principals: list[tuple[Principal, bytes]],
                 jwt: JwtVerifier | None = None) -> None:
        self._principals = principals
        self._jwt = jwt

    @classmethod
    def from_config(cls, api: ApiConfig, rbac: RbacConfig, env: Mapping[str, str], *,
                    clock: Clock) -> TokenAuthenticator:
        limits = rate_limits(rbac)
        entries: list[tuple[Principal, bytes]] = []
        for p in api.principals:
            role = Role[p.role]
            limit = p.rate_limit_per_min if p.rate_limit_per_min else limits[role]
            digest = _env_digest(p.token_env, env) if p.token_env else bytes.fromhex(
                p.token_sha256 or "")
            entries.append((Principal(p.name, role, limit), digest))
        if not api.principals and api.auth_token_env:
            digest = _env_digest(api.auth_token_env, env)
            entries.append((Principal("default", Role.OWNER, limits[Role.OWNER]), digest))
        shared = shared_token_problem(api, env)
        if shared is not None:
            raise AuthConfigError(shared)
        if api.jwt is None:
            return cls(entries)
        from .jwt import JwtVerifier  # only a JWT config needs it

        return cls(entries, JwtVerifier.from_config(api.jwt, clock, limits))

    def authenticate(self, bearer: str | None) -> Principal:
        if not bearer:
            raise AuthenticationError("no credentials")
        if self._jwt is not None and bearer.count(".") == 2:
            return self._jwt.verify(bearer)
        presented = _digest(bearer)
        found: Principal | None = None
        for principal, digest in self._principals:  # no early exit: timing says nothing
            if hmac.compare_digest(presented, digest):
                found = principal
        if found is None:
            raise AuthenticationError("invalid credentials")
        return found


def shared_token_problem(api: ApiConfig, env: Mapping[str, str]) -> str | None:
    """Two principals one token authenticates (one variable named twice, two holding the same
    value, or a variable's token whose digest another's `token_sha256` is): `authenticate`
    would pick one of them — the roles may differ — so a start refuses. Unset variables are
    left to the check that reports them."""
    holders: dict[bytes, str] = {}
    for p in api.principals:
        if p.token_env:
            token = env.get(p.token_env)
            if not token:
                continue
            digest, source = _digest(token), f"${p.token_env}"
        else:
            digest, source = bytes.fromhex(p.token_sha256 or ""), "its token_sha256"
        mine = f"{p.name} ({source})"
        other = holders.setdefault(digest, mine)
        if other != mine:
            return (f"principals {other} and {mine} have the same token: who presents it "
                    "would be either; give each its own")
    return None


def _env_digest(name: str, env: Mapping[str, str]) -> bytes:
    token = env.get(name, "")
    if len(_bytes(token)) < MIN_TOKEN_BYTES:
        raise AuthConfigError(
            f"${name} must hold a token of at least {MIN_TOKEN_BYTES} bytes"
            + ("" if token else " (it is unset or empty)")
        )
    return _digest(token)


def rate_limits(rbac: RbacConfig) -> dict[Role, int | None]:
    limits = dict(DEFAULT_RATE_LIMITS)
    limits.update({Role[name]: value for name, value in rbac.rate_limits_per_min.items()})
    return limits


# -- rate limits ----------------------------------------------------------------------------


class RateLimiter:
    """A token bucket per principal: `limit` requests a minute, refilled continuously."""

    def __init__(self, clock: Clock) -> None:
        self._clock = clock
        self._buckets: dict[str, tuple[float, float]] = {}  # name -> (tokens, at)

    def allow(self, principal: Principal) -> bool:
        limit = principal.rate_limit_per_min
        if limit is None:
            return True
        now = self._clock.monotonic()
        tokens, at = self._buckets.get(principal.name, (float(limit), now))
        tokens = min(float(limit), tokens + (now - at) * limit / 60.0)
        if tokens < 1.0:
            self._buckets[principal.name] = (tokens, now)
            return False
        self._buckets[principal.name] = (tokens - 1.0, now)
        return True
