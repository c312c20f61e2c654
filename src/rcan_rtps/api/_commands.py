"""A COMMAND body in, an (HTTP status, body) out: shared by POST /api/command and the WebSocket.

Pre-command refusals (schema, RURI grammar, size) go through `Governor.reject_request`, which
audits them for an authenticated principal; everything else is `Governor.decide`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import msgspec
from aiohttp import web

from rcan_rtps.governance import Governor, Principal, outcomes
from rcan_rtps.rcan import (
    ErrorCode,
    InvalidRuriError,
    SchemaValidationError,
    validate_command,
    validation_path,
)

from ._bodies import error_body

Reply = tuple[int, Any]
_TOO_DEEP = "JSON is nested too deeply"


async def read_limited(request: web.Request, limit: int) -> bytes | None:
    """The body, or None when it exceeds `limit` (read no further than that)."""
    if request.content_length is not None and request.content_length > limit:
        return None
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
                      observe: Callable[[float], None] | None = None) -> Reply:
    started = time.perf_counter()
    try:
        return await _run_command(governor, principal, raw)
    finally:
        if observe is not None:
            observe(time.perf_counter() - started)


async def _run_command(governor: Governor, principal: Principal, raw: bytes) -> Reply:
    try:
        command = validate_command(raw)
    except RecursionError:  # msgspec gives up on deep nesting with this, not a DecodeError
        return await schema_failure(governor, principal, "$", _TOO_DEEP)
    except SchemaValidationError as exc:
        return await schema_failure(governor, principal, exc.path, exc.detail)
    except InvalidRuriError as exc:
        decision = await governor.reject_request(principal, outcomes.invalid_ruri(exc.rule))
        return decision.http_status, decision.body()
    decision = await governor.decide(command, principal)
    return decision.http_status, decision.body()


def decode_as(raw: bytes, kind: type[Any]) -> Any:
    """Strict decode of a small JSON body; raises SchemaValidationError with the field path."""
    try:
        return msgspec.json.decode(raw, type=kind)
    except msgspec.ValidationError as exc:
        path, detail = validation_path(exc)
        raise SchemaValidationError(path, detail) from exc
    except (msgspec.DecodeError, RecursionError) as exc:
        raise SchemaValidationError("$", str(exc) or _TOO_DEEP) from exc
