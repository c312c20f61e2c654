"""The console's handlers: its static page, who the caller is, and WebSocket tickets.

`_console` registers the routes; this module, the page's files and their headers are loaded
by the first request for any of them (most runs are never opened in a browser).

- `GET /` redirects to `/console/`; `GET /console/` is the page, `GET /console/<file>` its
  assets (`rcan_rtps.console`). No principal needed: they hold no data. Each response carries
  a strict Content-Security-Policy (no inline script or style, same origin only, never
  framed) and `nosniff`; nothing is cached without revalidation (an upgraded bridge serves
  its own page).
- `GET /api/whoami`: the caller's principal and role, and what the console should offer it
  (the API decides either way: hiding a button is no permission check).
- `POST /api/ws-ticket`: a single-use ticket for `GET /api/ws?ticket=` (see `_tickets`).
"""

from __future__ import annotations

import msgspec
from aiohttp import web

from rcan_rtps.console import CONTENT_TYPES, CSP, asset, asset_names
from rcan_rtps.rcan import ErrorCode, Role

from ._bodies import error_response, json_response
from ._console import PREFIX
from ._keys import CHECKS, CREDENTIAL_LEFT, GOVERNOR, PRINCIPAL, SETTINGS, WS_TICKETS
from ._tickets import TicketReply

INDEX = "index.html"
HEADERS = {
    "Content-Security-Policy": CSP,
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Cross-Origin-Opener-Policy": "same-origin",
    "Cross-Origin-Resource-Policy": "same-origin",
    "Cache-Control": "no-cache",
}


class May(msgspec.Struct, kw_only=True):
    command: bool  # motion (`move`)
    approve: bool  # some held command could be this principal's to review
    # Its approvals must be signed (its signature policy is `required`): the console cannot
    # sign, so it offers only Deny and says where to approve from.
    must_sign_approvals: bool
    clear_estop: bool
    read_audit: bool


class WhoAmI(msgspec.Struct, kw_only=True):
    principal: str
    role: str
    # The roles this one acts for (itself and every lower one): a held command whose
    # `requires_auth_from_role` is among them is this principal's to approve.
    covers: list[str]
    may: May


class ConsolePages:
    """The page and its files (listed, then each read, on first request), and the redirect."""

    def __init__(self) -> None:
        self._names: frozenset[str] | None = None
        self._cache: dict[str, bytes] = {}

    def _serve(self, name: str) -> web.Response:
        if self._names is None:
            self._names = asset_names()
        if name not in self._names:
            return error_response(404, "NOT_FOUND", reason="no_such_asset", headers=HEADERS)
        body = self._cache.get(name)
        if body is None:
            body = self._cache[name] = asset(name)
        suffix = name[name.rindex("."):]
        return web.Response(body=body, headers={**HEADERS, "Content-Type": CONTENT_TYPES[suffix]})

    async def to_console(self, request: web.Request) -> web.Response:
        return web.Response(status=302, headers={**HEADERS, "Location": PREFIX})

    async def page(self, request: web.Request) -> web.Response:
        return self._serve(INDEX)

    async def file(self, request: web.Request) -> web.Response:
        return self._serve(request.match_info["name"])

    async def whoami(self, request: web.Request) -> web.Response:
        return await get_whoami(request)

    async def ws_ticket(self, request: web.Request) -> web.Response:
        return await post_ws_ticket(request)


async def get_whoami(request: web.Request) -> web.Response:
    principal, governor = request[PRINCIPAL], request.app[GOVERNOR]
    settings, role = request.app[SETTINGS], request[PRINCIPAL].role
    covers = sorted({r for r in Role if r <= role}, key=int)
    signatures = request.app[CHECKS].signatures
    return json_response(WhoAmI(
        principal=principal.name, role=role.name, covers=[r.name for r in covers],
        may=May(command=role >= governor.role_for("move"),
                approve=role >= settings.hitl_list_role,
                must_sign_approvals=signatures is not None
                and signatures.policy(principal.name) == "required",
                clear_estop=role >= governor.role_for("clear_estop"),
                read_audit=role >= settings.audit_read_role)))


async def post_ws_ticket(request: web.Request) -> web.Response:
    """A ticket for the caller's own WebSocket (any authenticated principal)."""
    tickets, principal = request.app[WS_TICKETS], request[PRINCIPAL]
    ticket = tickets.issue(principal)
    if ticket is None:
        return error_response(429, ErrorCode.RATE_LIMITED, reason="too_many_tickets",
                              headers={"Retry-After": "1"})
    # Good until the credential it was asked with runs out, if that comes first (a JWT's
    # exp, a certificate's notAfter): its redemption is refused from then on.
    left = request.app[CREDENTIAL_LEFT](principal)
    good_for = tickets.ttl_s if left is None else max(0.0, min(tickets.ttl_s, left))
    return json_response(TicketReply(ticket=ticket, expires_in_s=good_for,
                                     principal=principal.name),
                         headers={"Cache-Control": "no-store"})
