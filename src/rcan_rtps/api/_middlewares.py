"""Two middlewares: a last resort (no 500, ever) and authentication (every `/api/*` route;
not the node manifest nor the console's static pages).

Order, outermost first: `track_requests` (connection deadlines, in `_conn`) → `last_resort` →
`authenticate` → handler. Authentication comes before any body is read, so an unauthenticated
caller cannot make the bridge read, parse or audit anything it sends.
"""

from __future__ import annotations

import logging
import ssl
from collections.abc import Callable

import msgspec
from aiohttp import web
from aiohttp.typedefs import Handler, Middleware

from rcan_rtps.governance import AuditError, AuthenticationError, Principal, outcomes
from rcan_rtps.rcan import ErrorCode

from ._bodies import error_response, failure_reply, json_response
from ._errors import BodyEncoding, BodyTimeout
from ._keys import (
    AUTHENTICATOR,
    CERT_PRINCIPALS,
    CREDENTIAL_LEFT,
    GOVERNOR,
    PRINCIPAL,
    WS_TICKETS,
)
from ._tickets import same_origin, ticket_of

log = logging.getLogger(__name__)
CERTIFICATE_EXPIRED = "certificate_expired"  # the 401's `reason` once a notAfter has passed

_HTTP_CODES = {
    404: "NOT_FOUND",
    405: "METHOD_NOT_ALLOWED",
    413: ErrorCode.PAYLOAD_TOO_LARGE.value,
}


def last_resort() -> Middleware:
    """HTTP errors become JSON; anything unexpected is logged and answered 503, never 500.
    A client that went away (reset mid-body, or mid-response) is no error: one debug line."""

    @web.middleware
    async def middleware(request: web.Request, handler: Handler) -> web.StreamResponse:
        try:
            return await handler(request)
        except web.HTTPException as exc:
            if exc.status < 400:
                raise
            code = _HTTP_CODES.get(exc.status, "SCHEMA_VALIDATION_FAILED"
                                   if exc.status == 400 else f"HTTP_{exc.status}")
            headers = {k: v for k, v in exc.headers.items() if k.lower() == "allow"}
            return error_response(exc.status, code, reason=exc.reason, headers=headers)
        except BodyTimeout:
            return await _body_timed_out(request)
        except BodyEncoding as exc:
            code = "SCHEMA_VALIDATION_FAILED" if exc.status == 400 else "UNSUPPORTED_MEDIA_TYPE"
            return error_response(exc.status, code, reason=exc.reason)
        except AuditError as exc:
            # Nothing may happen unrecorded: without an audit log the bridge is unavailable.
            log.exception("audit log failed while serving %s %s", request.method, request.path,
                          extra=_log_context(request))
            return _failure(exc)
        except ConnectionError as exc:
            if not _client_gone(request):  # e.g. a connection of the bridge's own failed
                log.exception("unexpected error serving %s %s", request.method, request.path,
                              extra=_log_context(request))
                return _failure(exc)
            log.debug("client went away during %s %s: %s", request.method, request.path,
                      exc, extra=_log_context(request))
            return _gone()
        except Exception as exc:
            log.exception("unexpected error serving %s %s", request.method, request.path,
                          extra=_log_context(request))
            return _failure(exc)

    return middleware


async def _body_timed_out(request: web.Request) -> web.StreamResponse:
    """408, not audited (no request was ever complete), then the connection closes at once:
    aiohttp would otherwise linger reading the rest of the body the peer is trickling."""
    response = error_response(408, "REQUEST_TIMEOUT", reason="body_timeout")
    response.force_close()
    await response.prepare(request)
    await response.write_eof()
    if request.transport is not None:
        request.transport.close()  # sends what is buffered (the 408) first
    return response


def _client_gone(request: web.Request) -> bool:
    transport = request.transport
    return transport is None or transport.is_closing()


def _gone() -> web.Response:
    """For aiohttp to finish the request with; nobody is there to read it."""
    response = error_response(400, "CLIENT_GONE", reason="connection_closed")
    response.force_close()
    return response


def _log_context(request: web.Request) -> dict[str, str]:
    """Log `extra=` naming the request's principal, once authentication has found one."""
    principal = request.get(PRINCIPAL)
    return {"principal": principal.name} if principal is not None else {}


def _failure(exc: Exception) -> web.Response:
    status, body = failure_reply(exc)
    return json_response(body, status)


def _nothing_static(path: str) -> bool:
    return False


def authenticate(public: frozenset[str] = frozenset(),
                 static: Callable[[str], bool] = _nothing_static) -> Middleware:
    """Every route needs a principal (a Bearer credential, a WebSocket ticket on `/api/ws`, or
    a mapped mTLS client certificate), except GETs of the `public` paths (the node manifest:
    §17.3 says no authentication) and GETs of the paths `static` accepts (the
    console's page and assets, which hold no data: what they show comes from `/api/*`), which
    never look at a credential."""

    @web.middleware
    async def middleware(request: web.Request, handler: Handler) -> web.StreamResponse:
        if request.method == "GET" and request.path in public:
            return await handler(request)
        if request.method == "GET" and static(request.path):
            return await handler(request)
        try:
            principal, presented = _principal(request)
        except AuthenticationError as exc:
            return await _unauthenticated(request, exc)
        if principal is None:
            return await _unauthenticated(request, None if not presented else
                                          AuthenticationError("invalid credentials"))
        request[PRINCIPAL] = principal
        return await handler(request)

    return middleware


async def _unauthenticated(request: web.Request,
                           refused: AuthenticationError | None) -> web.Response:
    """401; a refused JWT says why (`reason`, and RFC 6750's error_description)."""
    rejection = outcomes.UNAUTHENTICATED
    challenge = 'Bearer realm="rcan"'
    if refused is not None:
        challenge += ', error="invalid_token"'
        if refused.reason is not None:
            rejection = msgspec.structs.replace(rejection, reason=refused.reason)
            # The messages are fixed ASCII text: nothing of the token is echoed.
            challenge += f', error_description="{str(refused).replace(chr(34), chr(39))}"'
    decision = await request.app[GOVERNOR].reject_request(None, rejection)
    return json_response(decision.body(), decision.http_status, {"WWW-Authenticate": challenge})


def _principal(request: web.Request) -> tuple[Principal | None, bool]:
    """(principal or None, whether a credential was presented); a refused bearer credential
    raises AuthenticationError. A WebSocket ticket or a client certificate counts only without
    an `Authorization` header, and only from no origin or the bridge's own (`_tickets`): a
    browser presents its certificate by itself, whichever site's page made the request (a
    cross-site POST or WebSocket would otherwise act as the certificate's principal). A
    bearer token is sent only by who holds it: its request is the token's, whatever its
    `Origin`."""
    headers = request.headers.getall("Authorization", [])
    if len(headers) > 1:  # two credentials: which one counts is ambiguous, so neither does
        return None, True
    if headers:
        scheme, _, token = headers[0].partition(" ")
        if scheme.lower() != "bearer" or not token.strip():
            return None, True
        return request.app[AUTHENTICATOR].authenticate(token.strip()), True
    ticket = ticket_of(request)
    if ticket is not None:  # spent here, whatever comes of it (tickets are single-use)
        principal = request.app[WS_TICKETS].redeem(ticket)
        if principal is not None:
            _still_valid(request, principal)
        return (principal if same_origin(request) else None), True
    peer = peer_certificate(request)
    if peer is None:
        return None, False
    name, not_after = peer
    principal = request.app[CERT_PRINCIPALS].get(name)
    if principal is None or not same_origin(request):
        return None, True
    # Read at every request: a kept-alive (or resumed) TLS connection was verified once, at
    # its handshake, and may live on past the certificate's notAfter.
    principal = msgspec.structs.replace(principal, expires_at=not_after)
    _still_valid(request, principal)
    return principal, True


def _still_valid(request: web.Request, principal: Principal) -> None:
    """Raises AuthenticationError if `principal`'s credential has run out: a JWT's `exp` (a
    ticket lives `TTL_S`, a JWT may have less left, and the socket it opened pushed the
    status and the held commands to a credential REST refuses) or a client certificate's
    notAfter (its connection, or a ticket asked for over it, outliving it)."""
    left = request.app[CREDENTIAL_LEFT](principal)
    if left is None or left > 0:
        return
    if principal.name in request.app[CERT_PRINCIPALS]:  # (a JWT's name is never configured)
        raise AuthenticationError("the client certificate has expired (notAfter passed)",
                                  reason=CERTIFICATE_EXPIRED)
    from rcan_rtps.governance.jwt import EXPIRED  # (loaded: a JWT made this principal)

    raise AuthenticationError("the JWT the ticket was asked with has expired", reason=EXPIRED)


def peer_certificate(request: web.Request) -> tuple[str, float] | None:
    """Subject CN and notAfter (Unix time) of the client certificate, if the TLS handshake
    verified one. The notAfter is OpenSSL's reading of the verified certificate (`ssl`'s
    `getpeercert`), the one the handshake was judged by."""
    transport = request.transport
    if transport is None:
        return None
    ssl_object = transport.get_extra_info("ssl_object")
    if not isinstance(ssl_object, ssl.SSLObject):
        return None
    cert = ssl_object.getpeercert()  # empty unless the certificate was verified
    if not cert:
        return None
    subject = cert.get("subject", ())
    names = [attr[1] for rdn in subject if isinstance(rdn, tuple) for attr in rdn
             if isinstance(attr, tuple) and attr[0] == "commonName"]
    if len(names) != 1:  # several CNs: no unambiguous identity
        return None
    return names[0], _not_after(cert.get("notAfter"))


def _not_after(text: object) -> float:
    """A certificate's notAfter as `getpeercert` spells it; one that cannot be read counts as
    passed (fail closed: OpenSSL verified a certificate that has one)."""
    try:
        return float(ssl.cert_time_to_seconds(text)) if isinstance(text, str) else 0.0
    except ValueError:
        return 0.0


async def safe_headers(request: web.Request, response: web.StreamResponse) -> None:
    """Every response (`on_response_prepare`, so also those of aiohttp's own errors and of
    the middlewares) says `nosniff`: a browser never runs an answer as another type than it
    is labelled (an error page echoing a path, a JSON body, as script or HTML). One that sets
    no caching of its own is not stored (`no-store`): status, audit pages and WebSocket
    tickets are for the caller now, not for a browser's disk or a proxy."""
    response.headers.setdefault("X-Content-Type-Options", "nosniff")
    response.headers.setdefault("Cache-Control", "no-store")
