"""The conformance command takes the OWNER's token however it looks: a token may begin with
`-` (`--token=-…`), or stay off the command line (`--token-env VAR`); the demo never prints
one that begins with `-` (a CI run failed when 1 in 64 did and `--token -…` read as an
option)."""

from __future__ import annotations

import pytest

from rcan_rtps.bridge.demo import demo_tokens, fresh_demo_token
from rcan_rtps.cli.conformance_cmd import _conformance
from rcan_rtps.cli.main import parse_args

pytestmark = pytest.mark.offline


def test_a_token_beginning_with_a_dash_is_taken_after_an_equals_sign() -> None:
    args = parse_args(["conformance", "--url", "http://127.0.0.1:1", "--token=-abc",
                       "--token-for", "USER=-def"])
    assert args.token == "-abc" and args.token_for == [("USER", "-def")]


def test_the_owner_token_comes_from_one_place(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):  # both
        parse_args(["conformance", "--url", "u", "--token", "t", "--token-env", "V"])
    with pytest.raises(SystemExit):  # neither
        parse_args(["conformance", "--url", "u"])
    assert "--token" in capsys.readouterr().err


def test_an_unset_token_variable_is_a_clear_error(monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.delenv("RCAN_TEST_NO_SUCH_TOKEN", raising=False)
    args = parse_args(["conformance", "--url", "http://127.0.0.1:1",
                       "--token-env", "RCAN_TEST_NO_SUCH_TOKEN"])
    assert _conformance(args) == 2
    assert "RCAN_TEST_NO_SUCH_TOKEN: that variable is not set" in capsys.readouterr().err


def test_demo_tokens_never_begin_with_a_dash_and_keep_a_given_one() -> None:
    assert all(not fresh_demo_token().startswith("-") for _ in range(500))
    assert len(set(fresh_demo_token() for _ in range(100))) == 100
    given = demo_tokens({"RCAN_BRIDGE_TOKEN": "-mine-0123456789abcdef"})
    assert "-mine-0123456789abcdef" in given.values()
