"""§12 RBAC: role monotonicity, tokens (env / SHA-256), single-token mode, EdDSA JWTs, limits."""

from __future__ import annotations

import base64
import hashlib
import json
import pkgutil
from pathlib import Path
from typing import Any

import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from govhelpers import RURI
from hypothesis import given
from hypothesis import strategies as st

import rcan_rtps.governance as governance
from rcan_rtps.config import loads_config
from rcan_rtps.governance.clock import ManualClock
from rcan_rtps.governance.errors import AuthConfigError, AuthenticationError
from rcan_rtps.governance.rbac import (
    DEFAULT_ACTION_ROLES,
    SCOPES,
    JwtVerifier,
    Principal,
    RateLimiter,
    RolePolicy,
    TokenAuthenticator,
    has_scope,
)
from rcan_rtps.rcan import Role

ACTIONS = list(DEFAULT_ACTION_ROLES)
TOKEN = "t0ken-for-ops-0123456789"


def test_public_api_is_exactly_the_export_list() -> None:
    public = {n for n in vars(governance) if not n.startswith("_")}
    # Submodules become attributes once anything imports them: they are not the export list.
    modules = {m.name for m in pkgutil.iter_modules(governance.__path__)} | {"annotations"}
    assert len(set(governance.__all__)) == len(governance.__all__)
    assert set(governance.__all__) == public - modules


def test_profile_defaults() -> None:
    policy = RolePolicy()
    assert [policy.required(a) for a in ("move", "arm_joint", "navigate", "stop")] == (
        [Role.USER] * 4)
    assert policy.required("estop") is Role.GUEST
    assert policy.required("clear_estop") is Role.OWNER
    assert [r.name for r in sorted(SCOPES.values())] == [
        "GUEST", "USER", "LEASEE", "OWNER", "CREATOR"]


def test_estop_cannot_be_raised_by_override() -> None:
    assert RolePolicy({"estop": Role.OWNER}).required("estop") is Role.GUEST


@given(
    overrides=st.dictionaries(st.sampled_from(ACTIONS), st.sampled_from(list(Role))),
    action=st.sampled_from(ACTIONS),
    low=st.sampled_from(list(Role)),
    high=st.sampled_from(list(Role)),
)
def test_if_a_role_may_act_every_higher_role_may(
    overrides: dict[str, Role], action: str, low: Role, high: Role
) -> None:
    policy = RolePolicy(overrides)
    if low <= high and policy.allows(low, action):
        assert policy.allows(high, action)
    scope = list(SCOPES)[int(low) - 1]
    if low <= high and has_scope(low, scope):
        assert has_scope(high, scope)


# -- tokens ---------------------------------------------------------------------------------


def authenticator(api: str, env: dict[str, str], clock: ManualClock | None = None,
                  tmp: Path | None = None) -> TokenAuthenticator:
    text = (f"robot: {{ruri: '{RURI}'}}\nbridge:\n  api: {api}\n"
            "  safety: {max_linear_vel: 1, max_angular_vel: 1}\n")
    config = loads_config(text, env={})
    return TokenAuthenticator.from_config(config.bridge.api, config.bridge.rbac, env,
                                          clock=clock or ManualClock())


def test_env_and_sha256_principals() -> None:
    digest = hashlib.sha256(b"planner-secret-0123456789").hexdigest()
    auth = authenticator(
        "{principals: [{name: ops, role: OWNER, token_env: OPS_TOKEN},"
        f" {{name: planner, role: USER, token_sha256: '{digest}', rate_limit_per_min: 7}}]}}",
        {"OPS_TOKEN": TOKEN},
    )
    assert auth.authenticate(TOKEN) == Principal("ops", Role.OWNER, 1000)
    assert auth.authenticate("planner-secret-0123456789") == Principal("planner", Role.USER, 7)
    for bad in ("", None, TOKEN + "x", TOKEN[:-1], digest):
        with pytest.raises(AuthenticationError):
            auth.authenticate(bad)


def test_single_token_mode_is_an_owner_named_default() -> None:
    auth = authenticator("{auth_token_env: RCAN_BRIDGE_TOKEN}", {"RCAN_BRIDGE_TOKEN": TOKEN})
    assert auth.authenticate(TOKEN) == Principal("default", Role.OWNER, 1000)


@pytest.mark.parametrize("value", [None, "", "short"])
def test_missing_or_weak_env_token_refuses_to_start(value: str | None) -> None:
    env = {} if value is None else {"RCAN_BRIDGE_TOKEN": value}
    with pytest.raises(AuthConfigError, match="RCAN_BRIDGE_TOKEN"):
        authenticator("{auth_token_env: RCAN_BRIDGE_TOKEN}", env)


# -- JWT ------------------------------------------------------------------------------------


def b64(raw: bytes) -> str:
    return base64.urlsafe_b64encode(raw).rstrip(b"=").decode()


def jwt(key: Ed25519PrivateKey, claims: dict[str, Any], header: dict[str, Any] | None = None,
        ) -> str:
    head = b64(json.dumps(header or {"alg": "EdDSA", "typ": "JWT"}).encode())
    body = b64(json.dumps(claims).encode())
    sig = key.sign(f"{head}.{body}".encode())
    return f"{head}.{body}.{b64(sig)}"


NOW = 1_800_000_000.0


@pytest.fixture
def issuer(tmp_path: Path) -> tuple[Ed25519PrivateKey, JwtVerifier]:
    key = Ed25519PrivateKey.generate()
    pem = key.public_key().public_bytes(serialization.Encoding.PEM,
                                        serialization.PublicFormat.SubjectPublicKeyInfo)
    (tmp_path / "jwt.pem").write_bytes(pem)
    return key, JwtVerifier(key.public_key(), audience="rcan-bridge", clock=ManualClock(NOW))


def claims(**kw: Any) -> dict[str, Any]:
    return {"sub": "agent-7", "role": "USER", "exp": NOW + 60, "aud": "rcan-bridge", **kw}


def test_valid_jwt(issuer: tuple[Ed25519PrivateKey, JwtVerifier]) -> None:
    key, verifier = issuer
    assert verifier.verify(jwt(key, claims())) == Principal("agent-7", Role.USER, 100)
    assert verifier.verify(jwt(key, claims(aud=["x", "rcan-bridge"]))).role is Role.USER


@pytest.mark.parametrize(
    ("change", "header"),
    [
        ({"exp": NOW - 31}, None),
        ({"exp": None}, None),
        ({"exp": True}, None),
        ({"aud": "other"}, None),
        ({"aud": None}, None),
        ({"role": "SUPERUSER"}, None),
        ({"role": None}, None),
        ({"sub": ""}, None),
        ({"nbf": NOW + 60}, None),
        ({}, {"alg": "none"}),
        ({}, {"alg": "HS256"}),
        ({}, {"alg": "EdDSA", "crit": ["x"]}),
    ],
)
def test_rejected_jwts(issuer: tuple[Ed25519PrivateKey, JwtVerifier], change: dict[str, Any],
                       header: dict[str, Any] | None) -> None:
    key, verifier = issuer
    body = {k: v for k, v in claims(**change).items() if v is not None}
    with pytest.raises(AuthenticationError):
        verifier.verify(jwt(key, body, header))


def test_jwt_signed_by_another_key_or_altered(
    issuer: tuple[Ed25519PrivateKey, JwtVerifier]
) -> None:
    key, verifier = issuer
    with pytest.raises(AuthenticationError, match="signature"):
        verifier.verify(jwt(Ed25519PrivateKey.generate(), claims()))
    head, _, sig = jwt(key, claims()).split(".")
    forged = b64(json.dumps(claims(role="CREATOR")).encode())
    with pytest.raises(AuthenticationError):
        verifier.verify(f"{head}.{forged}.{sig}")
    for junk in ("a.b.c", "..", "eyJ.eyJ.!!"):
        with pytest.raises(AuthenticationError):
            verifier.verify(junk)


def test_jwt_via_config(tmp_path: Path) -> None:
    key = Ed25519PrivateKey.generate()
    pem = key.public_key().public_bytes(serialization.Encoding.PEM,
                                        serialization.PublicFormat.SubjectPublicKeyInfo)
    (tmp_path / "jwt.pem").write_bytes(pem)
    clock = ManualClock(NOW)
    auth = authenticator(f"{{jwt: {{public_key: '{tmp_path}/jwt.pem', audience: rcan-bridge}}}}",
                         {}, clock)
    assert auth.authenticate(jwt(key, claims(role="OWNER"))).role is Role.OWNER


# -- rate limits ----------------------------------------------------------------------------


def test_token_bucket_per_principal() -> None:
    clock = ManualClock()
    limiter = RateLimiter(clock)
    guest, other = Principal("g", Role.GUEST, 10), Principal("h", Role.GUEST, 10)
    assert [limiter.allow(guest) for _ in range(11)] == [True] * 10 + [False]
    assert limiter.allow(other)
    clock.advance(5.9)
    assert not limiter.allow(guest)
    clock.advance(0.11)  # 10/min: one back every 6 s
    assert limiter.allow(guest)
    creator = Principal("c", Role.CREATOR, None)
    assert all(limiter.allow(creator) for _ in range(5000))


def test_configured_role_limits() -> None:
    digest = hashlib.sha256(TOKEN.encode()).hexdigest()
    text = (f"robot: {{ruri: '{RURI}'}}\nbridge:\n"
            f"  api: {{principals: [{{name: v, role: GUEST, token_sha256: '{digest}'}}]}}\n"
            "  safety: {max_linear_vel: 1, max_angular_vel: 1}\n"
            "  rbac: {rate_limits_per_min: {GUEST: 3}}\n")
    config = loads_config(text, env={})
    auth = TokenAuthenticator.from_config(config.bridge.api, config.bridge.rbac, {},
                                          clock=ManualClock())
    assert auth.authenticate(TOKEN).rate_limit_per_min == 3
