"""What a new user meets first, without a ROS graph: checks, errors and help that explain."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from rcan_rtps.cli.main import main
from rcan_rtps.ros.errors import WireError, seconds
from rcan_rtps.ros.participant import resolve_domain_id

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "turtlebot4.rcan.yaml"
TOKEN_VARS = ("RCAN_BRIDGE_TOKEN", "RCAN_OPS_TOKEN", "RCAN_AGENT_TOKEN", "RCAN_DASHBOARD_TOKEN",
              "RCAN_VIEWER_TOKEN")


def test_config_check_names_unset_token_variables(monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    for name in TOKEN_VARS:
        monkeypatch.delenv(name, raising=False)
    assert main(["config", "check", str(EXAMPLE)]) == 1
    err = capsys.readouterr().err
    assert "run` would fail here" in err and "RCAN_OPS_TOKEN" in err and "--file-only" in err
    assert main(["config", "check", "--file-only", str(EXAMPLE)]) == 0
    for name in TOKEN_VARS:
        monkeypatch.setenv(name, name * 2)  # each principal its own token
    assert main(["config", "check", str(EXAMPLE)]) == 0
    assert ": ok (" in capsys.readouterr().out


def test_config_check_names_the_file_in_yaml_errors(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "robot.rcan.yaml"
    bad.write_text("robot: [1\n")
    assert main(["config", "check", str(bad)]) == 1
    err = capsys.readouterr().err
    assert f'in "{bad}"' in err and "<unicode string>" not in err


def test_interface_show_hides_the_empty_placeholder(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["interface", "show", "std_srvs/srv/Trigger"]) == 0
    out = capsys.readouterr().out
    assert "structure_needs_at_least_one_member" not in out
    assert out.splitlines()[0] == "---" and "success" in out


def test_a_short_name_shows_the_one_service_or_action_of_that_name(
        capsys: pytest.CaptureFixture[str]) -> None:
    """`pkg/T` was read as the message `pkg/msg/T` only: a service or action named short was
    'unknown type'."""
    assert main(["interface", "show", "std_srvs/Trigger"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0] == "---" and "boolean success" in out
    assert main(["interface", "show", "nav2_msgs/NavigateToPose"]) == 0
    assert "PoseStamped pose" in capsys.readouterr().out
    assert main(["interface", "show", "std_msgs/String"]) == 0  # a message first, as before
    assert capsys.readouterr().out == "string data\n"


def test_a_package_and_kind_is_no_type(capsys: pytest.CaptureFixture[str]) -> None:
    """It said "unknown type 'nav_msgs/msg/msg'"."""
    assert main(["interface", "show", "nav_msgs/msg"]) == 1
    err = capsys.readouterr().err
    assert "unknown type 'nav_msgs/msg'" in err and "nav_msgs/msg/msg" not in err
    assert "nav_msgs/msg/" in err  # the package's messages suggested


def test_an_unbundled_type_points_at_idl_path(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["interface", "show", "my_msgs/action/Fibonacci"]) == 1
    err = capsys.readouterr().err
    assert "package 'my_msgs' is not in the bundled IDL" in err
    assert "--idl-path <ros>/share" in err and "example_interfaces/action/Fibonacci" in err


def test_ros_domain_id_must_be_a_number(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROS_DOMAIN_ID", "abc")
    with pytest.raises(WireError, match="ROS_DOMAIN_ID='abc' is not a domain id"):
        resolve_domain_id()
    assert resolve_domain_id(None, {"ROS_DOMAIN_ID": "7"}) == 7
    assert resolve_domain_id(None, {}) == 0


def test_run_sim_refuses_a_bad_ros_domain_id(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("ROS_DOMAIN_ID", "abc")
    assert main(["run", "--sim", "--no-mdns", "--state-dir", str(tmp_path)]) == 1
    assert "is not a domain id" in capsys.readouterr().err


@pytest.mark.parametrize(("duration", "text"), [(0.999997, "1 s"), (0.5, "0.5 s"),
                                                (2.25, "2.2 s"), (10.0, "10 s"), (5, "5 s")])
def test_durations_read_as_people_write_them(duration: float, text: str) -> None:
    assert seconds(duration) == text


def _agent(url: str, token: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "RCAN_URL": url, "RCAN_TOKEN": token}
    return subprocess.run([sys.executable, str(ROOT / "examples" / "agent_client.py")],
                          capture_output=True, text=True, env=env, timeout=60)


def test_agent_client_without_a_server_says_so() -> None:
    agent = _agent("http://127.0.0.1:9", "some-token")
    assert agent.returncode == 1
    assert "cannot reach the bridge" in agent.stderr and "Traceback" not in agent.stderr


def _operator(url: str, token: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "RCAN_URL": url, "RCAN_TOKEN": token}
    return subprocess.run([sys.executable, str(ROOT / "examples" / "operator_approve.py"),
                           "--yes"], capture_output=True, text=True, env=env, timeout=60)


def test_operator_approve_without_a_server_says_so() -> None:
    operator = _operator("http://127.0.0.1:9", "some-token")
    assert operator.returncode == 1
    assert "cannot reach the bridge" in operator.stderr and "Traceback" not in operator.stderr
    assert len(operator.stderr.splitlines()) == 1


def test_operator_approve_without_a_token_says_which() -> None:
    operator = _operator("http://127.0.0.1:9", "")
    assert operator.returncode == 2
    assert "set RCAN_TOKEN to an OWNER token" in operator.stderr


@pytest.mark.parametrize("values", ["{data: true", "{data: [1, 2}", "data: {a: 1]"])
def test_values_that_are_not_yaml_are_one_line(values: str,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """A bracket left open printed PyYAML's five-line report, '<unicode string>' and a caret
    included, after a '<message>: ' that named no field."""
    assert main(["service", "call", "/x", "std_srvs/srv/SetBool", values]) == 1
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1, err
    assert err.startswith("rcan-rtps: error: VALUES is not valid YAML: ")
    assert "<unicode string>" not in err and "<message>" not in err and "column " in err


def test_a_second_run_on_a_port_in_use_says_what_to_do(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The README's two commands, run twice: the second `run --sim` said only the errno."""
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        assert main(["run", "--sim", "--no-mdns", "--port", str(port),
                     "--state-dir", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1, err
    assert f"cannot listen on 127.0.0.1:{port}: Address already in use" in err
    assert "another `rcan-rtps run`" in err and "--port" in err
