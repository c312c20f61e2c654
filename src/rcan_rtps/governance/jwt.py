"""§12 authentication by EdDSA JWT (`bridge.api.jwt`): compact JWS, Ed25519 keys (a PEM key or
a JWKS), claims checked against the config.

Imported by `rbac.TokenAuthenticator` only when the config names a JWT key: a bridge with
bearer tokens alone never loads it (issue 27: idle memory).
"""

from __future__ import annotations

import base64
import binascii
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeGuard

import msgspec
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from rcan_rtps.config import JwtConfig
from rcan_rtps.rcan import JWT_LEVELS, M2M_TRUSTED, M2M_TRUSTED_LEVEL, Role

from ._durable import read_trusted
from .clock import Clock, latest_wall
from .errors import AuthConfigError, AuthenticationError
from .keyfacts import read_public_pem
from .rbac import DEFAULT_RATE_LIMITS, Principal

_MAX_JWT = 8192
MAX_JWKS_BYTES = 1024 * 1024  # a key set of thousands of keys: larger is none
_B64URL = re.compile(r"^[A-Za-z0-9_-]*$")
JWT_PREFIX = "jwt:"
DEFAULT_MAX_JWT_LIFETIME_S = 86400.0
_MAX_CLAIM_CHARS = 256  # iss and sub: names that end up in every log line and audit entry


def jwt_principal_name(issuer: str | None, subject: str) -> str:
    """The principal a JWT names: `jwt:<iss>/<sub>` (`jwt:/<sub>` without `iss`).

    Never a configured principal's name (those cannot hold `:`), and one (iss, sub) pair per
    name: `%` (and `/` in the issuer) and anything unprintable are percent-escaped as UTF-8,
    so the first `/` ends the issuer and no escape can be mistaken for a literal character.
    An unprintable character (a newline, a bidi override) never reaches a log line raw.
    """
    return f"{JWT_PREFIX}{_escape(issuer or '', '%/')}/{_escape(subject, '%')}"


def _escape(text: str, reserved: str) -> str:
    return "".join(c if c.isprintable() and c not in reserved else _percent(c) for c in text)


def _percent(char: str) -> str:
    return "".join(f"%{b:02X}" for b in char.encode("utf-8", "surrogatepass"))


# Why a JWT is refused, as the 401's `reason` (the message goes in WWW-Authenticate).
MALFORMED = "jwt_malformed"  # not a compact EdDSA JWS of JSON objects
BAD_SIGNATURE = "jwt_bad_signature"
UNKNOWN_KID = "jwt_unknown_kid"  # JWKS keys: no kid, or one the file does not hold
EXPIRED = "jwt_expired"  # or without exp
NOT_YET = "jwt_not_yet_valid"  # nbf or iat in the future
TOO_LONG = "jwt_lifetime_too_long"  # exp more than max_lifetime_s after iat (or now)
CLAIMS = "jwt_claims"  # aud, iss, sub or role
M2M_TRUSTED_REFUSED = "jwt_m2m_trusted_not_configured"  # see JwtConfig.m2m_trusted_role


def _refused(reason: str, message: str) -> AuthenticationError:
    return AuthenticationError(message, reason=reason)


def _b64url_or_none(part: str) -> bytes | None:
    """Strict base64url without padding; None for anything else, including a second
    spelling of the same bytes."""
    if not _B64URL.fullmatch(part) or len(part) % 4 == 1:
        return None
    try:
        raw = base64.urlsafe_b64decode(part + "=" * (-len(part) % 4))
    except (binascii.Error, ValueError):
        return None
    return raw if base64.urlsafe_b64encode(raw).rstrip(b"=").decode() == part else None


def _b64url(part: str) -> bytes:
    raw = _b64url_or_none(part)
    if raw is None:
        raise _refused(MALFORMED, "malformed JWT")
    return raw


def _json_object(raw: bytes) -> dict[str, Any]:
    try:
        obj = msgspec.json.decode(raw)
    except (msgspec.DecodeError, UnicodeDecodeError) as exc:
        raise _refused(MALFORMED, "malformed JWT") from exc
    if not isinstance(obj, dict):
        raise _refused(MALFORMED, "malformed JWT")
    return obj


_MAGNITUDE = 1e15  # past any time in s (year 31 million) and any role level


def _is_time(value: Any) -> TypeGuard[float]:
    """A number (not a bool) of a magnitude a time or a level can have: compared, never
    converted (`math.isfinite` of a JSON integer of 400 digits overflowed: a 500); NaN and
    the infinities fail the comparison."""
    return (isinstance(value, int | float) and not isinstance(value, bool)
            and -_MAGNITUDE < value < _MAGNITUDE)


# One PEM key (a token's `kid` is not looked at), or a JWKS's keys by `kid`.
JwtKeys = Ed25519PublicKey | Mapping[str, Ed25519PublicKey]


def load_pem_key(path: str) -> Ed25519PublicKey:
    try:
        return read_public_pem(path, trusted=True)
    except ValueError as exc:
        raise AuthConfigError(f"{exc} (the JWT public key)") from exc


def load_jwks(path: str) -> dict[str, Ed25519PublicKey]:
    """An RFC 7517 key set of Ed25519 public keys (RFC 8037 `OKP`), each with its own `kid`."""
    try:
        # (read_small: a FIFO there held the start for a writer that never came)
        doc = msgspec.json.decode(read_trusted(Path(path), MAX_JWKS_BYTES))
    except (OSError, ValueError, msgspec.DecodeError) as exc:
        raise AuthConfigError(f"cannot load JWKS {path}: {exc}") from exc
    keys = doc.get("keys") if isinstance(doc, dict) else None
    if not isinstance(keys, list) or not keys:
        raise AuthConfigError(f"JWKS {path}: needs a non-empty `keys` list")
    found: dict[str, Ed25519PublicKey] = {}
    for index, jwk in enumerate(keys):
        where = f"JWKS {path}: keys[{index}]"
        kid, key = _jwk(jwk, where)
        if kid in found:
            raise AuthConfigError(f"{where}: kid {kid!r} is used twice")
        found[kid] = key
    return found


def _jwk(jwk: Any, where: str) -> tuple[str, Ed25519PublicKey]:
    if not isinstance(jwk, dict):
        raise AuthConfigError(f"{where}: is not a JSON object")
    problem = _jwk_problem(jwk)
    if problem is not None:
        raise AuthConfigError(f"{where}: {problem}")
    return jwk["kid"], Ed25519PublicKey.from_public_bytes(_b64url_or_none(jwk["x"]) or b"")


def _jwk_problem(jwk: dict[str, Any]) -> str | None:
    kid, x = jwk.get("kid"), jwk.get("x")
    if not (isinstance(kid, str) and kid):
        return "needs a `kid` (a non-empty string): tokens choose their key by it"
    if (jwk.get("kty"), jwk.get("crv")) != ("OKP", "Ed25519"):
        return "is not an Ed25519 key (`kty` OKP, `crv` Ed25519)"
    if "d" in jwk:
        return "holds a private key (`d`): the bridge needs public keys only"
    if jwk.get("use", "sig") != "sig" or jwk.get("alg", "EdDSA") not in ("EdDSA", "Ed25519"):
        return "is not a signing key for EdDSA (`use`, `alg`)"
    ops = jwk.get("key_ops", ["verify"])
    if not (isinstance(ops, list) and "verify" in ops):
        # RFC 7517 §4.3: a key whose operations leave out `verify` is not for checking tokens
        return "is not a key for verifying (`key_ops` without \"verify\")"
    raw = _b64url_or_none(x) if isinstance(x, str) else None
    if raw is None or len(raw) != 32:
        return "`x` must be the 32-byte public key, base64url without padding"
    return None


class JwtVerifier:
    """Compact JWS with alg EdDSA (Ed25519) only; claims sub, role, exp, aud (iss, iat, nbf).

    A token lives at most `max_lifetime_s` (from `iat`, else from now); its principal is
    `jwt_principal_name(iss, sub)`, never a configured principal.
    """

    def __init__(self, keys: JwtKeys, *, audience: str, clock: Clock,
                 issuer: str | None = None, leeway_s: float = 30.0,
                 max_lifetime_s: float = DEFAULT_MAX_JWT_LIFETIME_S,
                 limits: Mapping[Role, int | None] = DEFAULT_RATE_LIMITS,
                 m2m_trusted_role: Role | None = None) -> None:
        self._keys = keys
        self._m2m_trusted = m2m_trusted_role
        self._audience = audience
        self._issuer = issuer
        self._leeway = leeway_s
        self._max_lifetime = max_lifetime_s
        self._clock = clock
        # exp is judged by the latest wall time read: a token that expired stays expired
        # when the clock is stepped back (nbf and iat by the clock now).
        self._latest = latest_wall(clock)
        self._limits = limits

    @classmethod
    def from_config(cls, cfg: JwtConfig, clock: Clock,
                    limits: Mapping[Role, int | None]) -> JwtVerifier:
        keys: JwtKeys = load_jwks(cfg.jwks) if cfg.jwks else load_pem_key(cfg.public_key or "")
        trusted = Role[cfg.m2m_trusted_role] if cfg.m2m_trusted_role else None
        return cls(keys, audience=cfg.audience, clock=clock, issuer=cfg.issuer,
                   leeway_s=cfg.leeway_s, max_lifetime_s=cfg.max_lifetime_s, limits=limits,
                   m2m_trusted_role=trusted)

    def verify(self, token: str) -> Principal:
        if len(token) > _MAX_JWT:
            raise _refused(MALFORMED, "JWT too large")
        head_b64, body_b64, sig_b64 = token.split(".")
        header = _json_object(_b64url(head_b64))
        # Only EdDSA: "none", HMAC or RSA would let a forged or downgraded token through.
        if header.get("alg") != "EdDSA" or "crit" in header:
            raise _refused(MALFORMED, "JWT alg must be EdDSA")
        try:
            self._key(header).verify(_b64url(sig_b64), f"{head_b64}.{body_b64}".encode("ascii"))
        except InvalidSignature as exc:
            raise _refused(BAD_SIGNATURE, "bad JWT signature") from exc
        return self._principal(_json_object(_b64url(body_b64)))

    def _key(self, header: dict[str, Any]) -> Ed25519PublicKey:
        if isinstance(self._keys, Ed25519PublicKey):
            return self._keys
        kid = header.get("kid")
        if not isinstance(kid, str):
            raise _refused(UNKNOWN_KID, "JWT header needs a kid (the keys are a JWKS)")
        key = self._keys.get(kid)
        if key is None:
            raise _refused(UNKNOWN_KID, "JWT kid is not in the JWKS")
        return key

    def _principal(self, claims: dict[str, Any]) -> Principal:
        self._check_times(claims)
        aud = claims.get("aud")
        audiences = aud if isinstance(aud, list) else [aud]
        if self._audience not in audiences:
            raise _refused(CLAIMS, "JWT audience mismatch")
        iss, sub = claims.get("iss"), claims.get("sub")
        if iss is not None and not _is_name(iss):
            raise _refused(CLAIMS, f"JWT iss must be a string of 1-{_MAX_CLAIM_CHARS} chars")
        if self._issuer is not None and iss != self._issuer:
            raise _refused(CLAIMS, "JWT issuer mismatch")
        if not _is_name(sub):
            raise _refused(CLAIMS, f"JWT needs a sub (1-{_MAX_CLAIM_CHARS} chars)")
        role = self._role(claims.get("role"), claims.get("rcan_role"))
        return Principal(jwt_principal_name(iss, sub), role, self._limits[role],
                         expires_at=float(claims["exp"]) + self._leeway)

    def _role(self, name: Any, level: Any) -> Role:
        """The role a token states: `role` (a name, the profile's or RCAN v2's) and/or
        `rcan_role` (an RCAN v2 level, rcan.identity.ROLE_TO_JWT_LEVEL); both must agree."""
        by_name = by_level = None
        if name is not None:
            by_name = self._named(name)
        if level is not None:
            by_level = self._leveled(level)
        if by_name is None and by_level is None:
            raise _refused(CLAIMS, "JWT needs a role (role or rcan_role)")
        if by_name is not None and by_level is not None and by_name is not by_level:
            raise _refused(CLAIMS, f"JWT role {name!r} and rcan_role {level!r} disagree")
        found = by_name if by_name is not None else by_level
        assert found is not None
        return found

    def _named(self, name: Any) -> Role:
        if name == M2M_TRUSTED:
            return self._trusted()
        if not isinstance(name, str) or name not in Role.__members__:
            raise _refused(CLAIMS, "JWT role is not a known role")
        return Role[name]

    def _leveled(self, level: Any) -> Role:
        if not _is_time(level):  # a finite number (not a bool)
            raise _refused(CLAIMS, "JWT rcan_role must be a number")
        if float(level) == M2M_TRUSTED_LEVEL:
            return self._trusted()
        role = JWT_LEVELS.get(float(level))
        if role is None:
            raise _refused(CLAIMS, f"JWT rcan_role {level!r} is not an RCAN role level")
        return role

    def _trusted(self) -> Role:
        if self._m2m_trusted is None:
            raise _refused(M2M_TRUSTED_REFUSED, "JWT role M2M_TRUSTED needs "
                           "bridge.api.jwt.m2m_trusted_role in the config")
        return self._m2m_trusted

    def _check_times(self, claims: dict[str, Any]) -> None:
        """exp required, not past; nbf and iat not in the future; exp at most max_lifetime_s
        after iat (or, without iat, after now): a token cannot be made to last for ever.
        Expired by the latest wall time read (`LatestWall`): a step back of the clock does
        not bring an expired token back."""
        now, latest = self._clock.time(), self._latest.time()
        exp, nbf, iat = claims.get("exp"), claims.get("nbf"), claims.get("iat")
        if not _is_time(exp) or latest > exp + self._leeway:
            raise _refused(EXPIRED, "JWT expired or without exp")
        if nbf is not None and (not _is_time(nbf) or now + self._leeway < nbf):
            raise _refused(NOT_YET, "JWT not valid yet")
        if iat is not None and (not _is_time(iat) or now + self._leeway < iat):
            raise _refused(NOT_YET, "JWT iat is not a time in the past")
        lifetime = exp - (now if iat is None else iat)
        if lifetime > self._max_lifetime:
            raise _refused(
                TOO_LONG, f"JWT lifetime {lifetime:.6g} s exceeds the maximum of "
                f"{self._max_lifetime:g} s (bridge.api.jwt.max_lifetime_s)")


def _is_name(value: Any) -> TypeGuard[str]:
    return isinstance(value, str) and 0 < len(value) <= _MAX_CLAIM_CHARS
