"""An approver role written below the role its held action needs to be issued is refused
(red team 22 left `hitl_approver_role: GUEST` and `authorized_roles: [GUEST]` loading: any
viewer approved an AI's motion). `run` and `config check` load alike."""

from __future__ import annotations

from pathlib import Path

import pytest

from rcan_rtps.cli.main import main
from rcan_rtps.config import ConfigError, loads_config
from rcan_rtps.governance import HitlPolicy
from rcan_rtps.rcan import Role

CONFIG = """\
robot: {ruri: rcan://registry.local/acme/bot/v1/abcdefgh01}
bridge:
  api: {auth_token_env: RT_OPS}
  safety: {max_linear_vel: 1.0, max_angular_vel: 1.0}
%s
"""
BELOW = ("an approver must be allowed to issue what it approves")


def _refusal(extra: str) -> tuple[str, str]:
    with pytest.raises(ConfigError) as info:
        loads_config(CONFIG % extra, env={})
    [issue] = info.value.issues
    return issue.path, issue.message


@pytest.mark.parametrize("role", ["GUEST", "CONTRIBUTOR"])  # CONTRIBUTOR: RCAN v2's GUEST
def test_a_default_approver_below_every_held_action_is_refused(role: str) -> None:
    path, message = _refusal(f"  rbac: {{hitl_approver_role: {role}}}")
    assert path == "$.bridge"
    assert message == (f"`rbac.hitl_approver_role` is {role}, below USER, the lowest role "
                       f"that may issue anything a human is asked to approve: {BELOW}")


def test_a_gate_letting_a_viewer_approve_is_refused() -> None:
    path, message = _refusal(
        "  hitl: {gates: [{action: dock}, {action: move, authorized_roles: [OWNER, GUEST]}]}")
    assert path == "$.bridge"
    assert message == ("`hitl.gates[1].authorized_roles` lets GUEST approve move, which needs "
                       f"USER to be issued: {BELOW}")


def test_a_gate_below_an_action_role_raised_by_rbac_is_refused() -> None:
    extra = ("  hitl: {gates: [{action: navigate, authorized_roles: [USER]}]}\n"
             "  rbac: {action_roles: {navigate: LEASEE}}")
    assert _refusal(extra)[1] == ("`hitl.gates[0].authorized_roles` lets USER approve "
                                  f"navigate, which needs LEASEE to be issued: {BELOW}")


@pytest.mark.parametrize("extra", [
    "  rbac: {hitl_approver_role: USER}",
    "  rbac: {hitl_approver_role: OPERATOR}",  # RCAN v2's USER
    "  hitl: {gates: [{action: navigate, authorized_roles: [LEASEE]}]}\n"
    "  rbac: {action_roles: {navigate: LEASEE}}",
])
def test_approvers_at_or_above_the_issuers_role_load(extra: str) -> None:
    loads_config(CONFIG % extra, env={})


def test_the_policy_raises_the_default_approver_to_an_actions_role() -> None:
    """What the governor holds with (tests/governance/test_approver_floor.py runs it)."""
    config = loads_config(CONFIG % "  rbac: {hitl_approver_role: USER, action_roles: "
                          "{arm_joint: OWNER, dock: LEASEE}}", env={})
    policy = HitlPolicy.from_config(config.bridge.hitl, config.bridge.rbac)
    assert policy.approver_role("arm_joint") is Role.OWNER
    assert policy.approver_role("dock") is Role.LEASEE
    assert policy.approver_role("move") is Role.USER


def test_config_check_refuses_it_too(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                     monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "robot.rcan.yaml"
    path.write_text(CONFIG % "  rbac: {hitl_approver_role: GUEST}")
    monkeypatch.setenv("RT_OPS", "x" * 32)
    assert main(["config", "check", str(path)]) == 1
    assert "hitl_approver_role" in capsys.readouterr().err
