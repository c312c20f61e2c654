"""Reading request bodies, and the REST side of deciding a COMMAND body.

Pre-command refusals (schema, RURI grammar, size) go through `Governor.reject_request`, which
audits them for an authenticated principal; everything else is `Governor.decide` (see
`_intake`, which the WebSocket shares).
"""

from __future__ import annotations

import asyncio
import sys
import zlib
from collections.abc import Coroutine, Iterator
from typing import Any, NamedTuple, TypeVar

from aiohttp import web

from rcan_rtps.governance import Governor, Principal, outcomes
from rcan_rtps.rcan import ErrorCode, convert_at, decode_object

from ._bodies import error_body
from ._errors import BodyEncoding, BodyTimeout
from ._intake import (
    NO_CHECKS,
    STOP_ROOM,
    Checks,
    HangUp,
    Observe,
    Reply,
    Skimmed,
    decide,
    intake,
    with_warnings,
)
from ._skills import Skills
from ._skim import Skeleton

T = TypeVar("T")
# Bodies are read a chunk of this at a time; one skimmed is inflated this much at a time, the
# loop given a turn after each: a body read that far must not hold it (a stop on another
# connection is decided meanwhile).
_PIECE = 64 * 1024


async def read_limited(request: web.Request, limit: int,
                       timeout_s: float | None = None) -> bytes | None:
    """The body, decoded as its Content-Encoding says, or None when it (or what it decodes
    to) exceeds `limit` (read no further than that).

    Raises BodyTimeout when the whole body has not arrived `timeout_s` after the headers did:
    a trickle of one byte a second must not hold a connection and a handler for hours.
    Raises BodyEncoding for a body its Content-Encoding does not describe.
    """
    raw = await _read_raw(request, limit, timeout_s)
    if raw is None:
        return None
    return decoded(request.headers.get("Content-Encoding", ""), raw, limit)


async def _read_raw(request: web.Request, limit: int, timeout_s: float | None) -> bytes | None:
    if request.content_length is not None and request.content_length > limit:
        return None
    content = request.content
    if content.is_eof():  # all of it arrived with the headers (the usual small command)
        data = content.read_nowait()  # no timer to arm and cancel, no chunk loop
        return data if len(data) <= limit else None
    return await _in_time(_read(request, limit), timeout_s)


async def _in_time(reading: Coroutine[Any, Any, T], timeout_s: float | None) -> T:
    """`reading`'s result, or BodyTimeout after `timeout_s`."""
    try:
        if sys.version_info >= (3, 11):  # no extra task (and loop turn) per request
            async with asyncio.timeout(timeout_s):
                return await reading
        return await asyncio.wait_for(reading, timeout_s)
    except asyncio.TimeoutError as exc:
        raise BodyTimeout(f"body not complete within {timeout_s} s") from exc


async def _read(request: web.Request, limit: int) -> bytes | None:
    held = await _held(request, limit)
    return held if len(held) <= limit else None


async def _held(request: web.Request, limit: int) -> bytes:
    """The body, or its start once past `limit` (by one chunk at most)."""
    buf = bytearray()
    async for chunk in request.content.iter_chunked(_PIECE):
        buf += chunk
        if len(buf) > limit:  # chunked bodies state no length: count as they come
            break
    return bytes(buf)


class CommandBody(NamedTuple):
    """A command's body as `read_command` read it: whole, or — past STOP_ROOM times the
    limit — its skeleton (`_skim`), which is only ever taken if it says stop."""

    data: bytes
    skimmed: Skimmed | None = None  # what the skeleton stands for; None: held whole
    warnings: tuple[str, ...] = ()  # what else was wrong with how it came (a stop's)


async def read_command(request: web.Request, limit: int,
                       timeout_s: float | None) -> CommandBody | None:
    """A command's body (REST, `/mcp`): whole up to STOP_ROOM times `limit`, as `read_limited`
    reads it; past that it is read on to its end through a `Skeleton` (its strings cut to
    `limit` / 16 bytes), so that a stop of any size stops and no body is held past the room;
    None when even the skeleton is larger (a body large by its shape, not its text).

    Raises BodyTimeout (the whole body within `timeout_s` of its headers, as for any body)
    and BodyEncoding."""
    header = request.headers.get("Content-Encoding", "")
    content = request.content
    if content.is_eof():  # all of it arrived with the headers (the usual small command)
        held = content.read_nowait()  # no timer to arm and cancel, no chunk loop
        whole = _whole(held, limit, header)
        if whole is not None:
            return whole
        return await _in_time(_skimmed(request, limit, held, header), timeout_s)
    return await _in_time(_read_command(request, limit, header), timeout_s)


async def _read_command(request: web.Request, limit: int, header: str) -> CommandBody | None:
    held = await _held(request, limit * STOP_ROOM)
    whole = _whole(held, limit, header)
    return whole if whole is not None else await _skimmed(request, limit, held, header)


def _whole(held: bytes, limit: int, header: str) -> CommandBody | None:
    """`held`, decoded, when it is the whole body and within STOP_ROOM times `limit` once
    decoded; None: it is to be skimmed, from its start."""
    room = limit * STOP_ROOM
    data = decoded(header, held, room) if len(held) <= room else None
    return None if data is None else CommandBody(data)


async def _skimmed(request: web.Request, limit: int, held: bytes,
                   header: str) -> CommandBody | None:
    """The body's skeleton, from what is `held` of it on to its end (`read_command`)."""
    room = limit * STOP_ROOM
    skeleton = Skeleton(keep=max(limit // 16, 64), cap=room)
    inflater = _Inflater(header, held)
    piece = held
    while piece:
        for text in inflater.undo(piece):
            if not skeleton.feed(text):
                return None
            await asyncio.sleep(0)
        piece = await request.content.read(_PIECE)
    inflater.finish()
    return CommandBody(skeleton.text, Skimmed(skeleton.size, skeleton.shortened),
                       inflater.warnings)


class _Inflater:
    """A skimmed body's content coding undone a piece at a time: none, or one of gzip and
    deflate (what a client that compresses sends). A body whose start is not what its
    header says is read as sent, warned of (a stop in bytes its header misnames still
    stops, as `decoded`'s callers do for a body held whole)."""

    def __init__(self, header: str, start: bytes) -> None:
        codings = _codings(header)
        self.warnings: tuple[str, ...] = ()
        self._zlib: zlib._Decompress | None = None
        if len(codings) > 1 or (codings and codings[0] not in _CODINGS):
            raise BodyEncoding(415, "a body this large is taken in one Content-Encoding at "
                               "most, gzip or deflate", b"")
        if codings:
            self._zlib = _decompressor(codings[0], start)
            if self._zlib is None:
                self.warnings = (f"$: the body is not {codings[0]} data, as its "
                                 "Content-Encoding says: read as sent",)

    def undo(self, data: bytes) -> Iterator[bytes]:
        inflater = self._zlib
        if inflater is None:
            yield data
            return
        try:
            yield inflater.decompress(data, _PIECE)
            while inflater.unconsumed_tail:
                yield inflater.decompress(inflater.unconsumed_tail, _PIECE)
        except zlib.error as exc:
            raise BodyEncoding(400, f"the body's compressed data is damaged: {exc}", b"") \
                from None

    def finish(self) -> None:
        if self._zlib is not None and not self._zlib.eof:
            raise BodyEncoding(400, "the body's compressed data ends early", b"")


def _decompressor(coding: str, start: bytes) -> zlib._Decompress | None:
    """A decompressor for `coding` that takes the body's first bytes; None if none does."""
    for wbits in _CODINGS[coding]:
        try:
            zlib.decompressobj(wbits).decompress(start[:_PIECE], 1)
        except zlib.error:
            continue
        return zlib.decompressobj(wbits)
    return None


# The codings a body may come in, and zlib's window bits for them: 47 reads a zlib or a gzip
# stream (told apart by its header), -15 a raw deflate stream (what some clients send as
# `deflate`). The app decodes them itself (`auto_decompress` is off): aiohttp's own decoding
# failed with a traceback in the log and a 503, or, for a caller it never authenticated, a
# traceback after the 401.
_CODINGS = {"gzip": (47,), "x-gzip": (47,), "deflate": (47, -15)}


def decoded(header: str, raw: bytes, limit: int) -> bytes | None:
    """`raw` with the codings `header` lists undone (the last applied first); None when the
    result exceeds `limit`. Raises BodyEncoding for a coding not taken or data not so coded."""
    data: bytes | None = raw
    for coding in reversed(_codings(header)):
        if coding not in _CODINGS:
            raise BodyEncoding(415, f"Content-Encoding {coding[:32]!r} is not taken (gzip, "
                               "deflate or none)", raw)
        assert data is not None
        data = _inflate(coding, data, limit, raw)
        if data is None:
            return None
    return data


def _codings(header: str) -> list[str]:
    """The codings a Content-Encoding header lists, in the order applied (identity left out)."""
    codings = (c.strip().lower() for c in header.split(","))
    return [c for c in codings if c not in ("", "identity")]


def _inflate(coding: str, data: bytes, limit: int, raw: bytes) -> bytes | None:
    for wbits in _CODINGS[coding]:
        inflater = zlib.decompressobj(wbits)
        try:
            out = inflater.decompress(data, limit + 1)
        except zlib.error:
            continue
        if len(out) > limit or inflater.unconsumed_tail:
            return None  # a bomb stops here: never more than `limit` + 1 bytes made
        if inflater.eof and not inflater.unused_data:
            return out
    raise BodyEncoding(400, f"the body is not {coding} data, as its Content-Encoding says",
                       raw)


async def too_large(governor: Governor, principal: Principal) -> Reply:
    decision = await governor.reject_request(principal, outcomes.PAYLOAD_TOO_LARGE)
    return decision.http_status, decision.body()


async def schema_failure(governor: Governor, principal: Principal, path: str,
                         detail: str) -> Reply:
    decision = await governor.reject_request(principal, outcomes.schema_failed(path))
    body = error_body(ErrorCode.SCHEMA_VALIDATION_FAILED, reason=detail, path=path,
                      audit_id=decision.audit_id)
    return decision.http_status, body


async def run_command(governor: Governor, principal: Principal, raw: bytes,
                      observe: Observe | None = None, checks: Checks = NO_CHECKS,
                      invocations: Skills | None = None,
                      warnings: tuple[str, ...] = (), hung_up: HangUp | None = None,
                      limit: int | None = None, skimmed: Skimmed | None = None) -> Reply:
    """A whole body to its reply (an INVOKE of a goal: when the goal has ended; given up if
    `hung_up` tells its client left). `warnings`: what the transport found wrong around the
    body, which a stop carries (`with_warnings`). `limit`: the size over which only a stop is
    taken (`intake`); None: the body is within it already. `skimmed`: `raw` is the skeleton
    of a larger body (`read_command`)."""
    limit = len(raw) if limit is None else limit
    item = with_warnings(intake(raw, limit, checks, principal.name, skimmed=skimmed),
                         warnings)
    return await decide(governor, principal, item, observe, invocations, hung_up)


def decode_as(raw: bytes, kind: type[T]) -> T:
    """Strict decode of a small JSON object body (unique keys); raises SchemaValidationError
    with the field path."""
    return convert_at(decode_object(raw), kind, "$")
