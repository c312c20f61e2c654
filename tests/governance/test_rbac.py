"""§12 RBAC: role monotonicity, tokens (env / SHA-256), single-token mode, EdDSA JWTs (their
own principals, a maximum lifetime, JWKS keys by kid), limits."""

from __future__ import annotations

import hashlib
import json
import pkgutil
from pathlib import Path
from typing import Any
from urllib.parse import unquote

import msgspec
import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from govhelpers import RURI
from hypothesis import given
from hypothesis import strategies as st
from jwthelpers import b64, public_jwk, sign_jwt, write_jwks

import rcan_rtps.governance as governance
from rcan_rtps.config import ConfigError, PrincipalConfig, loads_config
from rcan_rtps.governance.clock import ManualClock
from rcan_rtps.governance.errors import AuthConfigError, AuthenticationError
from rcan_rtps.governance.jwt import JwtVerifier, jwt_principal_name
from rcan_rtps.governance.rbac import (
    DEFAULT_ACTION_ROLES,
    DEFAULT_RATE_LIMITS,
    SCOPES,
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
    lazy = {"JwtVerifier"}  # resolved when first asked for (`governance.__getattr__`)
    assert governance.JwtVerifier is JwtVerifier
    assert len(set(governance.__all__)) == len(governance.__all__)
    assert set(governance.__all__) == (public | lazy) - modules


def test_profile_defaults() -> None:
    policy = RolePolicy()
    assert [policy.required(a) for a in ("move", "arm_joint", "navigate", "stop")] == (
        [Role.USER] * 4)
    assert policy.required("estop") is Role.GUEST
    assert policy.required("clear_estop") is Role.OWNER
    assert [r.name for r in sorted(SCOPES.values())] == [
        "GUEST", "USER", "LEASEE", "OWNER", "CREATOR"]
    # the profile's default rate limits per principal per minute (None: unlimited)
    assert dict(DEFAULT_RATE_LIMITS) == {Role.GUEST: 10, Role.USER: 100, Role.LEASEE: 500,
                                         Role.OWNER: 1000, Role.CREATOR: None}


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


@given(
    overrides=st.dictionaries(st.sampled_from(ACTIONS), st.sampled_from(list(Role))),
    action=st.sampled_from(ACTIONS),
    role=st.sampled_from(list(Role)),
    unknown=st.text(min_size=1).filter(lambda name: name not in ACTIONS),
)
def test_a_policy_refuses_what_it_does_not_allow_and_nothing_it_does_not_know(
    overrides: dict[str, Role], action: str, role: Role, unknown: str
) -> None:
    """`refuses` (the governor's count of motion on its way) is sure of a refusal, or says no:
    an action the policy does not know is not certainly refused."""
    policy = RolePolicy(overrides)
    assert policy.refuses(role, action) is not policy.allows(role, action)
    assert policy.refuses(role, unknown) is False


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


def jwt(key: Ed25519PrivateKey, claims: dict[str, Any], header: dict[str, Any] | None = None,
        ) -> str:
    return sign_jwt(key, claims, header)


NOW = 1_800_000_000.0
DAY = 86400.0


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
    # Taken until its exp plus the leeway (30 s): what outlives a request (a WebSocket) ends then.
    assert verifier.verify(jwt(key, claims())) == Principal("jwt:/agent-7", Role.USER, 100,
                                                            expires_at=NOW + 60 + 30)
    assert verifier.verify(jwt(key, claims(aud=["x", "rcan-bridge"]))).role is Role.USER
    named = verifier.verify(jwt(key, claims(iss="https://idp.example/", iat=NOW - 5)))
    assert named.name == "jwt:https:%2F%2Fidp.example%2F/agent-7"


@pytest.mark.parametrize(
    ("change", "header", "reason"),
    [
        ({"exp": NOW - 31}, None, "jwt_expired"),
        ({"exp": None}, None, "jwt_expired"),
        ({"exp": True}, None, "jwt_expired"),
        ({"aud": "other"}, None, "jwt_claims"),
        ({"aud": None}, None, "jwt_claims"),
        ({"role": "SUPERUSER"}, None, "jwt_claims"),
        ({"role": None}, None, "jwt_claims"),
        ({"sub": ""}, None, "jwt_claims"),
        ({"sub": 7}, None, "jwt_claims"),
        ({"sub": "x" * 257}, None, "jwt_claims"),
        ({"iss": ""}, None, "jwt_claims"),
        ({"iss": 7}, None, "jwt_claims"),
        ({"nbf": NOW + 60}, None, "jwt_not_yet_valid"),
        ({}, {"alg": "none"}, "jwt_malformed"),
        ({}, {"alg": "HS256"}, "jwt_malformed"),
        ({}, {"alg": "EdDSA", "crit": ["x"]}, "jwt_malformed"),
        # No token lasts for ever: 24 h from iat, or from now without one.
        ({"exp": 253402300799}, None, "jwt_lifetime_too_long"),  # 9999-12-31
        ({"exp": NOW + DAY + 1}, None, "jwt_lifetime_too_long"),
        ({"iat": NOW - 10, "exp": NOW + DAY}, None, "jwt_lifetime_too_long"),
        ({"iat": NOW - 3 * DAY, "exp": NOW + 60}, None, "jwt_lifetime_too_long"),
        # An iat in the future cannot shorten a far exp into a "short" lifetime.
        ({"iat": 253402300799 - 60, "exp": 253402300799}, None, "jwt_not_yet_valid"),
        ({"iat": "yesterday"}, None, "jwt_not_yet_valid"),
    ],
)
def test_rejected_jwts(issuer: tuple[Ed25519PrivateKey, JwtVerifier], change: dict[str, Any],
                       header: dict[str, Any] | None, reason: str) -> None:
    key, verifier = issuer
    body = {k: v for k, v in claims(**change).items() if v is not None}
    with pytest.raises(AuthenticationError) as info:
        verifier.verify(jwt(key, body, header))
    assert info.value.reason == reason


def test_lifetime_at_the_maximum_is_accepted(
    issuer: tuple[Ed25519PrivateKey, JwtVerifier]
) -> None:
    key, verifier = issuer
    assert verifier.verify(jwt(key, claims(exp=NOW + DAY))).role is Role.USER
    assert verifier.verify(jwt(key, claims(iat=NOW - 60, exp=NOW - 60 + DAY))).role is Role.USER
    assert verifier.verify(jwt(key, claims(iat=NOW + 20, exp=NOW + 60))).role is Role.USER  # leeway


def test_maximum_lifetime_is_configurable(tmp_path: Path) -> None:
    key = Ed25519PrivateKey.generate()
    write_jwks(tmp_path / "jwks.json", {"k1": key})
    auth = authenticator(f"{{jwt: {{jwks: '{tmp_path}/jwks.json', audience: rcan-bridge, "
                         "max_lifetime_s: 600}}", {}, ManualClock(NOW))
    kid = {"alg": "EdDSA", "kid": "k1"}
    assert auth.authenticate(jwt(key, claims(exp=NOW + 600), kid)).role is Role.USER
    with pytest.raises(AuthenticationError, match="exceeds the maximum of 600 s"):
        auth.authenticate(jwt(key, claims(exp=NOW + 601), kid))


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


# -- JWT identity: a token never speaks for a configured principal --------------------------


def test_a_jwt_naming_a_static_principal_is_another_principal(tmp_path: Path) -> None:
    key = Ed25519PrivateKey.generate()
    write_jwks(tmp_path / "jwks.json", {"k1": key})
    auth = authenticator(
        "{principals: [{name: ops, role: OWNER, token_env: OPS_TOKEN}, "
        "{name: default, role: USER, token_env: OPS_TOKEN2}], "
        f"jwt: {{jwks: '{tmp_path}/jwks.json', audience: rcan-bridge}}}}",
        {"OPS_TOKEN": TOKEN, "OPS_TOKEN2": TOKEN + "2"}, ManualClock(NOW))
    kid = {"alg": "EdDSA", "kid": "k1"}
    static = auth.authenticate(TOKEN)
    for sub in ("ops", "default"):
        as_jwt = auth.authenticate(jwt(key, claims(sub=sub, role="GUEST"), kid))
        assert as_jwt.name != static.name and as_jwt.name != "default"
        assert as_jwt.name == f"jwt:/{sub}"
    issued = auth.authenticate(jwt(key, claims(sub="ops", iss="idp-a"), kid))
    assert issued.name == "jwt:idp-a/ops"


def decode_jwt_name(name: str) -> tuple[str | None, str]:
    """The inverse of jwt_principal_name: that it exists shows no two pairs share a name."""
    assert name.startswith("jwt:")
    iss, slash, sub = name[4:].partition("/")
    assert slash
    return (unquote(iss, errors="surrogatepass") or None,
            unquote(sub, errors="surrogatepass"))


def is_config_principal_name(name: str) -> bool:
    try:
        msgspec.convert({"name": name, "role": "USER", "token_env": "X"}, PrincipalConfig)
    except msgspec.ValidationError:
        return False
    return True


@given(issuer=st.none() | st.text(min_size=1), subject=st.text(min_size=1),
       static=st.from_regex(r"\A[A-Za-z0-9][A-Za-z0-9_.@-]{0,63}\Z"))
def test_no_jwt_subject_maps_onto_a_configured_principal(issuer: str | None, subject: str,
                                                          static: str) -> None:
    name = jwt_principal_name(issuer, subject)
    assert is_config_principal_name(static)  # the strategy draws names a config may hold
    assert not is_config_principal_name(name) and name != static and name != "default"
    assert decode_jwt_name(name) == (issuer, subject)  # injective: across issuers too
    assert name.isprintable()  # nothing raw in a log line: no newline, no bidi override


@pytest.mark.parametrize(("pair_a", "pair_b"), [
    (("a/b", "c"), ("a", "b/c")),
    (("a%2Fb", "c"), ("a/b", "c")),
    (("a", "b\nc"), ("a", "b%0Ac")),
])
def test_lookalike_issuers_and_subjects_stay_apart(pair_a: tuple[str | None, str],
                                                   pair_b: tuple[str | None, str]) -> None:
    # (An empty `iss` would read as none: the verifier refuses it, see test_rejected_jwts.)
    assert jwt_principal_name(*pair_a) != jwt_principal_name(*pair_b)


# -- JWKS: keys rotated by kid --------------------------------------------------------------


def jwks_authenticator(path: Path) -> TokenAuthenticator:
    return authenticator(f"{{jwt: {{jwks: '{path}', audience: rcan-bridge}}}}", {},
                         ManualClock(NOW))


def test_jwks_keys_are_chosen_by_kid(tmp_path: Path) -> None:
    old, new, stranger = (Ed25519PrivateKey.generate() for _ in range(3))
    path = write_jwks(tmp_path / "jwks.json", {"2025-old": old, "2026-new": new})
    auth = jwks_authenticator(path)
    for kid, key in (("2025-old", old), ("2026-new", new)):
        token = jwt(key, claims(sub=kid), {"alg": "EdDSA", "kid": kid})
        assert auth.authenticate(token).name == f"jwt:/{kid}"
    refused = [
        jwt(stranger, claims(), {"alg": "EdDSA", "kid": "2027"}),  # unknown kid
        jwt(old, claims(), {"alg": "EdDSA", "kid": "2027"}),  # a known key, unknown kid
        jwt(old, claims(), {"alg": "EdDSA"}),  # no kid
        jwt(old, claims(), {"alg": "EdDSA", "kid": 1}),
    ]
    for token in refused:
        with pytest.raises(AuthenticationError) as info:
            auth.authenticate(token)
        assert info.value.reason == "jwt_unknown_kid"
    with pytest.raises(AuthenticationError, match="signature"):  # the kid of another key
        auth.authenticate(jwt(old, claims(), {"alg": "EdDSA", "kid": "2026-new"}))


def test_a_key_removed_from_the_jwks_no_longer_verifies_at_start(tmp_path: Path) -> None:
    old, new = Ed25519PrivateKey.generate(), Ed25519PrivateKey.generate()
    path = write_jwks(tmp_path / "jwks.json", {"old": old, "new": new})
    old_token = jwt(old, claims(), {"alg": "EdDSA", "kid": "old"})
    new_token = jwt(new, claims(), {"alg": "EdDSA", "kid": "new"})
    assert jwks_authenticator(path).authenticate(old_token).role is Role.USER
    write_jwks(path, {"new": new})  # rotated out; the bridge reads the file when it starts
    restarted = jwks_authenticator(path)
    assert restarted.authenticate(new_token).role is Role.USER
    with pytest.raises(AuthenticationError, match="kid"):
        restarted.authenticate(old_token)


@pytest.mark.parametrize(("document", "problem"), [
    ("not json", "cannot load JWKS"),
    ('{"keys": []}', "non-empty `keys`"),
    ('[1]', "non-empty `keys`"),
    ('{"keys": [1]}', "not a JSON object"),
    ('{"keys": [{"kty": "OKP", "crv": "Ed25519", "x": "@X@"}]}', "needs a `kid`"),
    ('{"keys": [{"kty": "OKP", "crv": "X25519", "x": "@X@", "kid": "a"}]}', "not an Ed25519"),
    ('{"keys": [{"kty": "RSA", "n": "AQAB", "e": "AQAB", "kid": "a"}]}', "not an Ed25519"),
    ('{"keys": [{"kty": "OKP", "crv": "Ed25519", "x": "@X@", "d": "@X@", "kid": "a"}]}',
     "private key"),
    ('{"keys": [{"kty": "OKP", "crv": "Ed25519", "x": "@X@", "kid": "a", "use": "enc"}]}',
     "not a signing key"),
    ('{"keys": [{"kty": "OKP", "crv": "Ed25519", "x": "AAAA", "kid": "a"}]}', "32-byte"),
    ('{"keys": [{"kty": "OKP", "crv": "Ed25519", "x": "@X@=", "kid": "a"}]}', "32-byte"),
    ('{"keys": [{"kty": "OKP", "crv": "Ed25519", "x": "@X@", "kid": "a"}, '
     '{"kty": "OKP", "crv": "Ed25519", "x": "@X@", "kid": "a"}]}', "used twice"),
])
def test_bad_jwks_files_refuse_to_start(tmp_path: Path, document: str, problem: str) -> None:
    x = public_jwk(Ed25519PrivateKey.generate(), "a")["x"]
    path = tmp_path / "jwks.json"
    path.write_text(document.replace("@X@", x))
    with pytest.raises(AuthConfigError, match=problem):
        jwks_authenticator(path)
    with pytest.raises(AuthConfigError, match="cannot load JWKS"):
        jwks_authenticator(tmp_path / "missing.json")


@pytest.mark.parametrize("keys", ["", "public_key: a.pem, jwks: b.json, "])
def test_jwt_config_names_exactly_one_key_source(keys: str) -> None:
    text = (f"robot: {{ruri: '{RURI}'}}\nbridge:\n"
            f"  api: {{jwt: {{{keys}audience: rcan-bridge}}}}\n"
            "  safety: {max_linear_vel: 1, max_angular_vel: 1}\n")
    with pytest.raises(ConfigError, match="exactly one of `public_key` or `jwks`"):
        loads_config(text, env={})


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
