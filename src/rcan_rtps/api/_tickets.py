"""WebSocket tickets: how a browser authenticates `GET /api/ws`.

A browser cannot set `Authorization` on a WebSocket. The console asks `POST /api/ws-ticket`
(with its bearer token, like any API call) for a ticket and opens `/api/ws?ticket=<ticket>`.
A ticket is:

- single-use: redeeming it removes it, whether the socket then opens or not;
- short-lived: `TTL_S` seconds from its issue (monotonic clock);
- its issuer's: the socket's principal is the one that asked for it (a ticket carries no
  role of its own, and nothing of the bearer token);
- no longer good than that credential: redeemed once the JWT it was asked with has expired,
  or the client certificate's notAfter has passed, it is refused (401 `jwt_expired`,
  `certificate_expired`: `_middlewares`), as the credential itself would be;
- bounded: at most `MAX_OUTSTANDING` unredeemed tickets exist, and at most `PER_PRINCIPAL`
  of one principal (beyond: 429) — a page needs one at a time, and one principal (a GUEST)
  asking in a loop must not use up every other principal's tickets, console included;
- same-origin: a browser redeeming it from another origin (an `Origin` header that names
  another host than the request's) is refused, and the ticket is spent.

Tickets are kept by their SHA-256, so looking one up compares digests, not the secret.
Nothing outlives the process. A ticket is not a credential for anything but the socket.
"""

from __future__ import annotations

import hashlib
import secrets
from collections import Counter, OrderedDict
from collections.abc import Callable
from urllib.parse import urlsplit

import msgspec
from aiohttp import web

from rcan_rtps._counts import count_down
from rcan_rtps.governance import Principal

TTL_S = 30.0
MAX_OUTSTANDING = 1024
PER_PRINCIPAL = 8
WS_PATH = "/api/ws"
TICKET_PATH = "/api/ws-ticket"


class TicketReply(msgspec.Struct, kw_only=True):
    ticket: str
    expires_in_s: float
    principal: str
    ws_path: str = WS_PATH


def _digest(ticket: str) -> bytes:
    return hashlib.sha256(ticket.encode("utf-8", "surrogateescape")).digest()


class WsTickets:
    """The unredeemed tickets of one app; `now` is a monotonic clock in seconds."""

    def __init__(self, now: Callable[[], float], *, ttl_s: float = TTL_S,
                 max_outstanding: int = MAX_OUTSTANDING,
                 per_principal: int = PER_PRINCIPAL) -> None:
        self._now = now
        self._ttl = ttl_s
        self._max = max_outstanding
        self._per_principal = per_principal
        # digest → (principal, expiry); insertion order is expiry order (one fixed TTL).
        self._open: OrderedDict[bytes, tuple[Principal, float]] = OrderedDict()
        self._held: Counter[str] = Counter()  # principal name → its unredeemed tickets

    def issue(self, principal: Principal) -> str | None:
        """A new ticket for `principal`, or None when too many are outstanding (its own, or
        all principals')."""
        self._forget_expired()
        if len(self._open) >= self._max or self._held[principal.name] >= self._per_principal:
            return None
        ticket = secrets.token_urlsafe(32)
        self._open[_digest(ticket)] = (principal, self._now() + self._ttl)
        self._held[principal.name] += 1
        return ticket

    def redeem(self, ticket: str) -> Principal | None:
        """The ticket's principal, once; None if unknown, spent or expired."""
        found = self._open.pop(_digest(ticket), None)
        if found is None:
            return None
        principal, expires = found
        count_down(self._held, principal.name)
        return principal if self._now() < expires else None

    @property
    def ttl_s(self) -> float:
        return self._ttl

    @property
    def outstanding(self) -> int:
        return len(self._open)

    def _forget_expired(self) -> None:
        now = self._now()
        while self._open:
            digest, (_, expires) = next(iter(self._open.items()))
            if expires > now:
                return
            count_down(self._held, self._open.pop(digest)[0].name)


def ticket_of(request: web.Request) -> str | None:
    """The ticket a WebSocket request presents (`/api/ws?ticket=`), if any."""
    if request.path != WS_PATH or request.method != "GET":
        return None
    return request.query.get("ticket")


def same_origin(request: web.Request) -> bool:
    """No `Origin` (not a browser), or one naming the host the request was sent to."""
    origin = request.headers.get("Origin")
    if origin is None:
        return True
    try:
        netloc = urlsplit(origin).netloc
    except ValueError:
        return False
    return bool(netloc) and netloc.lower() == request.host.lower()

