"""Errors of the HTTP/WebSocket API.

    ApiServerError      base of every error the API raises (requests are answered, never raised)
    ├── BodyTimeout     a request body did not arrive in time (answered 408 by a middleware)
    ├── BodyEncoding    a body not what its Content-Encoding says, or in a coding not taken
    ├── ReadsBusy       too many audit reads wait for the reader thread (answered 429)
    └── AuditUnreadable a line the audit reads need is not an audit entry (answered 503)

Binding a socket raises OSError, like the stdlib; misuse (e.g. `ApiServer.url` before start)
raises RuntimeError.
"""

from __future__ import annotations


class ApiServerError(Exception):
    """Base of every error raised by `rcan_rtps.api`."""


class BodyTimeout(ApiServerError):
    """The request body did not arrive within `body_timeout_s` (answered 408, not audited:
    no request was ever complete)."""


class BodyEncoding(ApiServerError):
    """A request body that is not what its Content-Encoding says (400), or in a coding the API
    does not take (415); answered by a middleware, not audited (like a body timeout: what was
    sent cannot be read). `raw`: the body as it came, where a stop may still be found."""

    def __init__(self, status: int, reason: str, raw: bytes) -> None:
        super().__init__(reason)
        self.status = status
        self.reason = reason
        self.raw = raw


class ReadsBusy(ApiServerError):
    """Too many reads wait for the audit reader thread: answered 429 `reads_busy` (a bound,
    not a fault)."""


class AuditUnreadable(ApiServerError):
    """A line of the audit log that a read needs is not an audit entry: not JSON, nested too
    deeply, or without its seq and time — the file was edited or damaged on disk while the
    bridge ran (its writer writes only entries). Answered 503 AUDIT_UNREADABLE, naming
    `rcan-rtps audit verify`, which finds the line."""

    REASON = "a line of the log is not an audit entry: run `rcan-rtps audit verify`"
