"""`RobotApi` over the bridge's REST API, with the agent's token and nothing else (the stdio
server, `rcan-rtps mcp`).

Replies come back as they are (status and JSON body), refusals included: deciding is the
bridge's. What is not a reply — the bridge unreachable, a body that is not JSON — is a
`BridgeUnavailable`, whose message says so without a traceback.
"""

from __future__ import annotations

import asyncio
import copy
import json
from collections.abc import Awaitable, Iterable
from types import TracebackType
from typing import Any, overload
from urllib.parse import quote, urlsplit

import aiohttp

from rcan_rtps import _transport_warnings as transport

from .ports import Blob, BridgeUnavailable, Reply

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


class BridgeClient:
    def __init__(self, url: str, token: str, *, timeout_s: float = REQUEST_TIMEOUT_S) -> None:
        self.url = check_url(url)
        self._headers = {"Authorization": f"Bearer {token}"}
        self._timeout = aiohttp.ClientTimeout(total=timeout_s)
        self._http: aiohttp.ClientSession | None = None
        self._command_headers: dict[str, str] = {}

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
        if self._http is not None:
            await self._http.close()

    # -- RobotApi -------------------------------------------------------------------------

    async def command(self, body: dict[str, Any]) -> Reply:
        return await self._request("POST", "/api/command", body, headers=self._command_headers)

    async def motion(self, body: dict[str, Any]) -> Reply:
        return await self.command(body)  # cancelled, its request is cut off (as any command's)

    def cancel_motion(self) -> Awaitable[Reply]:
        return asyncio.ensure_future(self._request("POST", "/api/command/cancel"))

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
