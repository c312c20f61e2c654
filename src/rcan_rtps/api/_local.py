"""The API as one principal sees it, called in process: what the bridge's `/mcp` tools use.

Each method is its REST route's function (`_routes`, `_rare_routes`, `_commands`,
`_safety_manifest`) with the principal that authenticated the MCP request — the same intake,
governance, audit and replies, without a second HTTP round trip. Replies are the JSON the
route would have sent.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Awaitable
from typing import TYPE_CHECKING, Any

import msgspec
from aiohttp import web

from rcan_rtps.governance import Principal
from rcan_rtps.governance.governor import ClientCancel

from . import _rare_routes as rare
from . import _routes as r
from ._bodies import GoalList, PendingList, error_body
from ._commands import run_command, schema_failure, too_large
from ._images import image_list
from ._intake import STOP_ROOM
from ._keys import (
    CHECKS,
    CREDENTIAL_LEFT,
    GOVERNOR,
    IMAGES,
    INVOCATIONS,
    OBSERVE,
    ROBOT,
    SETTINGS,
    STATUS,
)
from ._safety_manifest import manifest_reply
from .ports import ImageFrame

if TYPE_CHECKING:
    from rcan_rtps.mcp_server.ports import Blob, Reply

NOT_TEXT = "a string holds an unpaired surrogate: not Unicode text"
CREDENTIAL_EXPIRED = "credential_expired"  # a heartbeat's 401 once no credential holds


def _outlasts(new: Principal, old: Principal) -> bool:
    """Whether `new`'s credential holds longer than `old`'s (None: it does not expire)."""
    return old.expires_at is not None and (new.expires_at is None
                                           or new.expires_at > old.expires_at)


async def _acked(cancelled: ClientCancel, principal: Principal) -> Reply:
    return _reply(200, await r.cancel_acked(cancelled, principal))


def _reply(status: int, body: Any) -> Reply:
    from rcan_rtps.mcp_server.ports import Reply

    if isinstance(body, bytes):
        return Reply(status, json.loads(body))
    return Reply(status, msgspec.to_builtins(body))


class LocalApi:
    """`mcp_server.ports.RobotApi` inside the bridge, as `principal`; `warnings`: what the
    request was found wrong with before it reached a tool, which its stops carry;
    `measured`: the door has measured (and warned of) the size of what the client sent, so a
    command made from it is not measured against `max_body_bytes` again (up to `STOP_ROOM`
    times it, as the doors read); `commanded`: whether a command was sent through it (a stop
    the SDK did run)."""

    def __init__(self, app: web.Application, principal: Principal,
                 fixed_manifest: dict[str, Any], warnings: tuple[str, ...] = (), *,
                 measured: bool = False) -> None:
        self._app = app
        self._principal = principal
        self._manifest = fixed_manifest
        self._warnings = warnings
        self._measured = measured
        self.commanded = False

    async def command(self, body: dict[str, Any]) -> Reply:
        self.commanded = True
        app, governor = self._app, self._app[GOVERNOR]
        try:
            raw = msgspec.json.encode(body)
        except UnicodeEncodeError:  # an unpaired surrogate (from an agent's JSON): no text
            return _reply(*await schema_failure(governor, self._principal, "$", NOT_TEXT))
        limit = app[SETTINGS].max_body_bytes
        if len(raw) > limit * STOP_ROOM:  # (as the HTTP doors read no further)
            return _reply(*await too_large(governor, self._principal))
        if self._measured:
            limit *= STOP_ROOM
        # Over `limit`, only a stop is taken (`_intake._oversize`), as at the HTTP doors.
        return _reply(*await run_command(governor, self._principal, raw, app[OBSERVE],
                                         app[CHECKS], app[INVOCATIONS], self._warnings,
                                         limit=limit))

    async def motion(self, body: dict[str, Any]) -> Reply:
        try:
            return await self.command(body)
        except asyncio.CancelledError:
            # Its client cancelled the call (the SDK cancels the handler): told in this step,
            # before the decision's task runs again. The stop's entry is the governor's task.
            self._app[GOVERNOR].command_cancelled(self._principal)
            raise

    def cancel_motion(self) -> Awaitable[Reply]:
        cancelled = self._app[GOVERNOR].motion_cancelled(self._principal)  # now, in this step
        return _acked(cancelled, self._principal)

    def renewed(self, principal: Principal) -> None:
        """A later request of the principal's, with a credential that may hold longer (a
        fresh JWT): its heartbeats go on for as long as the latest credential holds."""
        if principal.name == self._principal.name and _outlasts(principal, self._principal):
            self._principal = principal

    async def heartbeat(self) -> Reply:
        # Heartbeats are the principal's requests: refused, as REST refuses them, once its
        # credential has run out (its control session then lapses, and the bridge stops what
        # it left moving), not sent on its behalf for as long as its motion would run.
        left = self._app[CREDENTIAL_LEFT](self._principal)
        if left is not None and left <= 0:
            return _reply(401, error_body("UNAUTHENTICATED", reason=CREDENTIAL_EXPIRED))
        return _reply(200, r.heartbeat(self._app[GOVERNOR], self._principal))

    async def status(self) -> Reply:
        return _reply(200, self._app[STATUS].snapshot())

    async def goals(self) -> Reply:
        return _reply(200, GoalList(goals=self._app[ROBOT].goals()))

    async def goal(self, goal_id: str) -> Reply:
        return _reply(*r.goal_view(self._app[ROBOT], goal_id))

    async def pending(self, pending_id: str) -> Reply:
        return _reply(*await rare.pending_view(self._app[GOVERNOR], self._principal, pending_id))

    async def my_pending(self) -> Reply:
        governor = self._app[GOVERNOR]
        await governor.expire_pending()
        return _reply(200, PendingList(pending=rare.own_pending(governor, self._principal)))

    async def my_audit(self, last: int) -> Reply:
        return _reply(*await rare.my_audit(self._app, self._principal, 0, last, True))

    async def safety_manifest(self) -> Reply:
        return _reply(*await manifest_reply(self._app, self._manifest))

    async def images(self) -> Reply:
        return _reply(200, image_list(self._app[IMAGES].names()))

    async def image(self, name: str) -> Reply | Blob:
        from rcan_rtps.mcp_server.ports import Blob

        status, frame = await rare.image_reply(self._app[IMAGES], name)
        if isinstance(frame, ImageFrame):
            return Blob(frame.mime, frame.data)
        return _reply(status, frame)
