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


def test_an_empty_token_is_named_as_given(capsys: pytest.CaptureFixture[str]) -> None:
    """`--token ''` was reported as `--token-env None: that variable is not set`."""
    args = parse_args(["conformance", "--url", "http://127.0.0.1:1", "--token", ""])
    assert _conformance(args) == 2
    err = capsys.readouterr().err
    assert "--token: empty" in err and "None" not in err


@pytest.mark.parametrize("given", [["--token", "rcan_abc\n"], ["--token-env", "RCAN_TEST_TOKEN"],
                                   ["--token", "t", "--token-for", "USER=rcan_def\r\n"]])
def test_a_token_with_a_line_end_is_a_clear_error(
        given: list[str], monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """A token read with its line end (a variable filled from a file) crashed the command
    with aiohttp's ValueError (header injection) at the first request, a traceback."""
    monkeypatch.setenv("RCAN_TEST_TOKEN", "rcan_abc\n")
    try:
        args = parse_args(["conformance", "--url", "http://127.0.0.1:1", *given])
    except SystemExit as exit_:  # --token-for: argparse's own error
        assert exit_.code == 2
    else:
        assert _conformance(args) == 2
    err = capsys.readouterr().err
    assert "control character" in err and "rcan_abc" not in err and "rcan_def" not in err


def test_a_bridge_that_does_not_answer_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    """A wrong --url (or a bridge not started) was 24 FAIL lines of the same connection error
    and 'not conformant': the run never reached a case."""
    args = parse_args(["conformance", "--url", "http://127.0.0.1:1", "--token", "t" * 32])
    assert _conformance(args) == 2
    out, err = capsys.readouterr()
    assert "FAIL" not in out and len(err.splitlines()) == 1
    assert "cannot reach the bridge at http://127.0.0.1:1" in err
