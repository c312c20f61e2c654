"""Every option and positional of every `rcan-rtps` command says what it is for."""

from __future__ import annotations

import argparse
from collections.abc import Iterator

from rcan_rtps.cli.main import build_parser


def _walk(parser: argparse.ArgumentParser, path: str) -> Iterator[tuple[str, argparse.Action]]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _walk(sub, f"{path} {name}")
        else:
            yield path, action


def test_every_argument_has_help() -> None:
    missing = [f"{path}: {'/'.join(action.option_strings) or action.dest}"
               for path, action in _walk(build_parser(), "rcan-rtps")
               if not action.help or action.help == argparse.SUPPRESS]
    assert not missing, "arguments without help:\n" + "\n".join(missing)


def test_every_command_has_help() -> None:
    def commands(parser: argparse.ArgumentParser, path: str) -> Iterator[str]:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                described = {a.dest for a in action._choices_actions if a.help}
                for name, sub in action.choices.items():
                    if name not in described:
                        yield f"{path} {name}"
                    yield from commands(sub, f"{path} {name}")

    assert not list(commands(build_parser(), "rcan-rtps"))


def test_run_help_names_the_token_variables() -> None:
    text = build_parser()._subparsers._group_actions[0].choices["run"].format_help()  # type: ignore[union-attr]
    for name in ("RCAN_BRIDGE_TOKEN", "RCAN_DEMO_USER_TOKEN", "RCAN_DEMO_VIEWER_TOKEN",
                 "token_env"):
        assert name in text, name
