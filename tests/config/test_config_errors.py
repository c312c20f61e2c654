"""Config errors from one pass over the YAML tree: every problem at once, with key path and line."""

from __future__ import annotations

import copy
import datetime
from pathlib import Path
from typing import Any

import msgspec
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rcan_rtps.config import ConfigError, RcanConfig, Ros2Config, SafetyConfig, loads_config
from rcan_rtps.config._schema import INVALID, Walker, Where

REPO = Path(__file__).resolve().parents[2]
MINIMAL = """\
robot:
  ruri: rcan://registry.local/clearpath/husky/a200-0001
bridge:
  api: {auth_token_env: RCAN_BRIDGE_TOKEN}
  safety: {max_linear_vel: 1.5, max_angular_vel: 1.0}
"""


def issues_of(text: str, env: dict[str, str] | None = None) -> list[tuple[str, int | None, str]]:
    with pytest.raises(ConfigError) as info:
        loads_config(text, env=env or {})
    return [(i.path, i.line, i.message) for i in info.value.issues]


def where_of(text: str) -> set[tuple[str, int | None]]:
    return {(path, line) for path, line, _ in issues_of(text)}


def only_issue(text: str) -> tuple[str, int | None, str]:
    [issue] = issues_of(text)
    return issue


def with_safety(extra: str) -> str:
    return MINIMAL.replace("max_angular_vel: 1.0}", f"max_angular_vel: 1.0, {extra}}}")


def test_many_errors_in_one_file_are_all_reported_with_their_lines() -> None:
    text = """\
robot:
  ruri: rcan://registry.local/clearpath/husky/a200-0001
  nmae: typo
bridge:
  ros2:
    telemetry_rate_hz: 0
    node_name: "has space"
    request_mappings: {"": cyclone, nav: zenoh}
  hitl:
    timeout_seconds: forever
    gates:
      - {action: move}
      - {action: estop}
      - {action: navigate, authorized_roles: [USER, ROOT]}
  api:
    port: 70000
    auth_token_env: RCAN_BRIDGE_TOKEN
    principals:
      - {name: ok, role: USER, token_env: OK}
      - {name: "", role: USER, token_env: X}
    max_body_bytes: 1
  safety:
    max_linear_vel: -1
    velocity_exceed_deny: 1
    workspace: [[0, 0], [1, 0, 2], [1, 1]]
  audit: []
"""
    assert where_of(text) == {
        ("$.robot.nmae", 3),
        ("$.bridge.ros2.telemetry_rate_hz", 6),
        ("$.bridge.ros2.node_name", 7),
        ("$.bridge.ros2.request_mappings.", 8),
        ("$.bridge.ros2.request_mappings.nav", 8),
        ("$.bridge.hitl.timeout_seconds", 10),
        ("$.bridge.hitl.gates[1].action", 13),
        ("$.bridge.hitl.gates[2].authorized_roles[1]", 14),
        ("$.bridge.api.port", 16),
        ("$.bridge.api.principals[1].name", 20),
        ("$.bridge.api.max_body_bytes", 21),
        ("$.bridge.safety.max_linear_vel", 23),
        ("$.bridge.safety.max_angular_vel", 22),  # missing: the line of its section
        ("$.bridge.safety.velocity_exceed_deny", 24),
        ("$.bridge.safety.workspace[1]", 25),
        ("$.bridge.audit", 26),
    }


def test_issues_are_sorted_by_line() -> None:
    text = "bridge: {bogus: 1}\nrobot: {ruri: 5}\n"
    lines = [line for _, line, _ in issues_of(text)]
    assert lines == sorted(lines)


def test_more_errors_than_the_old_retry_limit_are_all_reported() -> None:
    unknown = "".join(f"  extra_{n}: 1\n" for n in range(150))
    text = MINIMAL.replace("bridge:\n", "bridge:\n" + unknown)
    issues = issues_of(text)
    assert len(issues) == 150
    assert issues[0][:2] == ("$.bridge.extra_0", 4)
    assert issues[-1][:2] == ("$.bridge.extra_149", 153)


def test_unknown_key_suggests_a_close_name() -> None:
    path, line, message = only_issue(with_safety("max_linear_velocity: 2"))
    assert (path, line) == ("$.bridge.safety.max_linear_velocity", 5)
    assert "did you mean `max_linear_vel`" in message


def test_missing_required_key_points_at_its_section() -> None:
    text = MINIMAL.replace("max_linear_vel: 1.5, ", "")
    assert only_issue(text) == ("$.bridge.safety.max_linear_vel", 5, "missing required key")
    assert only_issue("robot: {}\n" + MINIMAL.split("\n", 2)[2])[:2] == ("$.robot.ruri", 1)


@pytest.mark.parametrize(
    ("extra", "path", "words"),
    [
        ("session_timeout_s: 0", "session_timeout_s", "Expected `float` > 0.0, got 0.0"),
        ("session_timeout_s: 3601", "session_timeout_s", "Expected `float` <= 3600.0"),
        ("estop_state_path: [a]", "estop_state_path", "Expected `str | null`, got `array`"),
        ("workspace: [[0, 0], [1, 0]]", "workspace", "at least 3"),
        ("workspace: [[0, 0], [1], [1, 1]]", "workspace[1]", "Expected `array` of length 2"),
        ("workspace: {a: 1}", "workspace", "Expected `array | null`, got `object`"),
    ],
)
def test_each_kind_of_value_error(extra: str, path: str, words: str) -> None:
    got_path, line, message = only_issue(with_safety(extra))
    assert (got_path, line) == (f"$.bridge.safety.{path}", 5)
    assert words in message


@pytest.mark.parametrize(
    ("ros2", "path", "words"),
    [
        ("domain_id: -1", "domain_id", "Expected `int` >= 0, got -1"),
        ("nav_frame_id: ''", "nav_frame_id", "Expected `str` of length >= 1"),
        (f"nav_frame_id: {'m' * 129}", "nav_frame_id", "Expected `str` of length <= 128"),
        ("node_name: 9lives", "node_name", "matching regex"),
        ("cmd_vel_type: Twist", "cmd_vel_type", "Invalid enum value 'Twist' (expected one of"),
        ("distro: 24", "distro", "Expected `str`, got `int`"),
        ("odom_topic: 'two words'", "odom_topic", "is not a valid ROS name"),
        ("request_mappings: {nav: zenoh}", "request_mappings.nav", "Invalid enum value"),
        ("request_mappings: [nav]", "request_mappings", "Expected `object`, got `array`"),
        ("request_mappings: {'': auto}", "request_mappings.", "of length >= 1"),
        ("arms: {Left: {topic: l}}", "arms.Left", "matching regex"),
        # Python's `$` matches before a last newline: these passed on 9523eb7.
        ('arms: {"left\\n": {topic: l}}', "arms.left\n", "matching regex"),
        ('arms: {left: {topic: l, joints: ["elbow\\n"]}}', "arms.left.joints[0]",
         "matching regex"),
        ("arms: {left: {topic: 'a b'}}", "arms.left.topic", "is not a valid ROS name"),
        ("arms: {left: {topic: l, joints: [a, a]}}", "arms.left.joints",
         "lists a joint more than once"),
        ("arms: {left: {joints: [a]}}", "arms.left.topic", "required"),
    ],
)
def test_each_kind_of_constraint_error(ros2: str, path: str, words: str) -> None:
    text = MINIMAL + f"  ros2: {{{ros2}}}\n"
    got_path, line, message = only_issue(text)
    assert (got_path, line) == (f"$.bridge.ros2.{path}", 6)
    assert words in message


def test_deeply_nested_and_list_item_paths() -> None:
    text = (
        MINIMAL
        + """\
  hitl:
    gates:
      - {action: move}
      - action: navigate
        authorized_roles:
          - USER
          - OWNER
          - SUPERUSER
"""
    )
    assert only_issue(text)[:2] == ("$.bridge.hitl.gates[1].authorized_roles[2]", 13)
    principals = MINIMAL.replace(
        "{auth_token_env: RCAN_BRIDGE_TOKEN}",
        "\n    principals:\n"
        "      - {name: a, role: USER, token_env: A}\n"
        "      - {name: b, role: USER, token_env: B}\n"
        "      - {name: 'not ok', role: USER, token_env: C}",
    )
    assert only_issue(principals)[:2] == ("$.bridge.api.principals[2].name", 8)


def test_a_section_checks_its_fields_even_when_a_sibling_is_wrong() -> None:
    text = with_safety("session_timeout_s: 0, workspace: [[0, 0], [1, 1], [2, 2]]")
    assert where_of(text) == {
        ("$.bridge.safety.session_timeout_s", 5),
        ("$.bridge.safety.workspace", 5),
    }


@pytest.mark.parametrize(
    ("text", "line", "words"),
    [
        ("- 1\n", 1, "expected a mapping at the top"),
        ("# a comment\njust a string\n", 2, "expected a mapping at the top"),
        ("", 1, "empty"),
        ("# nothing but a comment\n", 1, "empty"),
        ("---\n...\n", 1, "empty"),
        ("~\n", 1, "empty"),
    ],
)
def test_root_must_be_a_non_empty_mapping(text: str, line: int, words: str) -> None:
    assert only_issue(text)[:2] == ("$", line)
    assert words in only_issue(text)[2]


@pytest.mark.parametrize(
    ("text", "line"),
    [
        ("robot: {ruri: x\nbridge: {}\n", 2),
        ("robot:\n  ruri: x\n   bad: indent\n", 3),
        ("robot: *nowhere\n", 1),
        ("a: 1\n---\nb: 2\n", 2),
        ("robot: 'unterminated\n", 2),
    ],
)
def test_yaml_syntax_errors_have_a_line(text: str, line: int) -> None:
    path, got_line, message = only_issue(text)
    assert (path, got_line) == ("$", line)
    assert "not valid YAML" in message


@pytest.mark.parametrize(
    "value",
    ["!!int abc", "!!bool maybe", "2024-13-01", "!custom 1"],
)
def test_a_scalar_yaml_cannot_build_is_reported_at_its_key(value: str) -> None:
    text = MINIMAL.replace("max_linear_vel: 1.5", f"max_linear_vel: {value}")
    path, line, message = only_issue(text)
    assert (path, line) == ("$.bridge.safety.max_linear_vel", 5)
    assert "not valid YAML" in message


def test_an_unknown_tag_on_a_section_is_reported() -> None:
    text = MINIMAL.replace("safety: {", "safety: !custom {")
    assert only_issue(text)[:2] == ("$.bridge.safety", 5)
    assert "unsupported YAML tag '!custom'" in only_issue(text)[2]


def test_absurd_nesting_is_an_error_not_a_crash() -> None:
    path, _, message = only_issue("robot: " + "[" * 5000 + "]" * 5000 + "\n")
    assert path == "$" and ("nested too deeply" in message or "not valid YAML" in message)


@pytest.mark.parametrize(
    ("value", "words"),
    [
        (".nan", "got nan"),
        (".NaN", "got nan"),
        (".inf", "<= 1000000.0, got inf"),
        ("-.inf", "> 0.0, got -inf"),
        ("1.0e+400", "got inf"),  # overflows to inf when YAML reads it
        (
            "1e400",
            "Expected `float`, got `str`",
        ),  # YAML 1.1 floats need a dot and a signed exponent
        ("1" + "0" * 400, "Number out of range"),  # an int too big for a float
        ("1000001", "<= 1000000.0, got 1000001.0"),
    ],
)
def test_non_finite_and_huge_numbers_where_floats_are_bounded(value: str, words: str) -> None:
    text = MINIMAL.replace("max_linear_vel: 1.5", f"max_linear_vel: {value}")
    path, line, message = only_issue(text)
    assert (path, line) == ("$.bridge.safety.max_linear_vel", 5)
    assert words in message


def test_huge_integers_are_range_checked() -> None:
    text = MINIMAL.replace("{auth_token_env", "{port: " + "9" * 50 + ", auth_token_env")
    assert only_issue(text)[:2] == ("$.bridge.api.port", 4)
    assert "Expected `int` <= 65535" in only_issue(text)[2]


@pytest.mark.parametrize(
    ("api", "words"),
    [
        ("port: '8765'", "Expected `int`, got `str`"),
        ("port: true", "Expected `int`, got `bool`"),
        ("port: on", "Expected `int`, got `bool`"),  # YAML 1.1: on/off/yes/no are booleans
        ("port: 8765.0", "Expected `int`, got `float`"),
        ("port: null", "Expected `int`, got `null`"),
        ("port: {n: 1}", "Expected `int`, got `object`"),
        ("host: 127", "Expected `str`, got `int`: YAML reads the unquoted 127 as a number; "
                      "quote it ('127') to mean the text"),
        ("host: yes", "YAML reads the unquoted yes as a boolean; quote it ('yes')"),
        ("host: 2024-01-01", "Expected `str`, got `date`"),
        ("tls: cert.pem", "Expected `object | null`, got `str`"),
        ("principals: {}", "Expected `array`, got `object`"),
    ],
)
def test_wrong_types(api: str, words: str) -> None:
    text = MINIMAL.replace("{auth_token_env", f"{{{api}, auth_token_env")
    path, line, message = only_issue(text)
    assert path.startswith("$.bridge.api.") and line == 4
    assert words in message


def test_bool_and_number_coercions_follow_msgspec() -> None:
    assert only_issue(with_safety("velocity_exceed_deny: 1"))[2] == "Expected `bool`, got `int`"
    config = loads_config(with_safety("velocity_exceed_deny: no, session_timeout_s: 3"), env={})
    assert config.bridge.safety.velocity_exceed_deny is False
    assert config.bridge.safety.session_timeout_s == 3.0
    assert isinstance(config.bridge.safety.session_timeout_s, float)  # an int is a fine float
    workspace = loads_config(with_safety("workspace: [[0, 0], [2, 0], [0, 2]]"), env={})
    assert workspace.bridge.safety.workspace == [(0.0, 0.0), (2.0, 0.0), (0.0, 2.0)]


def test_null_means_absent_only_where_the_schema_allows_it() -> None:
    config = loads_config(MINIMAL.replace("{auth_token_env", "{tls: null, auth_token_env"), env={})
    assert config.bridge.api.tls is None
    assert only_issue(MINIMAL.replace("bridge:\n", "bridge:\n  ros2: ~\n"))[:2] == (
        "$.bridge.ros2",
        4,
    )


def test_environment_fallbacks_are_checked_like_file_values() -> None:
    issues = issues_of(MINIMAL, env={"ROS_DOMAIN_ID": "999", "ROS_DISTRO": "rolling"})
    assert {(path, line) for path, line, _ in issues} == {
        ("$.bridge.ros2.domain_id", None),
        ("$.bridge.ros2.distro", None),
    }
    config = loads_config(MINIMAL, env={"ROS_DOMAIN_ID": " 7 ", "ROS_DISTRO": "humble"})
    assert (config.bridge.ros2.domain_id, config.bridge.ros2.distro) == (7, "humble")


def test_merge_keys_read_as_yaml_does() -> None:
    text = (
        MINIMAL
        + """\
  hitl:
    confidence_gate: &gate {min_confidence: 0.5, on_fail: escalate}
  ros2:
    <<: {telemetry_rate_hz: 5, odom_topic: odom2}
    telemetry_rate_hz: 20
"""
    )
    config = loads_config(text, env={})
    assert config.bridge.ros2.telemetry_rate_hz == 20.0  # explicit beats merged
    assert config.bridge.ros2.odom_topic == "odom2"  # merged where not given
    assert config.bridge.hitl.confidence_gate is not None
    for bad_merge in ("{<<: 5}", "{<<: [{odom_topic: x}, 5]}", "&me {<<: *me}"):
        path, line, message = only_issue(MINIMAL + f"  ros2: {bad_merge}\n")
        assert (path, line) == ("$.bridge.ros2", 6)
        assert "merge" in message


def test_a_repeated_key_is_an_error_naming_both_lines() -> None:
    """Which of two values would count is a guess: a second `ros2:` block would silently
    replace the first (and with it the namespace the robot's topics are under)."""
    text = MINIMAL + "  ros2:\n    odom_topic: first\n    odom_topic: second\n"
    path, line, message = only_issue(text)
    assert (path, line) == ("$.bridge.ros2", 6)
    assert "repeated key `odom_topic` (first on line 7)" in message and "line 8" in message
    twice = MINIMAL + "  ros2: {namespace: /a}\n  ros2: {namespace: /b}\n"
    path, _, message = only_issue(twice)
    assert path == "$.bridge" and "repeated key `ros2`" in message


def test_a_value_the_walk_does_not_know_is_left_to_msgspec_and_reported_cleanly() -> None:
    class Appointment(msgspec.Struct):
        when: datetime.datetime

    info = msgspec.inspect.type_info(Appointment)
    walker = Walker()
    good = walker.value(yaml.compose("when: 2024-05-01T10:00:00Z"), info, Where("$", 1))
    assert good == Appointment(datetime.datetime(2024, 5, 1, 10, tzinfo=datetime.timezone.utc))
    assert walker.value(yaml.compose("when: soon"), info, Where("$.x", 3)) is INVALID
    [issue] = walker.issues
    assert (issue.path, issue.line) == ("$.x", 3)
    assert "datetime" in issue.message and "`$.when`" in issue.message


def test_field_checks_still_hold_outside_the_loader() -> None:
    with pytest.raises(ValueError, match="`cmd_vel_topic`: is not a valid ROS name"):
        Ros2Config(cmd_vel_topic="bad topic")
    with pytest.raises(ValueError, match="`workspace`: needs at least 3 points"):
        SafetyConfig(max_linear_vel=1, max_angular_vel=1, workspace=[(0, 0)])
    data = yaml.safe_load(MINIMAL)
    data["robot"]["ruri"] = "rcan://BAD"
    with pytest.raises(msgspec.ValidationError, match="`ruri`"):
        msgspec.convert(data, RcanConfig)


# Random mutations of a valid config: a config or a ConfigError comes back, nothing else.

VALID = yaml.safe_load((REPO / "config" / "mobile-base.rcan.yaml").read_text())
FIELDS = ["name", "role", "token_env", "action", "min_confidence", "cert", "key", "token"]
scalars = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(10**30), max_value=10**30)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12)
    | st.sampled_from(["USER", "OWNER", "move", "estop", "jazzy", "cmd_vel", "auto", "/x"])
)
junk = st.recursive(
    scalars,
    lambda inner: (
        st.lists(inner, max_size=4)
        | st.dictionaries(st.sampled_from(FIELDS) | st.text(max_size=8) | st.integers(), inner)
    ),
    max_leaves=10,
)


def paths_in(data: Any, at: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    found = [at]
    if isinstance(data, dict):
        for key, value in data.items():
            found += paths_in(value, (*at, key))
    elif isinstance(data, list):
        for index, value in enumerate(data):
            found += paths_in(value, (*at, index))
    return found


def mutate(data: Any, at: tuple[Any, ...], how: str, value: Any) -> Any:
    if not at:
        return value if how == "replace" else data
    parent = data
    for part in at[:-1]:
        parent = parent[part]
    if how == "replace":
        parent[at[-1]] = value
    elif how == "delete":
        del parent[at[-1]]
    elif isinstance(parent[at[-1]], dict):
        parent[at[-1]][f"new_{len(parent[at[-1]])}"] = value
    return data


def loads_or_config_error(text: str) -> RcanConfig | None:
    try:
        config = loads_config(text, env={})
    except ConfigError as exc:
        assert exc.issues
        assert all(issue.path.startswith("$") for issue in exc.issues)
        return None
    assert isinstance(config, RcanConfig)
    return config


def msgspec_verdict(data: Any) -> bytes | None:
    try:
        return msgspec.json.encode(msgspec.convert(data, RcanConfig))
    except msgspec.ValidationError:
        return None


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_mutated_configs_load_exactly_when_msgspec_accepts_them(data: st.DataObject) -> None:
    config = copy.deepcopy(VALID)
    for _ in range(data.draw(st.integers(min_value=1, max_value=4))):
        at = data.draw(st.sampled_from(paths_in(config)))
        how = data.draw(st.sampled_from(["replace", "delete", "add"]))
        config = mutate(config, at, how, data.draw(junk))
    loaded = loads_or_config_error(yaml.safe_dump(config, allow_unicode=True, sort_keys=False))
    # The walk and msgspec agree on every value: neither accepts what the other refuses.
    assert msgspec_verdict(config) == (None if loaded is None else msgspec.json.encode(loaded))


@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_mutated_yaml_text_never_crashes_the_loader(data: st.DataObject) -> None:
    text = (REPO / "config" / "mobile-base.rcan.yaml").read_text()
    pieces = st.sampled_from(
        [
            ":",
            "-",
            "[",
            "]",
            "{",
            "}",
            ",",
            "&a",
            "*a",
            "!!",
            "!x",
            "<<: ",
            "\n",
            "  ",
            "'",
            '"',
            "#",
            "|",
            ">",
            "?",
            "%",
            ".nan",
            "1e999",
            "~",
            "yes",
            "\t",
            "\x00",
            "é",
        ]
    )
    for _ in range(data.draw(st.integers(min_value=1, max_value=6))):
        start = data.draw(st.integers(min_value=0, max_value=len(text)))
        cut = data.draw(st.integers(min_value=0, max_value=8))
        text = text[:start] + data.draw(pieces) + text[start + cut :]
    loads_or_config_error(text)


def test_keys_that_nothing_would_honour_are_refused() -> None:
    """Issue 23 item 11: a key the bridge does not act on must not look as if it did."""
    path, _, message = only_issue(
        MINIMAL + "  hitl: {authorize_endpoint: /approve}\n")
    assert path == "$.bridge.hitl.authorize_endpoint" and "/api/hitl/authorize" in message
    loads_config(MINIMAL + "  hitl: {authorize_endpoint: /api/hitl/authorize}\n", env={})
    path, _, _ = only_issue(MINIMAL + "  rbac: {config_reload_role: OWNER}\n")
    assert path == "$.bridge.rbac.config_reload_role"


def test_unattended_move_s_is_checked() -> None:
    config = loads_config(with_safety("unattended_move_s: 1.5"), env={})
    assert config.bridge.safety.unattended_move_s == 1.5
    path, _, _ = only_issue(with_safety("unattended_move_s: 0"))
    assert path == "$.bridge.safety.unattended_move_s"


@pytest.mark.parametrize(("value", "read_as"), [("1:5", "65"), ("1:30", "90"),
                                                ("1:0:0.5", "3600.5")])
def test_a_base_60_number_is_refused_not_read_as_yaml_1_1_would(value: str, read_as: str) -> None:
    """Red team 18: YAML 1.1 reads an unquoted `1:5` as 65 (base 60): a speed limit written
    so loaded as 65 m/s, looser than any reading of what was written. Now it is an error."""
    text = MINIMAL.replace("max_linear_vel: 1.5", f"max_linear_vel: {value}")
    path, line, message = only_issue(text)
    assert (path, line) == ("$.bridge.safety.max_linear_vel", 5)
    assert f"reads the unquoted {value} as {read_as}" in message and "base 60" in message
    port = MINIMAL.replace("{auth_token_env", "{port: 1:30, auth_token_env")
    assert only_issue(port)[:2] == ("$.bridge.api.port", 4)
    operator = MINIMAL.replace("robot:\n", "robot:\n  operator: 1:30\n")
    assert "quote it ('1:30')" in only_issue(operator)[2]  # for a text, the old advice


@pytest.mark.parametrize(("key", "value", "read_as"), [
    ("max_linear_vel", "010", "8"), ("max_linear_vel", "-0_17", "-15"),
    ("session_timeout_s", "0100", "64")])
def test_a_leading_zero_octal_number_is_refused(key: str, value: str, read_as: str) -> None:
    """Red team 18: YAML 1.1 reads an unquoted `010` as 8 (octal): fewer approvals, a shorter
    or longer limit than the digits say. Now it is an error; `0x10` (explicit) still loads."""
    text = (MINIMAL.replace("max_linear_vel: 1.5", f"max_linear_vel: {value}")
            if key == "max_linear_vel" else with_safety(f"{key}: {value}"))
    path, _, message = only_issue(text)
    assert path == f"$.bridge.safety.{key}"
    assert f"reads the unquoted {value} as {read_as}" in message and "octal" in message
    gate = MINIMAL + "  hitl:\n    gates: [{action: move, approvals: 010}]\n"
    assert only_issue(gate)[0] == "$.bridge.hitl.gates[0].approvals"
    assert loads_config(with_safety("session_timeout_s: 0x10"),
                        env={}).bridge.safety.session_timeout_s == 16.0


@pytest.mark.parametrize("value", ["1e3", "2E-1", "1e400"])
def test_a_number_yaml_reads_as_text_says_so(value: str) -> None:
    """Red team 18: `max_linear_vel: 1e3` was refused as "Expected `float`, got `str`", no
    word of why a number is a string: YAML 1.1's floats need a dot and a signed exponent."""
    text = MINIMAL.replace("max_linear_vel: 1.5", f"max_linear_vel: {value}")
    path, _, message = only_issue(text)
    assert path == "$.bridge.safety.max_linear_vel"
    assert message.startswith("Expected `float`, got `str`")
    assert f"reads the unquoted {value} as text" in message and "1.0e+3" in message
    nan = MINIMAL.replace("max_linear_vel: 1.5", "max_linear_vel: nan")
    assert only_issue(nan)[2] == "Expected `float`, got `str`"  # a word, not digits


@pytest.mark.parametrize(("line", "words"), [
    ("replay_window_s: 4.9", "Expected `float` >= 5.0"),
    ("replay_window_s: 301", "Expected `float` <= 300.0"),
])
def test_the_replay_window_is_bounded_as_the_profile_says(line: str, words: str) -> None:
    """docs/rcan-profile.md §8.3: `replay_window_s` 5-300 s (a longer one keeps replays open)."""
    text = MINIMAL + f"  security: {{{line}}}\n"
    got_path, _, message = only_issue(text)
    assert got_path == "$.bridge.security.replay_window_s" and words in message


def test_an_optional_ros_name_is_checked_on_construction_too() -> None:
    """`nav_action: RosTopic | None`: the loader refused '0' but Ros2Config(nav_action='0')
    and msgspec.convert took it (Hypothesis found it: test_mutated_configs_load_exactly...)."""
    with pytest.raises(ValueError, match="`nav_action`: is not a valid ROS name"):
        Ros2Config(nav_action="0")
    assert Ros2Config(nav_action=None).nav_action is None
