"""A JWT is its own principal (`jwt:<iss>/<sub>`), whatever its `sub` says: it cannot release a
configured principal's lock, keep that principal's control session alive, or pass for it in
the audit. A refused JWT's 401 says why."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from jwthelpers import sign_jwt, write_jwks

from tests.api.apihelpers import Api

KID = "idp-2026"
MOTION = "motion: {principal_priorities: {ops: 100}, locks: [{name: teleop, priority: 100}]}"


class JwtApi:
    def __init__(self, api: Api, key: Ed25519PrivateKey) -> None:
        self.api = api
        self.key = key

    def token(self, sub: str, role: str, **claims: Any) -> str:
        body = {"sub": sub, "role": role, "aud": "rcan-bridge",
                "exp": self.api.clock.time() + 3600, **claims}
        return sign_jwt(self.key, body, {"alg": "EdDSA", "kid": KID})

    async def call(self, method: str, path: str, token: str,
                   body: Any = None) -> tuple[int, Any, str]:
        async with self.api.http.request(method, path, json=body,
                                         headers={"Authorization": f"Bearer {token}"}) as resp:
            return resp.status, await resp.json(), resp.headers.get("WWW-Authenticate", "")


def _key_source(tmp_path: Path, key: Ed25519PrivateKey, source: str) -> str:
    if source == "jwks":
        return f"jwks: '{write_jwks(tmp_path / 'jwks.json', {KID: key})}'"
    pem = key.public_key().public_bytes(serialization.Encoding.PEM,
                                        serialization.PublicFormat.SubjectPublicKeyInfo)
    (tmp_path / "jwt.pem").write_bytes(pem)
    return f"public_key: '{tmp_path / 'jwt.pem'}'"


@pytest.fixture(params=["jwks", "pem"])
async def jwt_api(tmp_path: Path, request: pytest.FixtureRequest) -> AsyncIterator[JwtApi]:
    key = Ed25519PrivateKey.generate()
    keys = _key_source(tmp_path, key, request.param)
    api = await Api(tmp_path, api_extra=f"jwt: {{{keys}, audience: rcan-bridge}}",
                    bridge_extra=MOTION).start()
    yield JwtApi(api, key)
    await api.close()


async def test_a_jwt_named_like_a_principal_cannot_release_its_lock(jwt_api: JwtApi) -> None:
    api = jwt_api.api
    assert (await api.command("ops", {"action": "lock", "params": {"name": "teleop"}}))[0] == 200
    impostor = jwt_api.token("ops", "USER")
    status, body, _ = await jwt_api.call("POST", "/api/command", impostor,
                                         {"action": "unlock", "params": {"name": "teleop"}})
    assert (status, body.get("reason")) == (409, "lower_priority")
    assert api.gov.streams.locks == {"teleop": 100}
    status, body = await api.command("planner", {"action": "move", "params": {"linear_x": 0.1}})
    assert (status, body["reason"]) == (409, "motion_locked")
    unlocks = [e for e in api.entries if e["action_type"] == "unlock"]
    assert [(e["principal"], e["outcome"]) for e in unlocks] == [("jwt:/ops", "denied")]


async def test_a_jwt_named_like_a_principal_does_not_heartbeat_its_session(
    jwt_api: JwtApi,
) -> None:
    api = jwt_api.api
    status, _ = await api.command("planner", {"action": "move", "params": {"linear_x": 0.2}})
    assert status == 200  # a held move: it lasts as long as planner's session
    impostor = jwt_api.token("planner", "GUEST")
    api.clock.advance(50)  # session_timeout_s is 60
    status, body, _ = await jwt_api.call("POST", "/api/heartbeat", impostor)
    assert status == 200
    api.clock.advance(50)  # planner itself has been silent for 100 s
    await api.gov.sweep()
    assert [action for action, _ in api.dispatcher.calls] == ["move", "stop"]
    assert body["principal"] == "jwt:/planner"  # the impostor kept its own session alive
    lost = [e for e in api.entries if e["event"] == "NETWORK_LOSS_SAFE_STOP"]
    assert [e["principal"] for e in lost] == ["planner"]


async def test_a_jwt_named_like_a_principal_is_another_principal_in_the_audit(
    jwt_api: JwtApi,
) -> None:
    api = jwt_api.api
    for sub, iss in (("ops", None), ("ops", "https://idp.example"), ("jwt:/ops", None)):
        token = jwt_api.token(sub, "OWNER", **({"iss": iss} if iss else {}))
        status, _, _ = await jwt_api.call("POST", "/api/command", token, {"action": "stop"})
        assert status == 200
    assert (await api.command("ops", {"action": "stop"}))[0] == 200
    stops = [e["principal"] for e in api.entries if e["action_type"] == "stop"]
    assert stops == ["jwt:/ops", "jwt:https:%2F%2Fidp.example/ops", "jwt:/jwt:/ops", "ops"]


def _signed(jwt_api: JwtApi, header: dict[str, Any] | None = None, **claims: Any) -> str:
    body = {"sub": "agent", "role": "USER", "aud": "rcan-bridge",
            "exp": jwt_api.api.clock.time() + 60, **claims}
    return sign_jwt(jwt_api.key, body, header or {"alg": "EdDSA", "kid": KID})


async def _told(jwt_api: JwtApi, token: str, reason: str, description: str) -> None:
    status, reply, challenge = await jwt_api.call("GET", "/api/status", token)
    assert (status, reply.get("error_code"), reply.get("reason")) == (
        401, "UNAUTHENTICATED", reason)
    assert 'error="invalid_token"' in challenge and description in challenge


async def test_a_jwt_that_would_last_for_ever_is_refused(jwt_api: JwtApi) -> None:
    token = _signed(jwt_api, exp=253402300799)  # 9999-12-31
    await _told(jwt_api, token, "jwt_lifetime_too_long", "exceeds the maximum of 86400 s")


@pytest.mark.parametrize("jwt_api", ["jwks"], indirect=True)
async def test_a_jwt_of_an_unknown_kid_is_refused(jwt_api: JwtApi) -> None:
    await _told(jwt_api, _signed(jwt_api, {"alg": "EdDSA", "kid": "gone"}), "jwt_unknown_kid",
                "kid is not in the JWKS")
    await _told(jwt_api, _signed(jwt_api, {"alg": "EdDSA"}), "jwt_unknown_kid", "needs a kid")


async def test_a_wrong_static_token_is_told_nothing(jwt_api: JwtApi) -> None:
    status, reply, challenge = await jwt_api.call("GET", "/api/status", "not-a-token-at-all")
    assert (status, reply.get("reason")) == (401, None)
    assert challenge == 'Bearer realm="rcan", error="invalid_token"'


@pytest.mark.parametrize("claim", ["exp", "iat", "nbf", "rcan_role"])
async def test_a_jwt_time_past_any_float_is_refused_as_its_claim(
        jwt_api: JwtApi, claim: str, caplog: pytest.LogCaptureFixture) -> None:
    """A signed claim of 401 digits (JSON integers have no bound; an issuer's bug): refused
    401 as that claim, never a 500 with a traceback (before: `math.isfinite` overflowed
    turning it into a float)."""
    reasons = {"exp": "jwt_expired", "iat": "jwt_not_yet_valid", "nbf": "jwt_not_yet_valid",
               "rcan_role": "jwt_claims"}
    extra: dict[str, Any] = {claim: 10**400}
    if claim == "rcan_role":
        extra["role"] = None
    body = {"sub": "agent", "role": "USER", "aud": "rcan-bridge",
            "exp": jwt_api.api.clock.time() + 60, **extra}
    body = {k: v for k, v in body.items() if v is not None}
    token = sign_jwt(jwt_api.key, body, {"alg": "EdDSA", "kid": KID})
    status, reply, _ = await jwt_api.call("GET", "/api/status", token)
    assert (status, reply.get("reason")) == (401, reasons[claim]), reply
    assert "Traceback" not in caplog.text
