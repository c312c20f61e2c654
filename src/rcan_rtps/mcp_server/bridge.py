"""`RobotApi` over the bridge's REST API, with the agent's token and nothing else (the stdio
server, `rcan-rtps mcp`).

Replies come back as they are (status and JSON body), refusals included: deciding is the
bridge's. What is not a reply — the bridge unreachable, a body that is not JSON — is a
`BridgeUnavailable`, whose message says so without a traceback.

A stop is carried through: its caller cancelled (its MCP client cancelled the call) gets no
reply, but the request goes on — a stop must reach the bridge all the same (cut off, it
mostly never did). A motion command is carried through too and, cancelled so, withdrawn
(`motion`). Any other command is cut off with its caller: a `clear_estop`, `lock` or
`unlock` its client no longer wants is not sent on (if the bridge had it whole already, it
decides it: the client cannot tell).
"""

from __future__ import annotations

import asyncio
import copy
import json
import logging
from collections.abc import Awaitable, Callable, Coroutine, Iterable
from types import TracebackType
from typing import Any, overload
from urllib.parse import quote, urlsplit

import aiohttp

from rcan_rtps import _transport_warnings as transport
from rcan_rtps.rcan._salvage import stop_intent

from .ports import Blob, BridgeUnavailable, Reply

log = logging.getLogger(__name__)
REQUEST_TIMEOUT_S = 10.0
__all__ = ["BridgeClient", "BridgeUnavailable", "Reply", "check_url"]


def check_url(url: str) -> str:
    """The bridge's base URL (http or https, a host, no path beyond `/`), without its `/`."""
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"--url {url!r}: expected http(s)://host:port of a running bridge")
    if parts.path not in ("", "/") or parts.query or parts.fragment:
        raise ValueError(f"--url {url!r}: give the bridge's base URL, without a path")
    return url.rstrip("/")


def path_part(value: str) -> str:
    """A value as one path segment (an id an agent gave is never a path of its own)."""
    return quote(value, safe="")


def _settled(carried: set[asyncio.Task[Any]]) -> Callable[[asyncio.Task[Any]], None]:
    """A carried request's end: forgotten, and its error taken (its caller may be gone)."""
    def done(task: asyncio.Task[Any]) -> None:
        carried.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.debug("a request whose caller was cancelled failed: %s", task.exception())
    return done


_warned_too_old = False


def _warn_too_old(url: str) -> None:
    """Once a process: the bridge has no POST /api/command/cancel (it predates it), so a
    cancelled motion call's motion is not stopped, nor its held command withdrawn."""
    global _warned_too_old
    if _warned_too_old:
        return
    _warned_too_old = True
    log.warning("the bridge at %s is too old to withdraw a cancelled motion call (POST "
                "/api/command/cancel: 404): its motion may start or run on, and a command of "
                "it held for approval stays pending; the agent should send stop (and withdraw "
                "what it no longer wants approved)", url)


def _stopped_by(stop: Reply, command: Reply) -> bool:
    """Whether the stop of a cancel (POST /api/command/cancel) ended what `command` started:
    its stream, or its goal."""
    applied = (stop.body.get("decision") or {}).get("applied") or {}
    started = command.body.get("message_id")
    if started is not None and applied.get("stream_ended") == started:
        return True
    goal = command.body.get("goal_id")
    return goal is not None and goal in (applied.get("goals_cancelled") or ())


class BridgeClient:
    def __init__(self, url: str, token: str, *, timeout_s: float = REQUEST_TIMEOUT_S) -> None:
        self.url = check_url(url)
        self._headers = {"Authorization": f"Bearer {token}"}
        self._timeout = aiohttp.ClientTimeout(total=timeout_s)
        self._http: aiohttp.ClientSession | None = None
        self._command_headers: dict[str, str] = {}
        # Requests carried through for callers that were cancelled, and the withdrawals of
        # cancelled motion commands: all of them done before the session closes (shared by
        # the `warning` views, as the session is).
        self._carried: set[asyncio.Task[Any]] = set()
        self._withdrawing: set[asyncio.Task[None]] = set()

    def warning(self, warnings: Iterable[str]) -> BridgeClient:
        """This client (its session shared), its commands carrying `warnings` for their audit
        entries: what the stdio door found wrong with a stop (`rcan_rtps._transport_warnings`;
        the bridge records them for a stop only)."""
        value = transport.header_value(warnings)
        view = copy.copy(self)
        view._command_headers = {} if value is None else {transport.HEADER: value}
        return view

    async def __aenter__(self) -> BridgeClient:
        self._http = aiohttp.ClientSession(headers=self._headers, timeout=self._timeout)
        return self

    async def __aexit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                        tb: TracebackType | None) -> None:
        while self._carried or self._withdrawing:  # each bounded by the request timeout
            await asyncio.wait({*self._carried, *self._withdrawing})
        if self._http is not None:
            await self._http.close()

    # -- RobotApi -------------------------------------------------------------------------

    async def command(self, body: dict[str, Any]) -> Reply:
        if stop_intent(body.items()) is None:  # not a stop: it goes no further than its caller
            return await self._command(body)
        return await asyncio.shield(self._carry(self._command(body)))

    async def motion(self, body: dict[str, Any]) -> Reply:
        if self._withdrawing:  # a cancelled motion command's withdrawal comes first (`_withdraw`)
            await asyncio.wait(set(self._withdrawing))
        sent = self._carry(self._command(body))
        try:
            return await asyncio.shield(sent)
        except asyncio.CancelledError:
            told = self.cancel_motion()  # at once: its motion must not start meanwhile
            withdrawing = asyncio.ensure_future(self._withdraw(sent, told))
            self._withdrawing.add(withdrawing)
            withdrawing.add_done_callback(self._withdrawing.discard)
            raise

    def cancel_motion(self) -> Awaitable[Reply]:
        return self._carry(self._cancel())

    async def _cancel(self) -> Reply:
        told = await self._request("POST", "/api/command/cancel")
        if told.status == 404:
            _warn_too_old(self.url)
        return told

    async def _withdraw(self, sent: asyncio.Task[Reply], told: Awaitable[Reply]) -> None:
        """A cancelled motion command's withdrawal, once its reply is known: the bridge was
        told at once (`told`), but that request may have reached it before the command itself
        did (two connections: either may be read first). A command then executed, which that
        stop did not stop, is stopped now. Meanwhile this seat's next motion command waits
        (`motion`): this second stop must not stop that."""
        try:
            stopped, reply = await told, await sent
            outcome = reply.body.get("outcome")
            # Held for a human after the cancel was decided (it found nothing of its yet):
            # a second cancel withdraws it (`Governor.command_cancelled`), lest an approval
            # start it for nobody.
            if outcome == "pending_auth" or (outcome == "executed"
                                             and not _stopped_by(stopped, reply)):
                await self.cancel_motion()
        except BridgeUnavailable as exc:
            log.warning("withdrawing a cancelled motion command: %s", exc)
        except Exception:  # nobody awaits this: the log has it
            log.exception("withdrawing a cancelled motion command failed")

    def _carry(self, request: Coroutine[Any, Any, Reply]) -> asyncio.Task[Reply]:
        """`request` in a task of its own, which a cancelled caller leaves running."""
        task = asyncio.ensure_future(request)
        self._carried.add(task)
        task.add_done_callback(_settled(self._carried))
        return task

    async def _command(self, body: dict[str, Any]) -> Reply:
        return await self._request("POST", "/api/command", body, headers=self._command_headers)

    async def heartbeat(self) -> Reply:
        return await self._request("POST", "/api/heartbeat")

    async def status(self) -> Reply:
        return await self._request("GET", "/api/status")

    async def goals(self) -> Reply:
        return await self._request("GET", "/api/goals")

    async def goal(self, goal_id: str) -> Reply:
        return await self._request("GET", f"/api/goals/{path_part(goal_id)}")

    async def pending(self, pending_id: str) -> Reply:
        return await self._request("GET", f"/api/hitl/pending/{path_part(pending_id)}")

    async def my_pending(self) -> Reply:
        return await self._request("GET", "/api/hitl/pending?mine=true")

    async def my_audit(self, last: int) -> Reply:
        return await self._request("GET", f"/api/audit/mine?last={int(last)}")

    async def safety_manifest(self) -> Reply:
        return await self._request("GET", "/api/safety/manifest")

    async def images(self) -> Reply:
        return await self._request("GET", "/api/images")

    async def image(self, name: str) -> Reply | Blob:
        return await self._request("GET", f"/api/images/{path_part(name)}", blob=True)

    @overload
    async def _request(self, method: str, path: str, body: Any = None, *,
                       headers: dict[str, str] | None = None) -> Reply: ...

    @overload
    async def _request(self, method: str, path: str, body: Any = None, *,
                       headers: dict[str, str] | None = None, blob: bool) -> Reply | Blob: ...

    async def _request(self, method: str, path: str, body: Any = None, *,
                       headers: dict[str, str] | None = None,
                       blob: bool = False) -> Reply | Blob:
        """The reply; with `blob`, a successful reply that is not JSON comes as it is."""
        if self._http is None:
            raise RuntimeError("BridgeClient used outside `async with`")
        try:
            async with self._http.request(method, self.url + path, json=body,
                                          headers=headers) as resp:
                raw = await resp.read()
                status = resp.status
                if blob and status == 200 and resp.content_type != "application/json":
                    return Blob(resp.content_type, raw)
        except (aiohttp.ClientError, asyncio.TimeoutError, OSError) as exc:
            raise BridgeUnavailable(f"the bridge at {self.url} did not answer {method} {path}: "
                                    f"{type(exc).__name__} {exc}".rstrip()) from exc
        try:
            decoded = json.loads(raw) if raw else {}
        except ValueError as exc:
            raise BridgeUnavailable(f"the bridge at {self.url} answered {method} {path} with "
                                    f"{status} and a body that is not JSON") from exc
        if not isinstance(decoded, dict):
            raise BridgeUnavailable(f"{method} {path}: expected a JSON object, got "
                                    f"{type(decoded).__name__}")
        return Reply(status, decoded)
