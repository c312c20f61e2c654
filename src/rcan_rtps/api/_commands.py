"""Reading request bodies, and the REST side of deciding a COMMAND body.

Pre-command refusals (schema, RURI grammar, size) go through `Governor.reject_request`, which
audits them for an authenticated principal; everything else is `Governor.decide` (see
`_intake`, which the WebSocket shares).
"""

from __future__ import annotations

import asyncio
import sys
from typing import TypeVar

from aiohttp import web

from rcan_rtps.governance import Governor, Principal, outcomes
from rcan_rtps.rcan import ErrorCode, convert_at, decode_object

from ._bodies import error_body
from ._errors import BodyTimeout
from ._intake import NO_CHECKS, Checks, Observe, Reply, decide, intake, with_warnings
from ._skills import Skills

T = TypeVar("T")


async def read_limited(request: web.Request, limit: int,
                       timeout_s: float | None = None) -> bytes | None:
    """The body, or None when it exceeds `limit` (read no further than that).

    Raises BodyTimeout when the whole body has not arrived `timeout_s` after the headers did:
    a trickle of one byte a second must not hold a connection and a handler for hours.
    """
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
                      warnings: tuple[str, ...] = ()) -> Reply:
    """A whole body, already within the size limit, to its reply (an INVOKE of a goal: when
    the goal has ended). `warnings`: what the transport found wrong around the body, which
    a stop carries (`with_warnings`)."""
    item = with_warnings(intake(raw, len(raw), checks, principal.name), warnings)
    return await decide(governor, principal, item, observe, invocations)


def decode_as(raw: bytes, kind: type[T]) -> T:
    """Strict decode of a small JSON object body (unique keys); raises SchemaValidationError
    with the field path."""
    return convert_at(decode_object(raw), kind, "$")
