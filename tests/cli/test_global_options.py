"""Global options go before the verb or after it (users put them in either place)."""

from __future__ import annotations

import pytest

from rcan_rtps.cli.main import build_parser, commands_of, parse_args

pytestmark = pytest.mark.offline

SEND_GOAL = ["action", "send_goal", "/f", "test_msgs/action/Fibonacci", "{order: 3}"]


def test_after_the_verb() -> None:
    args = parse_args([*SEND_GOAL, "--idl-path", "DIR", "--domain-id", "7", "--localhost",
                       "--distro", "humble", "--log-level", "debug", "--log-format", "json"])
    assert args.idl_path == ["DIR"] and args.domain_id == 7 and args.localhost is True
    assert args.distro == "humble" and args.log_level == "debug" and args.log_format == "json"


def test_before_the_verb() -> None:
    args = parse_args(["--idl-path", "DIR", "--domain-id", "7", "--localhost", "--distro",
                       "humble", "--log-level", "debug", "--log-format", "json", *SEND_GOAL])
    assert args.idl_path == ["DIR"] and args.domain_id == 7 and args.localhost is True
    assert args.distro == "humble" and args.log_level == "debug" and args.log_format == "json"


def test_defaults_when_given_nowhere() -> None:
    args = parse_args(SEND_GOAL)
    assert args.idl_path == [] and args.domain_id is None and args.localhost is None
    assert args.distro is None and args.log_level is None and args.log_format == "text"
    assert not hasattr(args, "idl_path_after_verb")


def test_the_later_one_wins_and_idl_paths_add_up() -> None:
    args = parse_args(["--domain-id", "1", "--idl-path", "A", "--distro", "jazzy",
                       "topic", "echo", "/t", "--domain-id", "2", "--idl-path", "B"])
    assert args.domain_id == 2 and args.idl_path == ["A", "B"] and args.distro == "jazzy"


def test_every_command_takes_them_after_the_verb() -> None:
    commands = commands_of(build_parser())
    assert len(commands) > 30  # every leaf: `topic echo`, `run`, `param dump`, …
    for command in commands:
        options = {s for a in command._actions for s in a.option_strings}
        assert {"--domain-id", "--idl-path", "--localhost", "--distro", "--log-level",
                "--log-format"} <= options, command.prog
