"""Red team 22: settings that loaded and silently weakened what they seem to say. An action's
role lowered below its default (a GUEST clearing anyone's e-stop); a motion priority given to
a name no principal has (a typo, a Cyrillic look-alike: nobody gets it); two principals told
apart by case alone; one token that two principals hold."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from rcan_rtps.cli.main import main
from rcan_rtps.config import ConfigError, loads_config
from rcan_rtps.governance import AuthConfigError, ManualClock, RolePolicy, TokenAuthenticator
from rcan_rtps.rcan import Role
from rcan_rtps.rcan.actions import specs

CONFIG = """\
robot: {ruri: rcan://registry.local/acme/bot/v1/abcdefgh01}
bridge:
  api:
    principals:
      - {name: viewer, role: GUEST, token_env: RT_VIEWER}
      - {name: admin, role: OWNER, token_env: RT_OPS}
%(principals)s
  safety: {max_linear_vel: 1.0, max_angular_vel: 1.0}
%(extra)s
"""


def _config(extra: str = "", principals: str = "") -> str:
    return CONFIG % {"extra": extra, "principals": principals}


def _refusal(text: str) -> tuple[str, str]:
    with pytest.raises(ConfigError) as info:
        loads_config(text, env={})
    [issue] = info.value.issues
    return issue.path, issue.message


# -- action roles: raised, never lowered ------------------------------------------------------


@pytest.mark.parametrize(("action", "role", "default"), [
    ("clear_estop", "GUEST", "OWNER"),  # any viewer could clear an e-stop an operator raised
    ("clear_estop", "LEASEE", "OWNER"),
    ("clear_estop", "CONTRIBUTOR", "OWNER"),  # RCAN v2's name of GUEST
    ("move", "GUEST", "USER"),
    ("arm_joint", "CONTRIBUTOR", "USER"),
    ("unlock", "GUEST", "USER"),
])
def test_an_action_role_below_its_default_is_refused(action: str, role: str,
                                                     default: str) -> None:
    """docs/actions.md: `action_roles` may raise the defaults. Before: it lowered them too."""
    path, message = _refusal(_config(f"  rbac: {{action_roles: {{{action}: {role}}}}}"))
    assert path == "$.bridge.rbac.action_roles"
    assert message == (f"{action}: {role} is below its default role {default}; a role may be "
                       "raised, never lowered")


@pytest.mark.parametrize("roles", [
    "{clear_estop: OWNER}", "{clear_estop: ADMIN}", "{clear_estop: CREATOR}",
    "{move: LEASEE, navigate: OPERATOR, stop: USER}", "{estop: GUEST}", "{estop: CONTRIBUTOR}",
])
def test_an_action_role_at_or_above_its_default_loads(roles: str) -> None:
    config = loads_config(_config(f"  rbac: {{action_roles: {roles}}}"), env={})
    policy = RolePolicy({a: Role[r] for a, r in config.bridge.rbac.action_roles.items()})
    for spec in specs():
        assert policy.required(spec.name) >= spec.default_role
    assert not policy.allows(Role.GUEST, "clear_estop")
    assert policy.allows(Role.GUEST, "estop")


def test_the_estop_rule_still_comes_first() -> None:
    path, message = _refusal(_config("  rbac: {action_roles: {estop: USER}}"))
    assert (path, message) == ("$.bridge.rbac.action_roles", "estop cannot be raised above GUEST")


# -- motion priorities name principals that exist ---------------------------------------------


@pytest.mark.parametrize("name", [
    "\u0430dmin",  # Cyrillic а: looks like `admin`, is nobody
    "Admin", "ADMIN", "admin ", "operator",
])
def test_a_motion_priority_for_no_principal_is_refused(name: str) -> None:
    """Before: loaded; the priority went to nobody, and `admin` kept its role's (a safety
    supervisor meant to preempt the planner could not)."""
    path, message = _refusal(_config(f"  motion: {{principal_priorities: {{'{name}': 100}}}}"))
    assert path == "$.bridge"
    assert message == (f"`motion.principal_priorities` names {name!r}, which is not in "
                       "`api.principals` (a JWT's principal is `jwt:<iss>/<sub>`)")


def test_a_motion_priority_for_a_jwt_principal_needs_a_jwt_issuer() -> None:
    text = _config("  motion: {principal_priorities: {'jwt:idp/planner': 20}}")
    assert _refusal(text)[1] == ("`motion.principal_priorities` names 'jwt:idp/planner', but "
                                 "there is no `api.jwt`")


def test_motion_priorities_of_configured_principals_load() -> None:
    config = loads_config(_config("  motion: {principal_priorities: {admin: 100, viewer: 1}}"),
                          env={})
    assert config.bridge.motion.principal_priorities == {"admin": 100, "viewer": 1}


def test_the_default_principal_of_auth_token_env_may_have_a_priority() -> None:
    text = _config("  motion: {principal_priorities: {default: 5}}").replace(
        "    principals:\n      - {name: viewer, role: GUEST, token_env: RT_VIEWER}\n"
        "      - {name: admin, role: OWNER, token_env: RT_OPS}\n", "    auth_token_env: RT_OPS\n")
    assert loads_config(text, env={}).bridge.motion.principal_priorities == {"default": 5}


# -- principals told apart by case alone -------------------------------------------------------


@pytest.mark.parametrize("name", ["ADMIN", "Admin", "aDmIn"])
def test_two_principals_differing_only_in_case_are_refused(name: str) -> None:
    """`admin` an OWNER and `ADMIN` a GUEST read as one in the audit log and the console."""
    extra = f"      - {{name: {name}, role: GUEST, token_env: RT_OTHER}}"
    path, message = _refusal(_config(principals=extra))
    assert path == "$.bridge.api.principals"
    assert message == f"'admin' and {name!r} differ only in case"


# -- one token, two principals ----------------------------------------------------------------

TWO = """\
robot: {ruri: rcan://registry.local/acme/bot/v1/abcdefgh01}
bridge:
  api:
    principals:
      - {name: viewer, role: GUEST, %(viewer)s}
      - {name: ops, role: OWNER, %(ops)s}
  safety: {max_linear_vel: 1.0, max_angular_vel: 1.0}
"""
TOKEN_A, TOKEN_B = "a" * 32, "b" * 32


@pytest.mark.parametrize(("viewer", "ops", "env"), [
    ("token_env: RT_A", "token_env: RT_A", {"RT_A": TOKEN_A}),  # one variable named twice
    ("token_env: RT_A", "token_env: RT_B", {"RT_A": TOKEN_A, "RT_B": TOKEN_A}),  # same value
    ("token_env: RT_A", f"token_sha256: {hashlib.sha256(TOKEN_A.encode()).hexdigest()}",
     {"RT_A": TOKEN_A}),  # a variable's token and another's digest
])
def test_one_token_of_two_principals_is_refused_by_run_and_config_check(
        viewer: str, ops: str, env: dict[str, str], tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """Before: loaded, and the token authenticated as whichever principal came last — here
    the OWNER, for a token handed out as the viewer's."""
    text = TWO % {"viewer": viewer, "ops": ops}
    config = loads_config(text, env={})
    with pytest.raises(AuthConfigError, match="have the same token") as info:
        TokenAuthenticator.from_config(config.bridge.api, config.bridge.rbac, env,
                                       clock=ManualClock())
    assert str(info.value).startswith("principals viewer ($RT_A) and ops (")
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    (tmp_path / "robot.rcan.yaml").write_text(text)
    assert main(["config", "check", str(tmp_path / "robot.rcan.yaml")]) == 1
    assert "bridge.api.principals: principals viewer ($RT_A) and ops" in capsys.readouterr().err


def test_each_principal_with_its_own_token_is_itself() -> None:
    config = loads_config(TWO % {"viewer": "token_env: RT_A", "ops": "token_env: RT_B"}, env={})
    auth = TokenAuthenticator.from_config(config.bridge.api, config.bridge.rbac,
                                          {"RT_A": TOKEN_A, "RT_B": TOKEN_B}, clock=ManualClock())
    assert auth.authenticate(TOKEN_A).role is Role.GUEST
    assert auth.authenticate(TOKEN_B).role is Role.OWNER


# -- a number told it is text -------------------------------------------------------------------


@pytest.mark.parametrize("value", ["!!str 1.0", "!!str 2", "!<tag:yaml.org,2002:str> 0.5"])
def test_a_number_tagged_as_text_is_not_told_it_lacks_a_dot(value: str) -> None:
    """Before: `!!str 1.0` was refused with "YAML reads the unquoted 1.0 as text (its floats
    need a dot ...)", advice that fits `1e3`, not a number the file itself tagged as text."""
    text = _config().replace("max_linear_vel: 1.0", f"max_linear_vel: {value}")
    path, message = _refusal(text)
    assert (path, message) == ("$.bridge.safety.max_linear_vel", "Expected `float`, got `str`")


def test_a_plain_1e3_is_still_told_why_it_is_text() -> None:
    _, message = _refusal(_config().replace("max_linear_vel: 1.0", "max_linear_vel: 1e3"))
    assert "YAML reads the unquoted 1e3 as text" in message
