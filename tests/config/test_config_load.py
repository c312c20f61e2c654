"""`.rcan.yaml` loading: defaults, env fallbacks, every error with key path and line, CLI."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from rcan_rtps.cli import config_cmd
from rcan_rtps.config import ConfigError, load_config, loads_config
from rcan_rtps.config._load import MAX_CONFIG_BYTES

REPO = Path(__file__).resolve().parents[2]
MINIMAL = """\
robot:
  ruri: rcan://registry.local/clearpath/husky/a200-0001
bridge:
  api: {auth_token_env: RCAN_BRIDGE_TOKEN}
  safety: {max_linear_vel: 1.5, max_angular_vel: 1.0}
"""


def issues_of(text: str) -> list[tuple[str, int | None, str]]:
    with pytest.raises(ConfigError) as info:
        loads_config(text, env={})
    return [(i.path, i.line, i.message) for i in info.value.issues]


@pytest.mark.parametrize("name", ["mobile-base.rcan.yaml", "arm.rcan.yaml"])
def test_examples_load(name: str) -> None:
    config = load_config(REPO / "config" / name, env={})
    assert config.bridge.safety.max_linear_vel > 0
    assert Path(config.bridge.audit.path).is_absolute()


def test_defaults_from_the_profile() -> None:
    config = loads_config(MINIMAL, env={})
    ros2, hitl, safety = config.bridge.ros2, config.bridge.hitl, config.bridge.safety
    assert (ros2.domain_id, ros2.distro, ros2.telemetry_rate_hz) == (0, "jazzy", 10.0)
    assert ros2.cmd_vel_type == "geometry_msgs/msg/Twist"
    assert ros2.nav_frame_id == "map"
    assert hitl.timeout_seconds == 300.0
    assert hitl.require_distinct_approver is False
    assert safety.session_timeout_s == 2.0
    assert safety.velocity_exceed_deny is True
    assert config.bridge.api.port == 8765
    # not the bridge spec's 0.0.0.0: loopback unless the deployment opts in to a network
    # (docs/governance.md, "Decisions where the profile is silent": api.host)
    assert config.bridge.api.host == "127.0.0.1"


def test_domain_and_distro_fall_back_to_ros_env() -> None:
    config = loads_config(MINIMAL, env={"ROS_DOMAIN_ID": "42", "ROS_DISTRO": "humble"})
    assert (config.bridge.ros2.domain_id, config.bridge.ros2.distro) == (42, "humble")
    explicit = MINIMAL + "  ros2: {domain_id: 7, distro: kilted}\n"
    config = loads_config(explicit, env={"ROS_DOMAIN_ID": "42", "ROS_DISTRO": "humble"})
    assert (config.bridge.ros2.domain_id, config.bridge.ros2.distro) == (7, "kilted")


def test_bad_ros_domain_env_is_reported() -> None:
    with pytest.raises(ConfigError) as info:
        loads_config(MINIMAL, env={"ROS_DOMAIN_ID": "x"})
    assert info.value.issues[0].path == "$.bridge.ros2.domain_id"


def test_every_error_is_reported_with_path_and_line() -> None:
    text = """\
robot:
  ruri: rcan://BAD
bridge:
  ros2: {domain_id: 999, distro: rolling, cmd_vel_topic: "bad topic"}
  api:
    principals:
      - {name: a, role: SUPERUSER, token_env: A}
      - {name: b, role: USER, token_env: B, token_sha256: %s}
      - {name: c, role: USER, token: hunter2}
  safety:
    max_linear_vel: 1.0
    max_angular_vel: .nan
    workspace: [[0, 0], [1, 1], [2, 2]]
  rbac: {action_roles: {estop: USER}}
  bogus: 1
""" % ("a" * 64)
    got = {(path, line) for path, line, _ in issues_of(text)}
    assert got == {
        ("$.robot.ruri", 2),
        ("$.bridge.ros2.domain_id", 4),
        ("$.bridge.ros2.distro", 4),
        ("$.bridge.ros2.cmd_vel_topic", 4),
        ("$.bridge.api.principals[0].role", 7),
        ("$.bridge.api.principals[1]", 8),
        ("$.bridge.api.principals[2].token", 9),
        ("$.bridge.api.principals[2]", 9),  # ...and so it has no token at all
        ("$.bridge.safety.max_angular_vel", 12),
        ("$.bridge.safety.workspace", 13),
        ("$.bridge.rbac.action_roles", 14),
        ("$.bridge.bogus", 15),
    }


def test_plaintext_token_message_says_what_to_use() -> None:
    text = MINIMAL.replace("{auth_token_env: RCAN_BRIDGE_TOKEN}",
                           "{auth_token: s3cret, auth_token_env: T}")
    [(path, line, message)] = issues_of(text)
    assert (path, line) == ("$.bridge.api.auth_token", 4)
    assert "token_env or token_sha256" in message


@pytest.mark.parametrize(
    ("workspace", "problem"),
    [
        ("[[0, 0], [1, 0]]", "at least 3"),
        ("[[0, 0], [1, 1], [2, 2]]", "zero area"),
        ("[[0, 0], [2, 2], [2, 0], [0, 2]]", "crosses itself"),
        ("[[0, 0], [1, 0], [1, .inf]]", "non-finite"),
    ],
)
def test_degenerate_workspaces_are_rejected(workspace: str, problem: str) -> None:
    text = MINIMAL.replace("1.0}", f"1.0, workspace: {workspace}}}")
    [(path, line, message)] = issues_of(text)
    assert (path, line) == ("$.bridge.safety.workspace", 5)
    assert problem in message


def test_missing_sections_and_auth() -> None:
    issues = issues_of("robot: {ruri: 'rcan://r/a/b/abcdefgh'}\nbridge: {api: {}}\n")
    assert {(p, line) for p, line, _ in issues} == {("$.bridge.api", 2), ("$.bridge.safety", 2)}


def test_yaml_syntax_error_has_a_line() -> None:
    [(path, line, message)] = issues_of("robot:\n  ruri: [unclosed\nbridge: {}\n")
    assert path == "$" and line == 3 and "YAML" in message


def test_top_level_must_be_a_mapping() -> None:
    assert issues_of("- 1\n")[0][0] == "$"


def run_cli(*argv: str) -> int:
    parser = argparse.ArgumentParser()
    config_cmd.register(parser.add_subparsers(required=True))
    args = parser.parse_args(list(argv))
    code: int = args.func(args)
    return code


def test_cli_check_ok_and_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # --file-only: the token variables it names are not set here
    assert run_cli("config", "check", "--file-only",
                   str(REPO / "config" / "mobile-base.rcan.yaml")) == 0
    bad = tmp_path / "bad.rcan.yaml"
    bad.write_text(MINIMAL.replace("1.5", "-1").replace("ruri: rcan", "ruri: RCAN"))
    assert run_cli("config", "check", str(bad)) == 1
    err = capsys.readouterr().err
    assert f"{bad}:line 2: $.robot.ruri" in err
    assert f"{bad}:line 5: $.bridge.safety.max_linear_vel" in err
    assert "Traceback" not in err
    assert run_cli("config", "check", str(tmp_path / "missing.yaml")) == 1
    bad.write_bytes(b"\xff\xfe")
    assert run_cli("config", "check", str(bad)) == 1


def test_a_file_too_large_to_be_a_config_is_refused_unread(tmp_path: Path) -> None:
    # Red team 18: a 60 MB file took minutes and /dev/zero ended in a MemoryError traceback,
    # both read whole before YAML saw a byte. Now reading stops past the limit.
    big = tmp_path / "big.rcan.yaml"
    big.write_text(MINIMAL + ("# padding\n" * (MAX_CONFIG_BYTES // 10 + 1)))
    with pytest.raises(ConfigError) as info:
        load_config(big)
    [issue] = info.value.issues
    assert issue.path == "$" and f"more than {MAX_CONFIG_BYTES} bytes" in issue.message
    with pytest.raises(ConfigError, match="more than"):
        load_config("/dev/zero")  # endless: only the limit's worth is read


def test_a_file_just_under_the_limit_loads(tmp_path: Path) -> None:
    config = tmp_path / "padded.rcan.yaml"
    padding = "#" * (MAX_CONFIG_BYTES - len(MINIMAL.encode()) - 1) + "\n"
    config.write_text(MINIMAL + padding)
    assert config.stat().st_size == MAX_CONFIG_BYTES
    assert load_config(config, env={}).bridge.safety.max_linear_vel == 1.5


def test_the_sample_size_bound_is_configured_within_cyclones_range() -> None:
    """`ros2.max_sample_bytes`: 256 MiB unless set; below 64 KiB (no ROS graph would work)
    or past Cyclone's 32-bit size it is an error naming the key."""
    assert loads_config(MINIMAL, env={}).bridge.ros2.max_sample_bytes == 256 << 20
    set_to = MINIMAL + "  ros2: {max_sample_bytes: 16777216}\n"
    assert loads_config(set_to, env={}).bridge.ros2.max_sample_bytes == 16 << 20
    for bad in (1000, 1 << 31):
        [(path, _line, _message)] = issues_of(MINIMAL + f"  ros2: {{max_sample_bytes: {bad}}}\n")
        assert path == "$.bridge.ros2.max_sample_bytes"
