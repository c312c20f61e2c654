"""§12 RBAC: principals, authentication (tokens, EdDSA JWTs), required roles, rate limits."""

from __future__ import annotations

import base64
import binascii
import hashlib
import hmac
import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeGuard

import msgspec
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from rcan_rtps.config import ApiConfig, JwtConfig, RbacConfig
from rcan_rtps.rcan import Effect, Role
from rcan_rtps.rcan.actions import specs, with_effect

from .clock import Clock
from .errors import AuthConfigError, AuthenticationError

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
_MAX_JWT = 8192
_B64URL = re.compile(r"^[A-Za-z0-9_-]*$")


class Principal(msgspec.Struct, frozen=True):
    """An authenticated caller; its role comes from authentication only."""

    name: str
    role: Role
    rate_limit_per_min: int | None = None  # None: unlimited


def has_scope(role: Role, scope: str) -> bool:
    return role >= SCOPES[scope]


class RolePolicy:
    """Which role an action needs: the profile's table, with per-action overrides."""

    def __init__(self, overrides: Mapping[str, Role] | None = None) -> None:
        self._required = {**DEFAULT_ACTION_ROLES, **(overrides or {})}
        # Even a config cannot take the e-stop away from any authenticated principal.
        self._required[with_effect(Effect.ESTOP).name] = Role.GUEST

    def required(self, action: str) -> Role:
        return self._required[action]

    def allows(self, role: Role, action: str) -> bool:
        return role >= self._required[action]


# -- authentication -------------------------------------------------------------------------


def _digest(token: str) -> bytes:
    return hashlib.sha256(token.encode("utf-8")).digest()


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
        jwt = JwtVerifier.from_config(api.jwt, clock, limits) if api.jwt else None
        return cls(entries, jwt)

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


def _env_digest(name: str, env: Mapping[str, str]) -> bytes:
    token = env.get(name, "")
    if len(token.encode()) < MIN_TOKEN_BYTES:
        raise AuthConfigError(
            f"${name} must hold a token of at least {MIN_TOKEN_BYTES} bytes"
            + ("" if token else " (it is unset or empty)")
        )
    return _digest(token)


def rate_limits(rbac: RbacConfig) -> dict[Role, int | None]:
    limits = dict(DEFAULT_RATE_LIMITS)
    limits.update({Role[name]: value for name, value in rbac.rate_limits_per_min.items()})
    return limits


# -- EdDSA JWT ------------------------------------------------------------------------------


def _b64url(part: str) -> bytes:
    """Strict base64url without padding; a second spelling of the same bytes is refused."""
    if not _B64URL.fullmatch(part) or len(part) % 4 == 1:
        raise AuthenticationError("malformed JWT")
    try:
        raw = base64.urlsafe_b64decode(part + "=" * (-len(part) % 4))
    except (binascii.Error, ValueError) as exc:
        raise AuthenticationError("malformed JWT") from exc
    if base64.urlsafe_b64encode(raw).rstrip(b"=").decode() != part:
        raise AuthenticationError("malformed JWT")
    return raw


def _json_object(raw: bytes) -> dict[str, Any]:
    try:
        obj = msgspec.json.decode(raw)
    except (msgspec.DecodeError, UnicodeDecodeError) as exc:
        raise AuthenticationError("malformed JWT") from exc
    if not isinstance(obj, dict):
        raise AuthenticationError("malformed JWT")
    return obj


def _is_time(value: Any) -> TypeGuard[float]:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


class JwtVerifier:
    """Compact JWS with alg EdDSA (Ed25519) only; claims sub, role, exp, aud (iss, nbf)."""

    def __init__(self, key: Ed25519PublicKey, *, audience: str, clock: Clock,
                 issuer: str | None = None, leeway_s: float = 30.0,
                 limits: Mapping[Role, int | None] = DEFAULT_RATE_LIMITS) -> None:
        self._key = key
        self._audience = audience
        self._issuer = issuer
        self._leeway = leeway_s
        self._clock = clock
        self._limits = limits

    @classmethod
    def from_config(cls, cfg: JwtConfig, clock: Clock,
                    limits: Mapping[Role, int | None]) -> JwtVerifier:
        from cryptography.hazmat.primitives import serialization  # JWT configs only

        try:
            key = serialization.load_pem_public_key(Path(cfg.public_key).read_bytes())
        except (OSError, ValueError) as exc:
            raise AuthConfigError(f"cannot load JWT public key {cfg.public_key}: {exc}") from exc
        if not isinstance(key, Ed25519PublicKey):
            raise AuthConfigError(f"JWT public key {cfg.public_key} is not Ed25519")
        return cls(key, audience=cfg.audience, clock=clock, issuer=cfg.issuer,
                   leeway_s=cfg.leeway_s, limits=limits)

    def verify(self, token: str) -> Principal:
        if len(token) > _MAX_JWT:
            raise AuthenticationError("JWT too large")
        head_b64, body_b64, sig_b64 = token.split(".")
        header = _json_object(_b64url(head_b64))
        # Only EdDSA: "none", HMAC or RSA would let a forged or downgraded token through.
        if header.get("alg") != "EdDSA" or "crit" in header:
            raise AuthenticationError("JWT alg must be EdDSA")
        try:
            self._key.verify(_b64url(sig_b64), f"{head_b64}.{body_b64}".encode("ascii"))
        except InvalidSignature as exc:
            raise AuthenticationError("bad JWT signature") from exc
        return self._principal(_json_object(_b64url(body_b64)))

    def _principal(self, claims: dict[str, Any]) -> Principal:
        now = self._clock.time()
        exp, nbf = claims.get("exp"), claims.get("nbf")
        if not _is_time(exp) or now > exp + self._leeway:
            raise AuthenticationError("JWT expired or without exp")
        if nbf is not None and (not _is_time(nbf) or now + self._leeway < nbf):
            raise AuthenticationError("JWT not valid yet")
        aud = claims.get("aud")
        audiences = aud if isinstance(aud, list) else [aud]
        if self._audience not in audiences:
            raise AuthenticationError("JWT audience mismatch")
        if self._issuer is not None and claims.get("iss") != self._issuer:
            raise AuthenticationError("JWT issuer mismatch")
        sub, role = claims.get("sub"), claims.get("role")
        if not (isinstance(sub, str) and sub and isinstance(role, str)) or (
            role not in Role.__members__
        ):
            raise AuthenticationError("JWT needs a sub and a known role")
        return Principal(sub, Role[role], self._limits[Role[role]])


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
