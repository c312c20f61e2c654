"""A Ctrl-C while the command's modules load is one line and exit code 130, whatever the
interpreter wrapped it in (CI once showed a RuntimeError traceback: the interrupt landed in
a `__set_name__` of a cyclonedds class, which Python 3.11 wraps)."""

from __future__ import annotations

import argparse
from typing import Any, NoReturn

import pytest

from rcan_rtps.cli import main as cli


class _InterruptedDescriptor:
    def __set_name__(self, owner: type, name: str) -> NoReturn:
        raise KeyboardInterrupt


def _load_a_class_when_ctrl_c_lands(argv: Any = None) -> argparse.Namespace:
    type("Entity", (), {"_get_subscriber": _InterruptedDescriptor()})  # as cyclonedds.core
    raise AssertionError("unreachable: the class body raised")


def _import_error_during_ctrl_c(argv: Any = None) -> argparse.Namespace:
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt as exc:
        raise ImportError("partially initialized module", name="cyclonedds") from exc


@pytest.mark.parametrize("load", [_load_a_class_when_ctrl_c_lands, _import_error_during_ctrl_c])
def test_ctrl_c_in_a_wrapped_exception_is_one_line(
        load: Any, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(cli, "parse_args", load)
    assert cli.main(["run"]) == cli.EXIT_INTERRUPTED
    err = capsys.readouterr().err
    assert err == "rcan-rtps: interrupted\n", err


def test_a_bug_that_is_not_an_interrupt_still_raises(monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(argv: Any = None) -> argparse.Namespace:
        raise RuntimeError("a bug")

    monkeypatch.setattr(cli, "parse_args", broken)
    with pytest.raises(RuntimeError, match="a bug"):
        cli.main(["run"])
