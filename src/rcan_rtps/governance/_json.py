"""JSON decoding of the files the audit log keeps (its lines, tree heads, checkpoint, start
point): a value nested too deeply is malformed input like any other, not a RecursionError.

msgspec decodes nested values recursively and raises RecursionError a few thousand levels
down (`[[[[…]]]]`: a 10 kB line); every reader of these files expects DecodeError for what
it cannot read, so a line like that would take `audit verify`, or a start, down with a
traceback instead of naming the line.
"""

from __future__ import annotations

from typing import Any, TypeVar

import msgspec

T = TypeVar("T")


def decode(data: bytes) -> Any:
    """`msgspec.json.decode(data)`; raises msgspec.DecodeError for all it cannot read."""
    try:
        return msgspec.json.decode(data)
    except RecursionError as exc:
        raise msgspec.DecodeError("JSON is malformed: nested too deeply") from exc


def decode_as(data: bytes, type_: type[T], *, strict: bool = True) -> T:
    """`msgspec.json.decode(data, type=type_)`, with `decode`'s errors."""
    try:
        return msgspec.json.decode(data, type=type_, strict=strict)
    except RecursionError as exc:
        raise msgspec.DecodeError("JSON is malformed: nested too deeply") from exc
