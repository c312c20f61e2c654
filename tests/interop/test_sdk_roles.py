"""Issue 24 item 2 against a real `run --sim`: RCAN v2's role names in the config (OPERATOR,
ADMIN, CONTRIBUTOR) and JWTs whose `rcan_role` is the SDK's level for a role
(`rcan.identity.ROLE_TO_JWT_LEVEL`), driven by the official SDK's messages."""

from __future__ import annotations

import re
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from jwthelpers import sign_jwt, write_jwks
from rcan.address import RobotURI
from rcan.identity import ROLE_TO_JWT_LEVEL
from rcan.identity import Role as SdkRole
from rcan.message import RCANMessage
from rcan.safety import make_estop_message, make_resume_message

from rcan_rtps.bridge.demo import demo_yaml
from tests.interop.test_conformance import Sim, _sim

KID, AUDIENCE = "idp-1", "rcan-sim"


@pytest.fixture
def idp_key() -> Ed25519PrivateKey:
    return Ed25519PrivateKey.generate()


@pytest.fixture
def v2_sim(tmp_path: Path, domain_id: int, idp_key: Ed25519PrivateKey) -> Iterator[Sim]:
    text = demo_yaml(state_dir=tmp_path / "state", port=8765, domain_id=domain_id,
                     namespace="/robot1")
    renamed = (text.replace("role: GUEST", "role: CONTRIBUTOR")
               .replace("role: USER", "role: OPERATOR").replace("role: OWNER", "role: ADMIN"))
    assert renamed.count("CONTRIBUTOR") == renamed.count("OPERATOR") == 1
    jwks = write_jwks(tmp_path / "jwks.json", {KID: idp_key})
    renamed = renamed.replace("  api:\n", f"  api:\n    jwt: {{jwks: '{jwks}', audience: "
                              f"{AUDIENCE}}}\n", 1)
    config = tmp_path / "v2.rcan.yaml"
    config.write_text(renamed)
    yield from _sim(tmp_path, domain_id, "--config", str(config), "--no-mdns")


@pytest.fixture
async def http() -> AsyncIterator[aiohttp.ClientSession]:
    async with aiohttp.ClientSession() as session:
        yield session


async def _send(http: aiohttp.ClientSession, sim: Sim, token: str,
                body: dict[str, Any]) -> tuple[int, Any]:
    async with http.post(f"{sim.url}/api/command", json=body,
                         headers={"Authorization": f"Bearer {token}"}) as response:
        return response.status, await response.json()


def _jwt(key: Ed25519PrivateKey, sdk_role: SdkRole, sub: str) -> str:
    claims = {"sub": sub, "aud": AUDIENCE, "exp": int(time.time()) + 600,
              "rcan_role": ROLE_TO_JWT_LEVEL[sdk_role]}
    return sign_jwt(key, claims, {"alg": "EdDSA", "kid": KID})


async def _ruri(http: aiohttp.ClientSession, sim: Sim) -> RobotURI:
    async with http.get(f"{sim.url}/api/status",
                        headers={"Authorization": f"Bearer {sim.tokens['OWNER']}"}) as r:
        return RobotURI.parse((await r.json())["ruri"])


def _move(robot: RobotURI) -> dict[str, Any]:
    return RCANMessage(cmd="move", target=robot,
                       params={"linear_x": 0.0, "duration_s": 0.2}).to_dict()


async def test_v2_role_names_in_the_config(v2_sim: Sim, http: aiohttp.ClientSession) -> None:
    sim, robot = v2_sim, await _ruri(http, v2_sim)
    status, body = await _send(http, sim, sim.tokens["USER"], _move(robot))  # OPERATOR
    assert (status, body["status"]) == (200, "ok"), body
    status, body = await _send(http, sim, sim.tokens["GUEST"], _move(robot))  # CONTRIBUTOR
    assert (status, body["error_code"]) == (403, "INSUFFICIENT_PRIVILEGES"), body
    status, body = await _send(http, sim, sim.tokens["GUEST"],
                               make_estop_message(str(robot), "drill"))
    assert (status, body["status"]) == (200, "ok"), body  # the e-stop: anyone
    status, body = await _send(http, sim, sim.tokens["USER"],
                               make_resume_message(str(robot), "not yours"))
    assert (status, body["status"]) == (403, "blocked"), body
    status, body = await _send(http, sim, sim.tokens["OWNER"],  # ADMIN = OWNER
                               make_resume_message(str(robot), "clear"))
    assert (status, body["status"]) == (200, "ok"), body


async def test_jwt_rcan_role_levels_from_the_sdk(v2_sim: Sim, http: aiohttp.ClientSession,
                                                 idp_key: Ed25519PrivateKey) -> None:
    sim, robot = v2_sim, await _ruri(http, v2_sim)
    operator = _jwt(idp_key, SdkRole.OPERATOR, "agent-7")
    status, body = await _send(http, sim, operator, _move(robot))
    assert (status, body["status"]) == (200, "ok"), body
    guest = _jwt(idp_key, SdkRole.GUEST, "visitor")
    status, body = await _send(http, sim, guest, _move(robot))
    assert status == 403, body
    status, body = await _send(http, sim, guest, make_estop_message(str(robot), "drill"))
    assert (status, body["status"]) == (200, "ok"), body
    status, body = await _send(http, sim, operator, make_resume_message(str(robot), "no"))
    assert status == 403, body
    admin = _jwt(idp_key, SdkRole.ADMIN, "site-admin")
    status, body = await _send(http, sim, admin, make_resume_message(str(robot), "clear"))
    assert (status, body["status"]) == (200, "ok"), body
    async with http.get(f"{sim.url}/api/audit?since=0",
                        headers={"Authorization": f"Bearer {sim.tokens['OWNER']}"}) as r:
        entries = (await r.json())["entries"]
    roles = {e["principal"]: e["role"] for e in entries
             if (e.get("principal") or "").startswith("jwt:")}
    assert {re.sub(r"^jwt:[^/]*/", "", p): r for p, r in roles.items()} == {
        "agent-7": "USER", "visitor": "GUEST", "site-admin": "OWNER"}  # output: profile names
