"""No approver is below the role that may issue what it approves (red team 22 left this open:
`rbac.hitl_approver_role` or a gate's `authorized_roles` set to GUEST loaded, and a viewer
approved an AI's motion). The config refuses an approver role written below it (tests/config/
test_approver_roles.py); the default approver is raised to it per action, here: an action
whose role `rbac.action_roles` raised above `hitl_approver_role` is approved at its own role."""

from __future__ import annotations

from govhelpers import CONFIG, OPS, RURI, Harness, command, principal

from rcan_rtps.config import loads_config
from rcan_rtps.governance import AuditLog
from rcan_rtps.governance.governor import Governor
from rcan_rtps.rcan import ErrorCode, Outcome, Role

ARM = {"joints": ["shoulder"], "positions": [0.1], "duration_s": 2.0}
RBAC = "  rbac: {hitl_approver_role: USER, action_roles: {arm_joint: OWNER}}\n"
AGENT = principal("agent", Role.OWNER)  # may issue an arm move; its low confidence holds it
USER = principal("user", Role.USER)


async def _governor(harness: Harness) -> Governor:
    text = CONFIG % {"ruri": RURI, "dir": harness.tmp, "gates": "[]", "safety_extra": "",
                     "hitl_timeout": 300,
                     "hitl_extra": "confidence_gate: {min_confidence: 0.9, on_fail: escalate}"}
    config = loads_config(text + RBAC, env={})
    log = await AuditLog.open(config.bridge.audit.path, config.bridge.audit.key_path,
                              ruri=RURI, clock=harness.clock)
    harness.logs.append(log)
    gov = Governor.from_config(config, audit=log, dispatcher=harness.dispatcher,
                               clock=harness.clock)
    harness.governors.append(gov)
    return gov


async def test_an_action_raised_above_the_default_approver_is_approved_at_its_role(
        harness: Harness) -> None:
    gov = await _governor(harness)
    held = await gov.decide(command("arm_joint", ARM, confidence=0.2, ai_model="m"), AGENT)
    assert held.outcome is Outcome.PENDING_AUTH
    assert gov.pending()[0].requires_auth_from_role == "OWNER"
    refused = await gov.authorize(held.pending_id or "", USER)
    assert (refused.http_status, refused.error_code) == (403, ErrorCode.INSUFFICIENT_PRIVILEGES)
    assert refused.reason == "to approve it needs OWNER or higher", refused.reason
    assert harness.dispatcher.calls == []  # the USER released nothing
    approved = await gov.authorize(held.pending_id or "", OPS)
    assert approved.outcome is Outcome.EXECUTED
    assert [a for a, _ in harness.dispatcher.calls] == ["arm_joint"]


async def test_an_action_at_or_below_the_default_approver_keeps_it(harness: Harness) -> None:
    gov = await _governor(harness)
    held = await gov.decide(command("move", {"linear_x": 0.1}, confidence=0.2, ai_model="m"),
                            AGENT)
    assert held.outcome is Outcome.PENDING_AUTH
    assert gov.pending()[0].requires_auth_from_role == "USER"
    assert (await gov.authorize(held.pending_id or "", USER)).outcome is Outcome.EXECUTED
