"""A cap on each principal's MCP sessions, beside the SDK's cap on them all (`/mcp`).

The SDK's session manager caps the sessions it holds (`max_sessions`): past it, every new
session is refused until one ends (DELETE) or has been idle `session_idle_timeout`. Alone,
that cap is anyone's to fill: one client that opens sessions and abandons them (never sends
DELETE, never comes back) shut every principal out for half an hour. Here each principal also
has a cap of its own, well below the whole, so that no principal alone fills the whole.

A principal at its cap that opens another session gets room made in its own sessions: the one
idle longest (no request in flight the longest) is closed — as the idle timeout would close
it, only sooner — and answers 404 like any expired session. Only when none of them is idle
(each has a request in flight: a call being answered, an event stream open) is the new one
refused, 429 with a JSON-RPC error that names the cap. Other principals' sessions are never
touched for that. The manager's overall cap stays, shared fairly: once it is reached (more
principals than it holds caps' worth, each at its own), a new session of a principal holding
fewer gets room made in the sessions of the one holding the most — at least two more than the
newcomer's principal, so that no swap could be undone by the next —, its idle longest closed
as above. Only when no such principal has one idle is the new session refused, 503, said as
plainly as the 429.

Why close rather than refuse: the sessions a principal leaves idle are almost always ones its
client has abandoned (a crashed or restarted agent: the SDK's client sends no DELETE when it
dies), and that client is the one asking again; refusing would lock the principal out of its
own door for the idle timeout. A session with a request in flight (a call being answered, an
event stream held open) is never closed for a newcomer: that would cut it off mid-call. One
idle between calls may be, live client or not: it reopens a session as an expired one would.
Closing a session does what its idle expiry does: motion it started is held (heartbeats) until
that move or goal ends, as after an expiry; its principal stops it from any session.

Only a request that can open a session gets room made for it: a POST of an `initialize`. Any
other request without a session id (a call, an event stream, a DELETE) opens none — the SDK
answers it 400 — so it closes none either; at a cap it is refused 400 at once, saying that
only an `initialize` opens a session. (Room made for a request that opens nothing would let
a principal holding no session close others' at the cost of one request, each time the cap
was reached again.)
"""

from __future__ import annotations

import json
import logging
import math
from contextvars import ContextVar
from typing import Any, NamedTuple

import pydantic_core
from mcp.server.auth.middleware.bearer_auth import AuthorizationContext
from mcp.server.streamable_http import StreamableHTTPServerTransport
from mcp.server.streamable_http_manager import StreamableHTTPSessionManager
from mcp_types import INTERNAL_ERROR, INVALID_REQUEST
from starlette.types import Message, Receive, Scope, Send

log = logging.getLogger(__name__)


class Refusal(NamedTuple):
    """A new session refused: the HTTP status, and what the JSON-RPC error says."""

    status: int
    code: int
    message: str


# The refusal of the opening request being handled, set by `_admit_session` (which returns
# only "no room") for `_handle_stateful_request` to answer: the SDK's own refusal is fixed
# text that names no cap and no principal.
_REFUSED: ContextVar[list[Refusal]] = ContextVar("rcan_mcp_session_refused")
# Whether the opening request being handled can open a session (`_opens`): only then is room
# made for it.
_OPENS: ContextVar[bool] = ContextVar("rcan_mcp_session_opens", default=True)
SESSION_HEADER = b"mcp-session-id"
SDK_LOG = "mcp.server.streamable_http_manager"
_SDK_PARTS = ("_admit_session", "_handle_stateful_request", "_session_owners",
              "_server_instances")


class _RefusalsSaidHere(logging.Filter):
    """Drops the SDK's log line of a refusal this module made and logged itself (the SDK's
    would count the sessions of all principals against the cap of one)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not _REFUSED.get([])


class CappedSessions(StreamableHTTPSessionManager):
    """The SDK's session manager, with `per_principal` sessions at most for each principal
    (the credential a session is bound to) within its `max_sessions`."""

    def __init__(self, *args: Any, per_principal: int, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if self.session_idle_timeout is None:  # (idleness is read off the idle clock)
            raise ValueError("a per-principal cap needs sessions that expire when idle")
        if self.max_sessions is not None and not 0 < per_principal < self.max_sessions:
            raise ValueError("a principal's cap must be below the cap on all sessions")
        self.per_principal = per_principal
        # The cap stands on the SDK's private parts (mcp 2.3): one that lacks them would
        # take every session uncapped, in silence. Said once, loudly, at start.
        missing = [n for n in _SDK_PARTS if not hasattr(self, n)]
        if missing:
            log.warning("MCP: this mcp SDK lacks %s: sessions are capped over all principals "
                        "only, not per principal", ", ".join(missing))
        sdk_log = logging.getLogger(SDK_LOG)
        if not any(isinstance(f, _RefusalsSaidHere) for f in sdk_log.filters):
            sdk_log.addFilter(_RefusalsSaidHere())

    async def _handle_stateful_request(self, scope: Scope, receive: Receive, send: Send
                                       ) -> None:
        refused: list[Refusal] = []
        opens = True
        if not any(k.lower() == SESSION_HEADER for k, _ in scope.get("headers", ())):
            opens, receive = await _opens(scope, receive)
        token, opening = _REFUSED.set(refused), _OPENS.set(opens)
        try:
            await super()._handle_stateful_request(scope, receive, _answering(refused, send))
        finally:
            _OPENS.reset(opening)
            _REFUSED.reset(token)

    def _admit_session(self, requestor: AuthorizationContext | None
                       ) -> StreamableHTTPServerTransport | None:
        # Called under the manager's lock, and synchronous: the count, the choice and the
        # close happen with no other opening in between (a flood of concurrent openings by
        # one principal gets no more than its cap).
        mine = [sid for sid, owner in self._session_owners.items() if owner == requestor]
        name = requestor["client_id"] if requestor is not None else "?"
        if not _OPENS.get() and (len(mine) >= self.per_principal or (
                self.max_sessions is not None
                and len(self._server_instances) >= self.max_sessions)):
            self._refuse(Refusal(400, INVALID_REQUEST, (
                "no session: a request without an Mcp-Session-Id opens one only if it is "
                "an initialize")))
            return None
        if requestor is not None and len(mine) >= self.per_principal:
            idle = self._idle_longest(mine)
            if idle is None:
                log.info("MCP: %s has %d sessions open, none idle: a new one refused",
                         name, len(mine))
                self._refuse(Refusal(429, INVALID_REQUEST, (
                    f"too many MCP sessions: principal {name!r} has {len(mine)} open, its "
                    f"cap ({self.per_principal} per principal), each with a request in "
                    "flight: end one (DELETE) or open a new one once one is idle")))
                return None
            log.info("MCP: %s is at its cap of %d sessions: the one idle longest is closed "
                     "for a new one", name, self.per_principal)
            self._expire(idle)
        if requestor is not None and self.max_sessions is not None \
                and len(self._server_instances) >= self.max_sessions:
            self._make_room_fairly(name, len(mine))
        admitted = super()._admit_session(requestor)
        if admitted is None:
            log.warning("MCP: %d sessions open, the cap over all principals: a new one of "
                        "%s refused", len(self._server_instances), name)
            timeout = self.session_idle_timeout or 0.0
            self._refuse(Refusal(503, INTERNAL_ERROR, (
                f"the bridge's MCP sessions are all taken ({self.max_sessions}, its cap over "
                f"all principals): try again later (a session idle {timeout / 60:g} min "
                "closes)")))
        return admitted

    def _make_room_fairly(self, name: str, held: int) -> None:
        """At the cap over all principals: close the session idle longest of the principal
        holding the most, if it holds at least `held` + 2 (`held`: the newcomer's principal's
        own); of the next such if the first has none idle. A swap between two principals one
        apart would only move the unfairness, and could be swapped back at once."""
        by_owner: dict[str, list[str]] = {}
        for sid, owner in self._session_owners.items():
            if owner is not None and owner["client_id"] != name:
                by_owner.setdefault(owner["client_id"], []).append(sid)
        for owner_name, theirs in sorted(by_owner.items(), key=lambda kv: -len(kv[1])):
            if len(theirs) < held + 2:
                return
            idle = self._idle_longest(theirs)
            if idle is not None:
                log.info("MCP: %d sessions open, the cap over all principals: %s holds %d, "
                         "its idle longest is closed for a new one of %s (holding %d)",
                         len(self._server_instances), owner_name, len(theirs), name, held)
                self._expire(idle)
                return

    def _idle_longest(self, sessions: list[str]) -> str | None:
        """Of `sessions`, the one with no request in flight for the longest, if any is idle.
        The SDK's idle clock says it: while a request is in flight (an event stream open
        included) a session's idle deadline is infinite; once the last one ends, it is that
        moment plus the idle timeout — the earliest deadline is the longest idle."""
        deadlines: dict[str, float] = {}
        for sid in sessions:
            idle_scope = self._server_instances[sid].idle_scope
            # (None: a session being opened, its transport not yet connected)
            if idle_scope is not None and not idle_scope.cancel_called \
                    and idle_scope.deadline != math.inf:
                deadlines[sid] = idle_scope.deadline
        return min(deadlines, key=deadlines.__getitem__) if deadlines else None

    def _expire(self, session_id: str) -> None:
        """Close an idle session as its idle timeout would: forgotten at once (its id answers
        404 from now on), and its idle scope cancelled, which ends its server task; that
        task discards the session and terminates its transport, as after an expiry."""
        transport = self._server_instances.pop(session_id)
        self._session_owners.pop(session_id, None)
        if transport.idle_scope is not None:
            transport.idle_scope.cancel()

    @staticmethod
    def _refuse(refusal: Refusal) -> None:
        refused = _REFUSED.get(None)
        if refused is not None:
            refused.append(refusal)


async def _opens(scope: Scope, receive: Receive) -> tuple[bool, Receive]:
    """Whether a request without a session id may open one (a POST of an `initialize`
    request, read with the SDK's own parser), and a `receive` that hands the SDK its body
    again. A body that comes in parts is not read ahead: it may be an opening."""
    if scope.get("method") != "POST":
        return False, receive
    first = await receive()
    if first.get("type") != "http.request" or first.get("more_body", False):
        return True, _replaying(first, receive)
    try:
        message = pydantic_core.from_json(first.get("body", b""))
    except (ValueError, RecursionError):  # not JSON: the SDK answers it 400, no opening
        return False, _replaying(first, receive)
    opening = isinstance(message, dict) and message.get("method") == "initialize" \
        and message.get("id") is not None  # (a notification of that name opens nothing)
    return opening, _replaying(first, receive)


def _replaying(first: Message, receive: Receive) -> Receive:
    """`receive`, its `first` message (already read) handed out once before the rest."""
    pending = [first]

    async def again() -> Message:
        return pending.pop() if pending else await receive()

    return again


def _answering(refused: list[Refusal], send: Send) -> Send:
    """`send`, but the SDK's answer to an opening this module refused replaced by the
    refusal's own (the SDK's is one message start and one body: both are dropped)."""

    async def answer(message: Message) -> None:
        if not refused:
            await send(message)
            return
        if message["type"] != "http.response.start":
            return
        status, code, said = refused[0]
        body = json.dumps({"jsonrpc": "2.0", "id": None,
                           "error": {"code": code, "message": said}}).encode()
        await send({"type": "http.response.start", "status": status,
                    "headers": [(b"content-type", b"application/json"),
                                (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body, "more_body": False})

    return answer
