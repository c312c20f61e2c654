"""§16.1 AI accountability (issue 24, item 8): an AI command without a model is refused and
audited; `bridge.ai.agents` binds principals to the models they may name; stops are exempt
(executed, with a warning); `config check` refuses bad bindings."""

from __future__ import annotations

from pathlib import Path

import pytest
from govhelpers import PLANNER, Harness, command, principal

from rcan_rtps.cli.main import main
from rcan_rtps.config import ConfigError, loads_config
from rcan_rtps.governance import Governor
from rcan_rtps.governance.ai import AiPolicy
from rcan_rtps.rcan import ErrorCode, Outcome, Role

MOVE = {"linear_x": 0.1, "duration_s": 0.5}


@pytest.mark.parametrize("ai", [{"confidence": 0.9}, {"ai_provider": "openai"},
                                {"thought_id": "t-1"}, {"ai_model": "", "confidence": 0.9}],
                         ids=["confidence", "provider", "thought", "empty-model"])
async def test_an_ai_command_without_a_model_is_refused_and_audited(
        gov: Governor, harness: Harness, ai: dict[str, object]) -> None:
    d = await gov.decide(command("move", MOVE, **ai), PLANNER)
    assert (d.http_status, d.outcome, d.error_code, d.reason) == (
        400, Outcome.DENIED, ErrorCode.AUDIT_INCOMPLETE_AI_IDENTITY, "ai_model_required")
    entry = harness.entries[-1]
    assert (entry["event"], entry["deny_reason"]) == (
        "COMMAND_REJECTED", "AUDIT_INCOMPLETE_AI_IDENTITY:ai_model_required")
    assert entry["ai"]["model"] in (None, "")
    assert harness.dispatcher.calls == []


async def test_with_a_model_or_without_ai_it_goes_ahead(gov: Governor) -> None:
    d = await gov.decide(command("move", MOVE, ai_model="planner-7b", confidence=0.9), PLANNER)
    assert d.outcome is Outcome.EXECUTED
    d = await gov.decide(command("move", MOVE), PLANNER)  # a human's command
    assert d.outcome is Outcome.EXECUTED


async def test_a_stop_without_a_model_still_stops(gov: Governor) -> None:
    for action in ("stop", "estop"):
        d = await gov.decide(command(action, confidence=0.99), PLANNER)
        assert d.outcome is Outcome.EXECUTED, action
        assert d.warnings and "ai_model_required" in d.warnings[-1], d.warnings


AGENT = principal("agent-7", Role.USER)


def test_agents_keep_to_their_models() -> None:
    policy = AiPolicy({"agent-7": ["planner-7b", "planner-8b"]})
    ok = command("move", MOVE, ai_model="planner-8b", confidence=0.9)
    assert policy.check(ok, AGENT) is None
    other = policy.check(command("move", MOVE, ai_model="gpt-4o"), AGENT)
    assert other is not None and (other.http_status, other.error_code, other.reason) == (
        403, ErrorCode.INSUFFICIENT_PRIVILEGES, "ai_model_not_allowed")
    # a bound agent's command without AI identity is not a human's: it must name its model
    bare = policy.check(command("move", MOVE), AGENT)
    assert bare is not None and bare.reason == "ai_model_required"
    # others are not bound
    assert policy.check(command("move", MOVE, ai_model="gpt-4o"), PLANNER) is None


CONFIG = """\
robot: {ruri: rcan://registry.local/clearpath/husky/v1/a200-0001}
bridge:
  api:
    principals:
      - {name: agent-7, role: USER, token_env: T}
    %(api)s
  safety: {max_linear_vel: 1.0, max_angular_vel: 1.0}
  audit: {path: audit.jsonl, key_path: audit.key}
  ai:
    agents: %(agents)s
"""


def _config(agents: str, api: str = "") -> str:
    return CONFIG % {"agents": agents, "api": api}


def test_the_binding_loads_from_config() -> None:
    config = loads_config(_config("{agent-7: [planner-7b]}"), env={"T": "x" * 32})
    assert config.bridge.ai.agents == {"agent-7": ["planner-7b"]}


@pytest.mark.parametrize(("agents", "api", "says"), [
    ("{agent-8: [m]}", "", "not in `api.principals`"),
    ("{agent-7: []}", "", "bound to no model"),
    ("{agent-7: [m, m]}", "", "more than once"),
    ("{agent-7: ['']}", "", "$.bridge.ai.agents"),
    ("{'jwt:https://idp/x': [m]}", "", "no `api.jwt`"),
    ("[agent-7]", "", "$.bridge.ai.agents"),
])
def test_config_check_refuses_bad_bindings(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                           monkeypatch: pytest.MonkeyPatch, agents: str,
                                           api: str, says: str) -> None:
    monkeypatch.setenv("T", "x" * 32)
    path = tmp_path / "robot.rcan.yaml"
    path.write_text(_config(agents, api))
    assert main(["config", "check", str(path)]) == 1
    assert says in capsys.readouterr().err
    with pytest.raises(ConfigError):
        loads_config(_config(agents, api), env={"T": "x" * 32})
