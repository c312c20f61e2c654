"""Reading request bodies, and the REST side of deciding a COMMAND body.

Pre-command refusals (schema, RURI grammar, size) go through `Governor.reject_request`, which
audits them for an authenticated principal; everything else is `Governor.decide` (see
`_intake`, which the WebSocket shares).
"""

from __future__ import annotations

import asyncio
import sys
import zlib
from typing import TypeVar

from aiohttp import web

from rcan_rtps.governance import Governor, Principal, outcomes
from rcan_rtps.rcan import ErrorCode, convert_at, decode_object

from ._bodies import error_body
from ._errors import BodyEncoding, BodyTimeout
from ._intake import (
    NO_CHECKS,
    Checks,
    HangUp,
    Observe,
    Reply,
    decide,
    intake,
    with_warnings,
)
from ._skills import Skills

T = TypeVar("T")


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
    try:
        if sys.version_info >= (3, 11):  # no extra task (and loop turn) per request
            async with asyncio.timeout(timeout_s):
                return await _read(request, limit)
        return await asyncio.wait_for(_read(request, limit), timeout_s)
    except asyncio.TimeoutError as exc:
        raise BodyTimeout(f"body not complete within {timeout_s} s") from exc


async def _read(request: web.Request, limit: int) -> bytes | None:
    buf = bytearray()
    async for chunk in request.content.iter_chunked(64 * 1024):
        buf += chunk
        if len(buf) > limit:  # chunked bodies state no length: count as they come
            return None
    return bytes(buf)


# The codings a body may come in, and zlib's window bits for them: 47 reads a zlib or a gzip
# stream (told apart by its header), -15 a raw deflate stream (what some clients send as
# `deflate`). The app decodes them itself (`auto_decompress` is off): aiohttp's own decoding
# failed with a traceback in the log and a 503, or, for a caller it never authenticated, a
# traceback after the 401.
_CODINGS = {"gzip": (47,), "x-gzip": (47,), "deflate": (47, -15)}


def decoded(header: str, raw: bytes, limit: int) -> bytes | None:
    """`raw` with the codings `header` lists undone (the last applied first); None when the
    result exceeds `limit`. Raises BodyEncoding for a coding not taken or data not so coded."""
    codings = [c.strip().lower() for c in header.split(",")]
    data: bytes | None = raw
    for coding in reversed([c for c in codings if c not in ("", "identity")]):
        if coding not in _CODINGS:
            raise BodyEncoding(415, f"Content-Encoding {coding[:32]!r} is not taken (gzip, "
                               "deflate or none)", raw)
        assert data is not None
        data = _inflate(coding, data, limit, raw)
        if data is None:
            return None
    return data


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
                      limit: int | None = None) -> Reply:
    """A whole body to its reply (an INVOKE of a goal: when the goal has ended; given up if
    `hung_up` tells its client left). `warnings`: what the transport found wrong around the
    body, which a stop carries (`with_warnings`). `limit`: the size over which only a stop is
    taken (`intake`); None: the body is within it already."""
    limit = len(raw) if limit is None else limit
    item = with_warnings(intake(raw, limit, checks, principal.name), warnings)
    return await decide(governor, principal, item, observe, invocations, hung_up)


def decode_as(raw: bytes, kind: type[T]) -> T:
    """Strict decode of a small JSON object body (unique keys); raises SchemaValidationError
    with the field path."""
    return convert_at(decode_object(raw), kind, "$")
