"""`--log-format json`, `--log-level`: one valid JSON object per stderr line, always."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from rcan_rtps.cli._logging import JsonFormatter
from rcan_rtps.cli.main import build_parser

BAD_CONFIG = 'robot: {ruri: "not a ruri"}\nbridge: 7\n'


def rcan_rtps(*argv: str | bytes, cwd: Path) -> subprocess.CompletedProcess[bytes]:
    """The CLI in a child process; `run` with a broken config fails before any DDS starts."""
    return subprocess.run(
        [sys.executable, "-m", "rcan_rtps", *argv],
        cwd=cwd,
        capture_output=True,
        timeout=60,
        check=False,
    )


def json_lines(stderr: bytes) -> list[dict[str, Any]]:
    lines = stderr.decode("ascii").split("\n")  # ASCII only: no stream encoding can break it
    assert lines[-1] == ""
    return [json.loads(line) for line in lines[:-1]]


def record(msg: str, *args: object, **extra: Any) -> logging.LogRecord:
    rec = logging.LogRecord("rcan_rtps.test", logging.WARNING, __file__, 1, msg, args, None)
    rec.__dict__.update(extra)
    return rec


def test_json_log_lines_from_the_cli(tmp_path: Path) -> None:
    config = tmp_path / 'ré "quoted".rcan.yaml'
    config.write_text(BAD_CONFIG)
    done = rcan_rtps(
        "--log-format", "json", "--log-level", "debug", "run", "--config", str(config), cwd=tmp_path
    )
    assert done.returncode == 1
    entries = json_lines(done.stderr)
    assert any(e["level"] == "DEBUG" for e in entries)  # --log-level debug reached the root
    error = next(e for e in entries if e["level"] == "ERROR")
    assert error["logger"] == "rcan_rtps.cli"
    assert str(config) in error["event"] and "config error(s)\n" in error["event"]
    for entry in entries:
        assert {"time", "level", "logger", "event"} <= set(entry)
        assert entry["time"].endswith("Z")


def test_json_line_for_a_path_that_is_not_utf8(tmp_path: Path) -> None:
    done = rcan_rtps(
        "--log-format",
        "json",
        "run",
        "--config",
        os.fsencode(tmp_path) + b"/no\xff-such.yaml",
        cwd=tmp_path,
    )
    assert done.returncode == 1
    (error,) = json_lines(done.stderr)
    assert "no\\xff-such.yaml" in error["event"]


def test_text_format_is_the_default_and_debug_is_off(tmp_path: Path) -> None:
    (tmp_path / "bad.rcan.yaml").write_text(BAD_CONFIG)
    done = rcan_rtps("run", "--config", "bad.rcan.yaml", cwd=tmp_path)
    assert done.returncode == 1
    assert done.stderr.decode().startswith("rcan-rtps: error: bad.rcan.yaml: 2 config error(s)")
    assert b"DEBUG" not in done.stderr


def test_help_documents_both_flags() -> None:
    text = build_parser().format_help()
    assert "--log-format {text,json}" in text
    assert "--log-level {debug,info,warning,error}" in text


def test_formatter_adds_principal_and_audit_id_when_given() -> None:
    line = JsonFormatter().format(record("e-stop %s", "sent", principal="ops", audit_id="a-1"))
    entry = json.loads(line)
    assert entry["event"] == "e-stop sent"
    assert (entry["principal"], entry["audit_id"]) == ("ops", "a-1")
    assert entry["level"] == "WARNING" and entry["logger"] == "rcan_rtps.test"
    assert "principal" not in json.loads(JsonFormatter().format(record("x", principal=None)))


def test_formatter_puts_the_exception_in_exc() -> None:
    try:
        raise ValueError("boom")
    except ValueError:
        rec = record("it failed")
        rec.exc_info = sys.exc_info()
    entry = json.loads(JsonFormatter().format(rec))
    assert entry["event"] == "it failed"
    assert entry["exc"].startswith("Traceback") and entry["exc"].endswith("ValueError: boom")


@pytest.mark.parametrize(
    "text",
    [
        'quotes " and \\ backslash',
        "two\nlines\r\n",
        "tab\tand \x00 nul",
        "é ü 中文 🤖",
        "line\u2028separator\u2029paragraph\x85next",
    ],
)
def test_formatter_keeps_any_text_on_one_ascii_line(text: str) -> None:
    line = JsonFormatter().format(record("%s", text, principal=text))
    assert line.isascii() and len(line.splitlines()) == 1
    entry = json.loads(line)
    assert entry["event"] == text and entry["principal"] == text


def test_formatter_shows_bytes_that_were_not_utf8() -> None:
    name = os.fsdecode(b"audit-\xff.jsonl")  # a lone surrogate, as a non-UTF-8 path decodes
    entry = json.loads(JsonFormatter().format(record("cannot read %s", name)))
    assert entry["event"] == "cannot read audit-\\xff.jsonl"


def test_formatter_survives_bad_format_arguments() -> None:
    entry = json.loads(JsonFormatter().format(record("%d items", "not a number")))
    assert "%d items" in entry["event"] and "not a number" in entry["event"]
