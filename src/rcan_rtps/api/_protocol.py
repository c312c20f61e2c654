"""aiohttp's connection handler, answering what its HTTP parser refuses in the API's terms.

aiohttp's parser refuses some requests before any middleware can see them: a request line or
a header field over `MAX_LINE` bytes, more than `MAX_FIELDS` header fields, bytes that are
not HTTP. Its `RequestHandler.handle_error` then logs an ERROR with a traceback and answers
in plain text. `ApiRequestHandler` overrides that hook for those refusals only (a peer's
mistake, not the bridge's): the API's JSON error body — 431 for a head over the limits, 400
otherwise — and one log line without a traceback. Anything else (a fault of the app itself)
is still aiohttp's to answer and log. `ApiServer` serves its connections through it.
"""

from __future__ import annotations

import logging
from typing import Any

from aiohttp import web
from aiohttp.http_exceptions import BadHttpMethod, HttpProcessingError, LineTooLong

from ._bodies import error_response

log = logging.getLogger(__name__)

# aiohttp's defaults, named: a line (request line or header field) of 8190 bytes at most.
MAX_LINE = 8190
MAX_FIELDS = 128
HEAD_TOO_LARGE = "REQUEST_HEADER_FIELDS_TOO_LARGE"
BAD_REQUEST = "BAD_REQUEST"


def handler_args(keepalive_timeout: float) -> dict[str, Any]:
    """What the server's handlers are created with (the runner gets the same)."""
    # Bodies are decoded by `read_limited`, which answers one that fails (aiohttp's decoding
    # failed with tracebacks, for callers never authenticated too).
    return {"access_log": None, "keepalive_timeout": keepalive_timeout,
            "max_line_size": MAX_LINE, "max_field_size": MAX_LINE, "max_headers": MAX_FIELDS,
            "auto_decompress": False}


def _too_many_fields(exc: HttpProcessingError) -> bool:
    # The parser says so only in words (a plain BadHttpMessage).
    return "too many headers" in exc.message.lower()


class ApiRequestHandler(web.RequestHandler):
    """One connection, as aiohttp serves it, with the API's parser-error replies."""

    def handle_error(self, request: web.BaseRequest, status: int = 500,
                     exc: BaseException | None = None,
                     message: str | None = None) -> web.StreamResponse:
        # The parser's refusals come as status 400 with its exception (data_received).
        if status != 400 or not isinstance(exc, HttpProcessingError):
            return super().handle_error(request, status, exc, message)
        if request.writer.output_size > 0:  # as aiohttp: too late for another response
            raise ConnectionError("a response has been sent already")
        if isinstance(exc, LineTooLong) or _too_many_fields(exc):
            limit = (f"more than {self.max_headers} header fields" if _too_many_fields(exc)
                     else f"a request line or header field over {self.max_field_size} bytes")
            log.info("431 to %s: %s", request.remote, limit)
            response = error_response(431, HEAD_TOO_LARGE, reason="header_too_large")
        else:
            # Not HTTP at all (a scanner, TLS to the plain port) is noise: debug only.
            level = logging.DEBUG if isinstance(exc, BadHttpMethod) else logging.INFO
            log.log(level, "400 to %s: not a valid HTTP request (%s)", request.remote,
                    type(exc).__name__)
            response = error_response(400, BAD_REQUEST, reason="malformed_http")
        response.force_close()  # where the next request would begin is unknown
        return response
