"""The audit log read a line at a time, a chunk of the file held at once (never the file:
a log may be months long): lines forwards (what opening the log verifies, a page of
GET /api/audit) and backwards, and the message ids its newest entries name — what a start
reads back (the replay window's ids, the idempotent retries an earlier run decided) without
the start-only replay of `resume`, which a run lets go of.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator
from pathlib import Path

import msgspec

from ._json import decode

CHUNK = 64 * 1024
# How far back a start reads the log for ids: the time asked for bounds it, this too, should
# the clock have gone back (every entry then seems recent).
MAX_LINES_BACK = 200_000


def lines_forwards(fd: int, offset: int, end: int) -> Iterator[tuple[int, bytes]]:
    """(offset, line without its newline) from `offset` (a line's start) to `end`, read a
    chunk at a time. An unterminated tail (a line being appended, or torn) is not read in,
    only looked through for a newline; a line longer than a chunk is read whole."""
    while offset < end:
        block = os.pread(fd, min(CHUNK, end - offset), offset)
        if b"\n" not in block:
            newline = next_newline(fd, offset + len(block), end)
            if not block or newline is None:
                return
            block = os.pread(fd, newline + 1 - offset, offset)
        lines = block.split(b"\n")
        lines.pop()  # after the last newline: a line's start, read again with the next chunk
        for line in lines:
            yield offset, line
            offset += len(line) + 1


def next_newline(fd: int, offset: int, end: int) -> int | None:
    """The offset of the first newline at or after `offset` (before `end`), or None."""
    while offset < end:
        block = os.pread(fd, min(CHUNK, end - offset), offset)
        if not block:  # the file is shorter than it was
            return None
        found = block.find(b"\n")
        if found >= 0:
            return offset + found
        offset += len(block)
    return None


def lines_backwards(fd: int, size: int, floor: int = 0) -> Iterator[tuple[int, bytes]]:
    """(offset, line) from the last line to the first at or after `floor` (a line's start)."""
    end, tail = size, b""
    while end > floor:
        start = max(floor, end - CHUNK)
        block = os.pread(fd, end - start, start) + tail
        lines = block.split(b"\n")
        tail = lines.pop(0) if start > floor else b""  # maybe cut: completed by the next read
        offset = start + len(block)
        for line in reversed(lines):
            offset -= len(line) + 1
            if line.strip():
                yield offset + 1, line
        end = start


def logged_ids(path: Path, *, since_s: float) -> Iterator[tuple[str, str, float]]:
    """(message_id, principal, logged at, s) of the entries of the log at `path`, from its
    end back to the first logged before `since_s`. The log was verified when it was opened:
    a line that cannot be read (a torn tail) is passed over."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return
    try:
        lines = itertools.islice(lines_backwards(fd, os.fstat(fd).st_size), MAX_LINES_BACK)
        for _, line in lines:
            try:
                entry = decode(line)
            except msgspec.DecodeError:
                continue
            if not isinstance(entry, dict):
                continue
            logged_ms = entry.get("timestamp_ms")
            if not isinstance(logged_ms, int) or isinstance(logged_ms, bool):
                continue
            if logged_ms / 1000 < since_s:
                return
            msg_id, principal = entry.get("message_id"), entry.get("principal")
            if isinstance(msg_id, str):
                yield msg_id, principal if isinstance(principal, str) else "", logged_ms / 1000
    finally:
        os.close(fd)
