"""A small JSON text of the same shape as a large one, made as the large one streams by.

A stop always stops, whatever its size (non-negotiable 4), but a door must not hold an
authenticated client's arbitrarily large body to find out whether it says stop. What makes a
command large is its text — a `reasoning` of megabytes —, never its shape: so a body read past
`STOP_ROOM` times the size limit is read on through a `Skeleton`, which keeps its structure,
drops the whitespace between tokens and keeps each string's first `keep` bytes, and the
skeleton is what `intake` decides. A skeleton that still grows past its cap (a body large by
its shape: a huge array) is refused like any oversize body.

A string is cut only between whole units — a UTF-8 character, an escape (`\\n`, `\\u00e9`),
or a surrogate pair's two escapes —, so a cut string still decodes. What follows a cut, up to
the string's closing quote, is skipped by a regex match, not byte by byte: only the kept
bytes (at most the cap in all) are looked at one at a time.

Malformed JSON is not this module's to judge: the skeleton of a malformed text is passed on,
malformed, and `intake` refuses it (or finds the stop in it, as for any stop).
"""

from __future__ import annotations

import re

_QUOTE, _BACKSLASH, _U = 0x22, 0x5C, 0x75
_WHITESPACE = b" \t\r\n"
_HEX = frozenset(b"0123456789abcdefABCDEF")
# The rest of a string's content: what is no quote or backslash, and escapes whole (one
# search in C, however many escapes: a string of backslashes is no slower to skip).
_STRING_REST = re.compile(rb'[^"\\]*(?:\\.[^"\\]*)*', re.S)


class Skeleton:
    """Feed a JSON text in chunks; `text` is its skeleton. `feed` says False once the
    skeleton is over `cap` bytes (then nothing more is kept: the body is refused)."""

    def __init__(self, keep: int, cap: int) -> None:
        self.keep, self.cap = keep, cap
        self.size = 0  # bytes fed
        self.shortened = 0  # strings cut
        self._out = bytearray()
        self._in_string = False
        self._kept = 0  # of the current string's content
        self._cutting = False  # past `keep`: skipping to the closing quote
        self._escaped = False  # (cutting) the last byte skipped was an escaping backslash
        self._unit = bytearray()  # (keeping) a character or escape not yet whole

    @property
    def text(self) -> bytes:
        return bytes(self._out)

    @property
    def over(self) -> bool:
        return len(self._out) > self.cap

    def feed(self, chunk: bytes) -> bool:
        self.size += len(chunk)
        at, end = 0, len(chunk)
        while at < end and not self.over:
            if not self._in_string:
                at = self._structure(chunk, at)
            elif self._cutting:
                at = self._skip(chunk, at)
            else:
                at = self._keep_byte(chunk, at)
        return not self.over

    def _structure(self, chunk: bytes, at: int) -> int:
        quote = chunk.find(b'"', at)
        stop = len(chunk) if quote < 0 else quote
        self._out += chunk[at:stop].translate(None, _WHITESPACE)
        if quote >= 0:
            self._out.append(_QUOTE)
            self._in_string, self._kept, self._cutting = True, 0, False
            return quote + 1
        return stop

    def _skip(self, chunk: bytes, at: int) -> int:
        if self._escaped:  # the byte an escape's backslash took, in this chunk
            self._escaped = False
            at += 1
        quote = chunk.find(b'"', at)
        if chunk.find(b"\\", at, len(chunk) if quote < 0 else quote) < 0:
            end = len(chunk) if quote < 0 else quote  # no escape on the way (memchr: fast)
        else:
            rest = _STRING_REST.match(chunk, at)
            end = rest.end() if rest is not None else at
        if end == len(chunk):
            return end
        if chunk[end] == _BACKSLASH:  # the chunk's last byte: what it escapes comes next
            self._escaped = True
        else:
            self._close()
        return end + 1

    def _keep_byte(self, chunk: bytes, at: int) -> int:
        byte = chunk[at]
        unit = self._unit
        if unit and not _continues(unit, byte):
            self._settle()  # a malformed unit ends here; this byte starts afresh
            return at
        if not unit and byte == _QUOTE:
            self._close()
            return at + 1
        unit.append(byte)
        if _whole(unit):
            self._settle()
        return at + 1

    def _settle(self) -> None:
        """The pending unit is whole (or ends malformed): kept if it fits, else the cut."""
        unit = self._unit
        if self._kept + len(unit) <= self.keep:
            self._out += unit
            self._kept += len(unit)
        else:
            self._cutting = True
            self.shortened += 1
        unit.clear()

    def _close(self) -> None:
        if self._unit:
            self._settle()
        self._out.append(_QUOTE)
        self._in_string = self._cutting = self._escaped = False


def _whole(unit: bytearray) -> bool:
    """Whether `unit` (a UTF-8 character, or an escape) is complete."""
    first = unit[0]
    if first == _BACKSLASH:
        if len(unit) < 2 or unit[1] != _U:
            return len(unit) == 2
        if len(unit) < 6:
            return False
        return len(unit) == 12 or not _high_surrogate(unit)
    return len(unit) == _utf8_length(first)


def _continues(unit: bytearray, byte: int) -> bool:
    """Whether `byte` may come next in `unit` (whole units never reach here)."""
    if unit[0] != _BACKSLASH:
        return 0x80 <= byte <= 0xBF  # a UTF-8 continuation byte
    position = len(unit)
    if position == 1:
        return True  # whatever is escaped: `intake` judges a bad escape
    if position in (6, 7):  # a high surrogate's pair: `\u`, then hex
        return byte == (_BACKSLASH if position == 6 else _U)
    return byte in _HEX


def _high_surrogate(unit: bytearray) -> bool:
    return bytes(unit[2:4]).lower() in (b"d8", b"d9", b"da", b"db")


def _utf8_length(first: int) -> int:
    if first < 0xC0:
        return 1  # ASCII (or a stray continuation byte: one malformed unit)
    return 2 if first < 0xE0 else 3 if first < 0xF0 else 4
