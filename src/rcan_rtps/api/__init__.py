"""The bridge's HTTP and WebSocket API (aiohttp), in front of the governor.

Public API::

    build_app(*, governor, authenticator, robot, config, cert_principals=None) -> Application
    ApiServer(app, host=, port=, ssl_context=)     async context manager; `.url` once bound
    bind(host, port)                               a listening socket for ApiServer(sock=)
    server_ssl_context(tls) -> SSLContext          TLS; mTLS when `tls.client_ca` is set
    cert_principals(config) -> {CN: Principal}     the mTLS mapping (principal name = CN)
    RobotView, GoalView                            the contract the bridge implements
    ApiServerError                                 base of the API's errors (see `_errors`)

Routes (JSON unless said; every one needs a principal, including /api/openapi.json — the
document is no secret — but the node manifest, which §17.3 makes public):

    POST /api/command            COMMAND → decision (profile outcome table)
    GET  /api/status             STATUS (GUEST+)
    POST /api/heartbeat          keeps a control session alive (§10.8)
    GET  /api/goals[/{goal_id}]  goals of every goal action (GUEST+), 404 when unknown
    GET  /api/skills             the skills an INVOKE may name: §18's `invoke` capability and
                                 each skill's action, role, fixed and allowed params (GUEST+)
    GET  /api/hitl/pending       pending commands (the lowest role that can approve one):
                                 those the caller could approve, and its own
    POST /api/hitl/authorize     {"pending_id", "reason"?} → decision; the governor checks the
                                 approver; 202 while more approvals are needed (n-of-m); 403
                                 for an approver whose signature policy is `required` (it
                                 sends a signed AUTHORIZE to /api/command instead)
    POST /api/hitl/deny          {"pending_id"} → decision (any approver's denial ends it)
    POST /api/hitl/withdraw      {"pending_id"} → decision; the issuer's own (or an approver's)
    GET  /api/audit?since=&limit= entries verbatim (rbac.audit_read_role, LEASEE by default):
                                 up to `limit` (1000) and 4 MiB of them (one larger entry is
                                 a page alone); page on from `next_since`
    GET  /api/audit/verify       chain + signature check of what is on disk
    GET  /api/openapi.json       OpenAPI 3.1, generated from the msgspec schemas
    GET  /api/ws                 WebSocket: STATUS stream, commands in, outcomes out
    GET  /.well-known/rcan-node.json  §17 node manifest (public: RURI, versions, public keys)
    GET  /api/safety/manifest    Protocol 66 safety manifest (derived from config + registry)
    GET  /api/v1/audit?from=&to=&format=jsonl|csv  §20 export (audit_read_role), streamed,
                                 X-Audit-Chain-Root / X-Audit-Issuer-Sig

Decisions where the profile is silent:

- Principal: the `Authorization: Bearer` credential; without one, a verified mTLS client
  certificate whose subject CN is a configured principal's name. A presented credential that
  fails is 401 even if a certificate would have named someone; two Authorization headers are 401.
  A certificate (which a browser presents by itself, whatever page asks) names no one in a
  request whose `Origin` is another host than the bridge's: 401 (no cross-site request acts
  as its principal); a bearer token counts from any origin. A certificate's principal ends
  at its notAfter (read at every request: a connection kept alive past it is refused 401
  `certificate_expired`, its WebSocket closed 1008).
- A refused JWT's 401 has a `reason` (`jwt_expired`, `jwt_lifetime_too_long`, `jwt_unknown_kid`,
  ...) and the message in `WWW-Authenticate: ... error_description`; a JWT's principal is
  `jwt:<iss>/<sub>`, never a configured one (docs/governance.md, Identity).
- Authentication happens before a body is read: an unauthenticated 1 MB body gets 401, not 413,
  and nothing is audited. For an authenticated principal, 413 (size), 400 (schema, with the
  field path) and INVALID_RURI are audited as COMMAND_REJECTED via `Governor.reject_request`.
- Reads (status, goals, pending, audit) are not commands: refusing them is 403, not audited.
- Errors outside the profile's table: unknown route 404 `NOT_FOUND`, wrong method 405
  `METHOD_NOT_ALLOWED`; an unexpected exception is logged and answered 503 `failed`
  ROBOT_UNAVAILABLE `internal_error` (audit failure: 503 COMMAND_REJECTED `audit_unavailable`);
  the API never answers 500.
- A stop or e-stop over `max_body_bytes` stops all the same (a warning says its size), on
  every door; any other body over it gets 413. Up to 4× the limit (`_intake.STOP_ROOM`) a
  body is held whole; past that REST and `/mcp` read it on to its end through its skeleton
  (`_skim`: its shape, each string cut to `max_body_bytes` / 16 bytes, held to 4× the limit;
  compressed bodies inflated a piece at a time), so a stop of any size stops; a body still
  larger by its shape (a huge array) gets 413.
- WebSocket: frames over `max_body_bytes` get a 413 outcome frame (audited) unless they say
  stop; over 4× that the socket is closed (1009) before buffering. More than 32 queued
  commands → 429 frame. The credential must be in the upgrade request's headers (or the
  client certificate).
- E-stop lane (`_intake`): every frame is validated as it arrives; a valid `stop`/`estop` is
  decided at once, concurrently with the socket's queue — never 429, never behind queued
  commands — so its outcome frame may overtake earlier commands' frames (match by
  `message_id`). Bad frames (invalid UTF-8 binary, not JSON, schema, 413) get their error
  frame and the socket goes on; a decision that raises gets a 503 frame. A text frame that is
  not UTF-8 is a WebSocket protocol error: closed 1007 (RFC 6455).
- A WebSocket that closes while its principal holds a control session is session loss
  (§10.8): safe stop at once (after the command in flight and every stop sent are decided;
  queued commands are dropped). The session belongs to the principal, so any of the
  principal's sockets closing ends it — the safe side.
- Audit reads (`_reads`) never use the default executor (the audit writer's): pages are read
  by one dedicated thread (8 waiting at most; beyond, 429 RATE_LIMITED `reads_busy` with
  Retry-After); verification runs in one spawned, niced worker process, and concurrent
  verify requests share a run that started reading after they arrived (never refused).
  Starting that process leaves the signal mask of the starting thread as it was (SIGINT and
  SIGTERM stay blocked in every thread of `rcan-rtps run`: see `bridge.watchdog`).
- Slow peers (`_conn`, config `bridge.api.*_timeout_s`): request headers must be complete
  within `header_timeout_s` (10) of connecting, the next request's within
  `keepalive_timeout_s` (30) of the previous one's end (also the idle keep-alive limit),
  else the connection is closed; a body not complete `body_timeout_s` (30) after its headers
  is answered 408 `REQUEST_TIMEOUT` `body_timeout` (not audited: no request was complete)
  and the connection closed. A TLS handshake has `header_timeout_s` too. Invalid UTF-8 in a
  body is 400 SCHEMA_VALIDATION_FAILED, audited like any schema failure.
- What aiohttp's HTTP parser refuses before any middleware runs (`_protocol`): a request line
  or header field over 8190 bytes, or more than 128 header fields → 431
  `REQUEST_HEADER_FIELDS_TOO_LARGE` `header_too_large`; other malformed HTTP → 400
  `BAD_REQUEST` `malformed_http`. Both are the usual JSON error body (`outcome` denied), not
  audited (no request was ever read), logged as one line without a traceback, and the
  connection is closed.
- A client that goes away (connection reset mid-body or mid-response) is not an error: a
  debug line, no traceback, nothing audited for a body that never arrived whole.
"""

from ._app import build_app, settings_from_config
from ._errors import ApiServerError
from ._keys import ApiSettings, Authenticator
from ._server import ApiServer, bind
from ._tls import cert_principals, server_ssl_context
from .ports import GoalState, GoalView, RobotView

__all__ = [
    "ApiServer",
    "ApiServerError",
    "ApiSettings",
    "Authenticator",
    "GoalState",
    "GoalView",
    "RobotView",
    "bind",
    "build_app",
    "cert_principals",
    "server_ssl_context",
    "settings_from_config",
]
