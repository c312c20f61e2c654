"""Red team 30: a command held for a human does not run once its issuer's credential ran out.

Over REST nothing ended a held command whose issuer's JWT (`exp` plus `leeway_s`) or client
certificate (notAfter) ran out while it waited: approved later, it ran for a principal the
bridge refused every request of. Now an approval after that is refused 409
`issuer_credential_expired` and the command withdrawn (HITL_WITHDRAWN by its issuer, the reason
naming the expiry), and the governor's sweep withdraws it at that time itself; approvers stop
seeing it. Real JWTs (EdDSA) and real client certificates over TLS on 127.0.0.1."""

from __future__ import annotations

import datetime as dt
import ssl
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from jwthelpers import sign_jwt, write_jwks

from rcan_rtps.governance.review import CREDENTIAL_EXPIRED
from tests.api.apihelpers import Api
from tests.api.test_tls import Pki, mtls_api, pki  # noqa: F401 (fixtures)

KID = "idp-2030"
LEEWAY_S = 30.0  # the config's default `leeway_s`
ARM = {"action": "arm_joint", "params": {"joints": ["j0"], "positions": [0.1],
                                         "duration_s": 2.0}}
EXPIRED = "issuer_credential_expired"


class JwtApi:
    def __init__(self, api: Api, key: Ed25519PrivateKey) -> None:
        self.api, self.key = api, key

    def token(self, left_s: float) -> dict[str, str]:
        """A USER's bearer header whose JWT has `left_s` before its `exp`."""
        claims = {"sub": "agent", "role": "USER", "aud": "rcan-bridge",
                  "exp": self.api.clock.time() + left_s}
        return {"Authorization": "Bearer " + sign_jwt(self.key, claims,
                                                      {"alg": "EdDSA", "kid": KID})}

    async def post(self, path: str, headers: dict[str, str], body: Any) -> tuple[int, Any]:
        async with self.api.http.post(path, json=body, headers=headers) as resp:
            return resp.status, await resp.json()


@pytest.fixture
async def jwt_api(tmp_path: Path) -> AsyncIterator[JwtApi]:
    key = Ed25519PrivateKey.generate()
    jwks = write_jwks(tmp_path / "jwks.json", {KID: key})
    api = await Api(tmp_path, api_extra=f"jwt: {{jwks: '{jwks}', audience: rcan-bridge}}"
                    ).start()
    yield JwtApi(api, key)
    await api.close()


async def _held_by_jwt(jwt_api: JwtApi, left_s: float) -> str:
    status, body = await jwt_api.post("/api/command", jwt_api.token(left_s), ARM)
    assert (status, body["outcome"]) == (202, "pending_auth"), body
    return str(body["pending_id"])


def _withdrawn_for_expiry(api: Api, pending_id: str, issuer: str) -> None:
    """Its end is its issuer's withdrawal naming the expiry; it is no longer held; nothing
    reached the robot."""
    ends = [e for e in api.entries if e.get("pending_id") == pending_id
            and e["event"].startswith("HITL_")]
    assert [(e["event"], e["principal"]) for e in ends] == [("HITL_WITHDRAWN", issuer)], ends
    assert [r["reason"] for r in ends[0]["approvals"]] == [CREDENTIAL_EXPIRED]
    assert pending_id not in {p.pending_id for p in api.gov.pending()}
    assert [c for c in api.dispatcher.calls if c[0] == "arm_joint"] == []


async def _approvers_see_it_withdrawn(api: Api, pending_id: str) -> None:
    """Approvers no longer list it, and read `hitl_withdrawn` by its id."""
    status, listed = await api.call("GET", "/api/hitl/pending", "ops")
    assert status == 200 and pending_id not in {p["pending_id"] for p in listed["pending"]}
    status, body = await api.call("GET", f"/api/hitl/pending/{pending_id}", "ops")
    assert (status, body["state"], body["decision"]["reason"]) == (
        200, "resolved", "hitl_withdrawn"), body


async def test_an_approval_over_rest_after_the_issuer_s_jwt_expired_is_refused(
        jwt_api: JwtApi) -> None:
    api = jwt_api.api
    pending_id = await _held_by_jwt(jwt_api, 60)
    api.clock.advance(60 + LEEWAY_S + 1)  # its JWT is refused from here on
    status, body = await jwt_api.post("/api/heartbeat", jwt_api.token(-LEEWAY_S - 1), None)
    assert status == 401, body  # (as the issuer's own token would be)
    status, body = await api.call("POST", "/api/hitl/authorize", "ops",
                                  body={"pending_id": pending_id})
    assert (status, body.get("reason")) == (409, EXPIRED), body  # it ran: 200 executed
    _withdrawn_for_expiry(api, pending_id, "jwt:/agent")
    await _approvers_see_it_withdrawn(api, pending_id)


async def test_the_sweep_withdraws_a_held_command_when_its_jwt_expires(
        jwt_api: JwtApi) -> None:
    api = jwt_api.api
    pending_id = await _held_by_jwt(jwt_api, 60)
    kept = await _held_by_jwt(jwt_api, 3600)  # the same principal's, with a longer token
    api.clock.advance(60 + LEEWAY_S)
    await api.gov.sweep()
    _withdrawn_for_expiry(api, pending_id, "jwt:/agent")
    await _approvers_see_it_withdrawn(api, pending_id)
    status, body = await api.call("POST", "/api/hitl/authorize", "ops",
                                  body={"pending_id": kept})
    assert (status, body["outcome"]) == (200, "executed"), body


def _soon(api: Api, seconds: float) -> dt.datetime:
    """A notAfter `seconds` ahead of the app's clock (which is ahead of the real one)."""
    return dt.datetime.fromtimestamp(api.clock.time() + seconds, dt.timezone.utc)


async def _post(url: str, context: ssl.SSLContext, path: str, body: Any,
                headers: dict[str, str] | None = None) -> tuple[int, Any]:
    async with aiohttp.ClientSession() as session, session.post(
            url + path, ssl=context, json=body, headers=headers) as resp:
        return resp.status, await resp.json()


async def test_an_approval_after_the_issuer_s_certificate_expired_is_refused(
        mtls_api: tuple[Api, str], pki: Pki) -> None:  # noqa: F811
    api, url = mtls_api
    planner = pki.context(pki.client("planner", not_after=_soon(api, 5)))
    status, body = await _post(url, planner, "/api/command", ARM)
    assert (status, body["outcome"]) == (202, "pending_auth"), body
    pending_id = body["pending_id"]
    api.clock.advance(10)  # past its notAfter
    ops = pki.context(pki.client("ops"))  # (mTLS: every connection presents one)
    status, body = await _post(url, ops, "/api/hitl/authorize", {"pending_id": pending_id})
    assert (status, body.get("reason")) == (409, EXPIRED), body
    _withdrawn_for_expiry(api, pending_id, "planner")
