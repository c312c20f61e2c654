"""Logging set-up of the command line: `--log-level` and `--log-format text|json`.

JSON lines carry `time` (UTC, ISO 8601, ms), `level`, `logger`, `event` (the message), the
context fields a log call passes as `extra=` (`principal`, `audit_id`) when present, and
`exc` (the traceback as text) for an exception. Each record is exactly one line of ASCII:
non-ASCII is escaped as \\uXXXX, so no stream encoding or line splitter (U+2028 counts as a
line break for `str.splitlines`) can break a line, and bytes that were not UTF-8 (lone
surrogates from `surrogateescape`) appear as `\\xNN` text instead of failing the record.
"""

from __future__ import annotations

import logging
import re
import sys
from datetime import datetime, timezone
from typing import Any

import msgspec

LOG_FORMATS = ("text", "json")
LOG_LEVELS = ("debug", "info", "warning", "error")
DEFAULT_LOG_LEVEL = "warning"
SERVER_LOG_LEVEL = "info"  # `run`: one line per decision and safety event
TEXT_FORMAT = "%(asctime)s.%(msecs)03d %(levelname)s %(name)s: %(message)s"
TEXT_DATE_FORMAT = "%Y-%m-%d %H:%M:%S"
CONTEXT_FIELDS = ("principal", "audit_id")  # `extra=` keys the governance and API log with

_NON_ASCII = re.compile(r"[^\x00-\x7f]")
_encoder = msgspec.json.Encoder()


class JsonFormatter(logging.Formatter):
    """One JSON object per record, on one line."""

    def format(self, record: logging.LogRecord) -> str:
        fields = self.fields(record)
        try:
            raw = _encoder.encode(fields)
        except UnicodeEncodeError:  # a lone surrogate somewhere: show it, never drop the record
            raw = _encoder.encode({k: _printable(v) for k, v in fields.items()})
        return _NON_ASCII.sub(_escape, raw.decode("utf-8"))

    def fields(self, record: logging.LogRecord) -> dict[str, Any]:
        fields: dict[str, Any] = {
            "time": _iso_utc(record.created),
            "level": record.levelname,
            "logger": record.name,
            "event": _message(record),
        }
        for name in CONTEXT_FIELDS:
            value = record.__dict__.get(name)
            if value is not None:
                fields[name] = str(value)
        if record.exc_info:
            fields["exc"] = self.formatException(record.exc_info)
        elif record.exc_text:
            fields["exc"] = record.exc_text
        if record.stack_info:
            fields["stack"] = self.formatStack(record.stack_info)
        return fields


class TextFormatter(logging.Formatter):
    """TEXT_FORMAT, its time formatted once a second: a bridge logs a line per decision."""

    def __init__(self) -> None:
        super().__init__(TEXT_FORMAT, TEXT_DATE_FORMAT)
        self._cached = (-1, "")  # (second, its text): one object, so threads see a pair

    def formatTime(self, record: logging.LogRecord, datefmt: str | None = None) -> str:
        second, stamp = self._cached
        if int(record.created) != second:
            stamp = super().formatTime(record, datefmt)
            self._cached = (int(record.created), stamp)
        return stamp


def configure(level: str = DEFAULT_LOG_LEVEL, fmt: str = "text") -> None:
    """Root logging to stderr; like `basicConfig`, leaves an already configured root alone."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter() if fmt == "json" else TextFormatter())
    logging.basicConfig(level=level.upper(), handlers=[handler])
    # Neither format shows a record's source line, thread or process, and `run` logs a line
    # per decision: skip finding them (the logging HOWTO's "Optimization" switches).
    logging._srcfile = None  # no findCaller stack walk
    logging.logThreads = False
    logging.logProcesses = False
    logging.logMultiprocessing = False


def default_level(command: str | None) -> str:
    return SERVER_LOG_LEVEL if command == "run" else DEFAULT_LOG_LEVEL


def _message(record: logging.LogRecord) -> str:
    try:
        return record.getMessage()
    except Exception:  # bad %-args: keep what was logged rather than lose the line
        return f"{record.msg!r} % {record.args!r}"


def _iso_utc(created: float) -> str:
    stamp = datetime.fromtimestamp(created, tz=timezone.utc).isoformat(timespec="milliseconds")
    return stamp.replace("+00:00", "Z")


def _printable(value: object) -> object:
    if not isinstance(value, str):
        return value
    try:  # surrogates from `surrogateescape`-decoded bytes: back to the bytes, shown as \xNN
        return value.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    except UnicodeEncodeError:
        return value.encode("utf-8", "backslashreplace").decode("ascii")


def _escape(match: re.Match[str]) -> str:
    code = ord(match.group())
    if code <= 0xFFFF:
        return f"\\u{code:04x}"
    code -= 0x10000  # outside the BMP: a UTF-16 surrogate pair, as JSON spells it
    return f"\\u{0xD800 + (code >> 10):04x}\\u{0xDC00 + (code & 0x3FF):04x}"
