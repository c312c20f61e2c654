"""`bridge.skills` (what an RCAN INVOKE may run): checked against the action registry when the
config loads, every problem with its key path and line."""

from __future__ import annotations

import pytest

from rcan_rtps.config import ConfigError, loads_config

CONFIG = """\
robot: {ruri: rcan://registry.local/clearpath/husky/a200-0001}
bridge:
  api: {auth_token_env: RCAN_CHECK_TOKEN}
  safety: {max_linear_vel: 1.0, max_angular_vel: 1.0}
  skills:
%s
"""
ENV = {"RCAN_CHECK_TOKEN": "t" * 32}


def load(*skills: str) -> object:
    return loads_config(CONFIG % "\n".join(f"    {s}" for s in skills), env=ENV)


def test_skills_load_with_their_fixed_and_allowed_parameters() -> None:
    config = load("go_home: {action: navigate, params: {x: 0, y: 0, yaw: 0}}",
                  "com.example.go_to: {action: navigate, allow: [x, y, yaw], description: hi}")
    skills = config.bridge.skills  # type: ignore[attr-defined]
    assert skills["go_home"].params == {"x": 0, "y": 0, "yaw": 0}
    assert skills["com.example.go_to"].allow == ["x", "y", "yaw"]


@pytest.mark.parametrize(("skill", "path", "says"), [
    ("a: {action: navigate, params: {x: 0, zz: 1}, allow: [y, yaw]}", "skills.a",
     "zz: not a parameter of navigate"),
    ("a: {action: navigate, params: {x: 0}, allow: [x, y, yaw]}", "skills.a",
     "x: both fixed"),
    ("a: {action: navigate, allow: [x]}", "skills.a", "y, yaw: required by navigate"),
    ("a: {action: navigate, params: {x: far}, allow: [y, yaw]}", "skills.a", "params.x"),
    ("a: {action: estop}", "skills.a.action", "Invalid enum value 'estop'"),
    ("a: {action: fly}", "skills.a.action", "Invalid enum value 'fly'"),
    ("Go-Home: {action: navigate, allow: [x, y, yaw]}", "skills.Go-Home", "regex"),
    ("a: {action: navigate, allow: [x, y, yaw], speed: 1}", "skills.a.speed", "unknown key"),
])
def test_a_skill_the_registry_cannot_run_is_refused(skill: str, path: str, says: str) -> None:
    with pytest.raises(ConfigError) as caught:
        load(skill)
    issues = caught.value.issues
    assert [i.path for i in issues] == [f"$.bridge.{path}"], issues
    assert says in issues[0].message and issues[0].line == 6, issues
