"""Issue 24 item 2: RCAN v2's role names, in a config and in JWTs, map onto the profile's roles.

GUEST = GUEST, OPERATOR = USER, ADMIN = OWNER, CREATOR = CREATOR, CONTRIBUTOR → GUEST (fleet
contribution, not control), M2M_PEER → USER, M2M_TRUSTED refused unless configured; LEASEE stays
ours. JWT `rcan_role` levels are the SDK's (`rcan.identity.ROLE_TO_JWT_LEVEL`). The e-stop stays
open to every authenticated principal, whatever the SDK's scope table says (it puts `estop` at
CREATOR).
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from jwthelpers import sign_jwt, write_jwks
from rcan.identity import ROLE_TO_JWT_LEVEL, SCOPE_MIN_ROLE
from rcan.identity import Role as SdkRole
from rcan.safety import make_estop_message, make_resume_message

from rcan_rtps.config import ConfigError
from tests.api.apihelpers import Api, make_config
from tests.api.test_rcan3_messages import TARGET, sdk_command

# The mapping the issue asks for, by the SDK's role.
EXPECTED = {SdkRole.GUEST: "GUEST", SdkRole.OPERATOR: "USER", SdkRole.CONTRIBUTOR: "GUEST",
            SdkRole.ADMIN: "OWNER", SdkRole.M2M_PEER: "USER", SdkRole.CREATOR: "CREATOR"}
MOVE = {"action": "move", "params": {"linear_x": 0.1, "duration_s": 1.0}}


@pytest.mark.parametrize(("who", "role", "moves"), [
    ("operator", "USER", True), ("peer", "USER", True), ("admin", "OWNER", True),
    ("contributor", "GUEST", False),
])
async def test_v2_names_in_the_config(api: Api, who: str, role: str, moves: bool) -> None:
    status, body = await api.command(who, MOVE)
    assert (status == 200) is moves, body
    assert api.entry(body["audit_id"])["role"] == role  # output: the profile's names
    status, body = await api.command(who, make_estop_message(ruri=TARGET, reason="drill"))
    assert (status, body["outcome"]) == (200, "executed"), body  # the e-stop: anyone
    status, body = await api.command(who, make_resume_message(ruri=TARGET, reason="clear"))
    assert (status == 200) is (role == "OWNER"), body
    if status != 200:
        await api.command("ops", {"action": "clear_estop"})


async def test_an_admin_approves_what_waits_for_an_owner(api: Api) -> None:
    status, body = await api.command("operator", sdk_command(
        api, "arm_joint", {"joints": ["elbow"], "positions": [0.5], "duration_s": 1.0}))
    assert (status, body["status"]) == (202, "pending"), body
    status, body = await api.call("POST", "/api/hitl/authorize", "admin",
                                  body={"pending_id": body["pending_id"]})
    assert (status, body["outcome"]) == (200, "executed"), body


def test_v2_names_throughout_the_rbac_config(tmp_path: Path) -> None:
    config = make_config(tmp_path, bridge_extra=(
        "rbac: {hitl_approver_role: ADMIN, audit_read_role: OPERATOR, "
        "action_roles: {estop: CONTRIBUTOR, navigate: ADMIN}, rate_limits_per_min: {M2M_PEER: 7}}"))
    assert config.bridge.rbac.hitl_approver_role == "ADMIN"


@pytest.mark.parametrize(("extra", "says"), [
    ("rbac: {rate_limits_per_min: {USER: 5, OPERATOR: 9}}", "name the same role"),
    ("rbac: {action_roles: {estop: OPERATOR}}", "cannot be raised above GUEST"),
    ("motion: {role_priorities: {OWNER: 5, ADMIN: 9}}", "name the same role"),
])
def test_two_names_of_one_role_are_a_config_error(tmp_path: Path, extra: str, says: str) -> None:
    with pytest.raises(ConfigError) as info:
        make_config(tmp_path, bridge_extra=extra)
    assert says in str(info.value)


KID = "idp-v2"


@pytest.fixture
async def idp(tmp_path: Path) -> AsyncIterator[tuple[Api, Ed25519PrivateKey]]:
    key = Ed25519PrivateKey.generate()
    jwks = write_jwks(tmp_path / "jwks.json", {KID: key})
    api = await Api(tmp_path, api_extra=f"jwt: {{jwks: '{jwks}', audience: rcan-bridge}}").start()
    yield api, key
    await api.close()


def _token(api: Api, key: Ed25519PrivateKey, **claims: Any) -> dict[str, str]:
    body = {"sub": "agent-7", "aud": "rcan-bridge", "exp": api.clock.time() + 600, **claims}
    return {"Authorization": f"Bearer {sign_jwt(key, body, {'alg': 'EdDSA', 'kid': KID})}"}


@pytest.mark.parametrize("sdk_role", list(EXPECTED), ids=lambda r: r.name)
async def test_jwt_rcan_role_levels_are_the_sdks(idp: tuple[Api, Ed25519PrivateKey],
                                                 sdk_role: SdkRole) -> None:
    api, key = idp
    level = ROLE_TO_JWT_LEVEL[sdk_role]
    for claims in ({"rcan_role": level}, {"role": sdk_role.name},
                   {"role": sdk_role.name, "rcan_role": level}):
        status, body = await api.call("POST", "/api/command", body={"action": "stop"},
                                      headers=_token(api, key, **claims))
        assert status == (200 if EXPECTED[sdk_role] != "GUEST" else 403), (claims, body)
        assert api.entry(body["audit_id"])["role"] == EXPECTED[sdk_role], claims


async def test_m2m_trusted_is_refused_unless_configured(idp: tuple[Api, Ed25519PrivateKey],
                                                        tmp_path: Path) -> None:
    api, key = idp
    level = ROLE_TO_JWT_LEVEL[SdkRole.M2M_TRUSTED]
    for claims in ({"rcan_role": level}, {"role": "M2M_TRUSTED"}):
        status, body = await api.call("POST", "/api/command", body={"action": "stop"},
                                      headers=_token(api, key, **claims))
        assert (status, body["reason"]) == (401, "jwt_m2m_trusted_not_configured"), body
    jwks = tmp_path / "jwks.json"
    fleet = await Api(tmp_path / "fleet", api_extra=(
        f"jwt: {{jwks: '{jwks}', audience: rcan-bridge, m2m_trusted_role: OPERATOR}}")).start()
    try:
        status, body = await fleet.call("POST", "/api/command", body=MOVE,
                                        headers=_token(fleet, key, rcan_role=level))
        assert status == 200 and fleet.entry(body["audit_id"])["role"] == "USER", body
    finally:
        await fleet.close()


@pytest.mark.parametrize("claims", [
    {"role": "OPERATOR", "rcan_role": 3.0},  # two roles
    {"rcan_role": 3.5}, {"rcan_role": True}, {"rcan_role": "3"}, {},
])
async def test_unclear_jwt_roles_are_refused(idp: tuple[Api, Ed25519PrivateKey],
                                             claims: dict[str, Any]) -> None:
    api, key = idp
    status, body = await api.call("POST", "/api/command", body={"action": "stop"},
                                  headers=_token(api, key, **claims))
    assert (status, body["reason"]) == (401, "jwt_claims"), body


async def test_the_estop_is_open_to_every_role(idp: tuple[Api, Ed25519PrivateKey]) -> None:
    """The SDK's scope table puts `estop` at CREATOR; here a GUEST-level token stops."""
    assert SCOPE_MIN_ROLE["estop"] is SdkRole.CREATOR
    api, key = idp
    status, body = await api.call("POST", "/api/command", headers=_token(
        api, key, rcan_role=ROLE_TO_JWT_LEVEL[SdkRole.GUEST]),
        body=make_estop_message(ruri=TARGET, reason="anyone"))
    assert (status, body["outcome"]) == (200, "executed") and api.gov.latch.latched
