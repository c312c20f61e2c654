"""The MCP server: the tools of `tools`, each call a request to the bridge (`bridge`).

Built on the official SDK's low-level `Server` (the tools' schemas are derived, not written as
functions). Every action's call is a short-form COMMAND carrying the agent's identity: the
configured `ai_provider` and `ai_model`, the MCP client's `name/version` as `ai_client`, and a
`thought_id` of its own (GET /api/thoughts/{thought_id} shows what it led to). What the bridge
decides comes back as it is; a refusal is a tool error (`isError`) with the RCAN `error_code`
and `reason`. Tool errors never carry a traceback: an unexpected one is logged on stderr.
"""

from __future__ import annotations

import asyncio
import base64
import gc
import json
import logging
import signal
import sys
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import replace
from typing import Any, Generic, TypeVar, cast

import anyio
import mcp_types as types
import msgspec
import pydantic
from mcp.server.context import ServerRequestContext
from mcp.server.lowlevel import Server
from mcp.server.stdio import stdio_server
from mcp.shared.dispatcher import coerce_request_id
from mcp.shared.exceptions import MCPError
from mcp.shared.message import SessionMessage
from mcp_types.jsonrpc import INTERNAL_ERROR, INVALID_REQUEST, RequestId

from rcan_rtps import __version__
from rcan_rtps import _stop_signals as stop_signals

from .bridge import BridgeClient
from .keepalive import Keepalive
from .ports import Blob, BridgeUnavailable, Reply, RobotApi
from .resources import (
    IMAGE_DESCRIPTION,
    IMAGE_PREFIX,
    IMAGE_TEMPLATE,
    JSON_TYPE,
    RESOURCE_NOT_FOUND,
    RESOURCES,
)
from .results import (
    Result,
    ai_fields,
    command_body,
    failure_json,
    outcome_note,
    reply_json,
    result_json,
)
from .seat import Agent, Seat
from .stdio import StdinLines
from .stdio_door import PARSE_ERROR, StdioDoor, Unreadable
from .stop_tool import guarded, run_stop, stop_reply
from .tools import DURATION, WAIT_MAX_S, ToolDef, derive_tools

log = logging.getLogger(__name__)
POLL_S = 0.5
CLIENT_MAX = 256  # the bridge's `ai_client` is at most this long
LIST_TTL_MS = 300_000
# Motion calls answered, remembered for a cancel that crossed the answer: so many a principal.
ANSWERED_KEPT = 256
INSTRUCTIONS = (
    "Tools of one robot, governed by its rcan-rtps bridge: each action is checked against "
    "your role, the safety limits and the e-stop, and audited with your identity. A move is "
    "timed (duration_s). State your confidence: low confidence waits for a human. A held "
    "command returns a pending_id: call wait_for_approval. estop and stop always work.")


def client_of(ctx: ServerRequestContext[Any]) -> str:
    """The MCP client's `name/version`, as its initialization (or request) said."""
    params = ctx.session.client_params
    info = params.client_info if params is not None else None
    if info is None:
        return "unknown"
    return f"{info.name}/{info.version}"[:CLIENT_MAX]


def typed(done: Result) -> types.CallToolResult:
    """A tool result (`results`' JSON form) as the SDK's model, built as its fields are
    (not validated again: half again the cost, per call)."""
    return types.CallToolResult(
        content=[types.TextContent(type="text", text=c["text"]) for c in done["content"]],
        structured_content=done["structuredContent"], is_error=done["isError"])


def result(reply: Reply, note: str, **extra: Any) -> types.CallToolResult:
    """The bridge's reply as a tool result: an error when it refused (4xx, 5xx)."""
    return typed(reply_json(reply, note, **extra))


def tool_result(data: dict[str, Any], note: str, *, error: bool) -> types.CallToolResult:
    return typed(result_json(data, note, error=error))


def failure(message: str, error_code: str) -> types.CallToolResult:
    return typed(failure_json(message, error_code))


SeatOf = Callable[[ServerRequestContext[Any]], Seat]
K = TypeVar("K")
V = TypeVar("V")


class PerPrincipal(Generic[K, V]):
    """What is remembered of a principal's calls, apart from everyone else's (its seats'
    `Keepalive` names it: one a principal), at most `ANSWERED_KEPT` of them, its oldest let
    go first. Apart, so that another principal's calls never push one of its out: a cancel
    crossing its answer would then name nothing, and its motion run on, or stay held for a
    human to approve, for a client that cancelled it."""

    def __init__(self) -> None:
        self._kept: dict[Keepalive, OrderedDict[K, V]] = {}

    def get(self, principal: Keepalive, key: K) -> V | None:
        kept = self._kept.get(principal)
        return None if kept is None else kept.get(key)

    def put(self, principal: Keepalive, key: K, value: V) -> None:
        kept = self._kept.setdefault(principal, OrderedDict())
        kept[key] = value
        kept.move_to_end(key)
        while len(kept) > ANSWERED_KEPT:
            kept.popitem(last=False)

    def pop(self, principal: Keepalive, key: K) -> V | None:
        kept = self._kept.get(principal)
        if kept is None:
            return None
        value = kept.pop(key, None)
        if not kept:
            del self._kept[principal]
        return value


class RobotTools:
    """The handlers: list the derived tools and resources, run a tool, read a resource.

    `seat_of` says who calls: one fixed seat over stdio, the authenticated principal of each
    request at the bridge's `/mcp`. `tools` (tests) replaces the registry's; otherwise the
    tools are derived once the robot's safety manifest is known (its limits go into the
    descriptions), from `manifest` or from the bridge on the first listing.
    """

    def __init__(self, seat_of: SeatOf, *, tools: dict[str, ToolDef] | None = None,
                 manifest: Mapping[str, Any] | None = None) -> None:
        self._seat_of = seat_of
        self._described = tools is not None or manifest is not None
        self._tools = tools if tools is not None else derive_tools(manifest=manifest)
        self._listing: tuple[dict[str, ToolDef], types.ListToolsResult] | None = None
        # Motion calls answered `executed` or `pending_auth`, per principal, by MCP session
        # and request id, for a cancel that crossed the answer (`cancelled`): the key of their
        # hold (none for a held one: nothing of it runs yet).
        self._answered: PerPrincipal[tuple[str | None, RequestId], str] = PerPrincipal()
        # Per MCP session (per principal), its motion call answered last, until its next
        # request: a listing that comes next is the SDK client checking that answer
        # (`_checking`).
        self._last_answered: PerPrincipal[str | None, tuple[str | None, RequestId]] = (
            PerPrincipal())

    async def list_tools(self, ctx: ServerRequestContext[Any],
                         params: types.PaginatedRequestParams | None) -> types.ListToolsResult:
        self._checking(self._seat_of(ctx), ctx.request_id)
        if not self._described:
            await self._describe(self._seat_of(ctx).api)
        if self._listing is None or self._listing[0] is not self._tools:
            # The tools of a run do not change once described: clients may keep the list
            # (a 2026-07-28 client otherwise lists them again to check each call's result).
            self._listing = (self._tools, types.ListToolsResult(ttl_ms=LIST_TTL_MS, tools=[
                types.Tool(name=t.name, description=t.description, input_schema=t.input_schema)
                for t in self._tools.values()]))
        return self._listing[1]

    def is_motion(self, name: str) -> bool:
        """The tool named so is a motion tool's (`move`, `navigate`, ...)."""
        tool = self._tools.get(name)
        return tool is not None and tool.action is not None and tool.action.motion

    def input_schema(self, name: str) -> Mapping[str, Any] | None:
        """A tool's input schema, for the SDK's checks of a call (without listing them all)."""
        tool = self._tools.get(name)
        return None if tool is None else tool.input_schema

    async def _describe(self, api: RobotApi) -> None:
        """The tools with this robot's limits; without them while the bridge cannot say."""
        try:
            manifest = await api.safety_manifest()
        except BridgeUnavailable as exc:
            log.warning("safety manifest: %s", exc)
            return
        if manifest.ok:
            self._tools = derive_tools(manifest=manifest.body)
            self._described = True

    async def call_tool(self, ctx: ServerRequestContext[Any],
                        params: types.CallToolRequestParams) -> types.CallToolResult:
        seat = self._seat_of(ctx)
        self._last_answered.pop(seat.keepalive, seat.session)  # a call came in between
        tool = self._tools.get(params.name)
        if tool is None:
            return failure(f"no tool named {params.name!r}", "UNKNOWN_TOOL")
        args = dict(params.arguments or {})

        async def call() -> types.CallToolResult:
            if tool.action is not None:
                return await self._command(seat, tool, args, client_of(ctx))
            return await self._read(seat, tool.name, args)

        done = await guarded(tool.name, call, failure)
        if tool.action is not None and tool.action.motion and ctx.request_id is not None:
            self._answered_motion(seat, ctx.request_id, done)
        return done

    def _answered_motion(self, seat: Seat, request_id: RequestId,
                         done: types.CallToolResult) -> None:
        data = done.structured_content or {}
        # A held one too: a client that drops its `pending_auth` answer never learns of it,
        # and a human approving it later would move the robot for a caller that cancelled.
        if data.get("outcome") not in ("executed", "pending_auth"):
            return
        key = (seat.session, coerce_request_id(request_id))
        self._answered.put(seat.keepalive, key, str(data.get("thought_id")))
        self._last_answered.put(seat.keepalive, seat.session, key)

    def _checking(self, seat: Seat, request_id: RequestId | None) -> None:
        """A tools/list right after a motion call's answer: the SDK's client lists the tools
        to check that answer when it has no list (a session's first call; a list past its
        ttl), and a caller cancelled meanwhile never gets the answer — the client's
        `notifications/cancelled` names this listing, not the call. A cancel of it is taken
        as one of that call (`cancelled`): else the move ran on, held by the heartbeats for
        its whole duration. A listing cancelled for its own sake then stops the principal's
        motion too: the safe side."""
        last = self._last_answered.pop(seat.keepalive, seat.session)
        answered = None if last is None else self._answered.get(seat.keepalive, last)
        if answered is None or request_id is None:
            return
        self._answered.put(seat.keepalive, (seat.session, coerce_request_id(request_id)),
                           answered)

    async def cancelled(self, ctx: ServerRequestContext[Any],
                        params: types.CancelledNotificationParams) -> None:
        """A client's `notifications/cancelled`. One naming a call being carried out cancels
        its handler (the SDK does that; a motion call's `RobotApi.motion` then withdraws its
        motion). One naming a motion call already answered `executed` or `pending_auth`
        crossed that answer, which the client drops: it never learns its motion started, or
        was held for a human, so that motion is stopped, or withdrawn, now, as if the cancel
        had come in time (the principal's own alone: `Governor.command_cancelled`)."""
        if params.request_id is None:
            return
        seat = self._seat_of(ctx)
        # Only its principal's calls are looked at: another's is never its to cancel.
        answered = self._answered.pop(seat.keepalive,
                                      (seat.session, coerce_request_id(params.request_id)))
        if answered is None:
            return
        seat.keepalive.release(answered)
        log.warning("the MCP client cancelled motion call %r after its answer (it started, "
                    "or was held for approval): its principal's motion is stopped and its "
                    "held motion withdrawn", params.request_id)
        try:
            await seat.api.cancel_motion()
        except BridgeUnavailable as exc:
            log.warning("stopping the motion of a cancelled call: %s", exc)

    # -- actions --------------------------------------------------------------------------

    async def _command(self, seat: Seat, tool: ToolDef, args: dict[str, Any],
                       client: str) -> types.CallToolResult:
        assert tool.action is not None
        if tool.action.stopping:  # as the doors run the stops the SDK does not
            return typed(await run_stop(seat, tool.name, args, client))
        body = command_body(seat.agent, client, tool.name, args)
        params, thought_id = body["params"], body["thought_id"]
        if tool.timed and params.get(DURATION) is None:
            return failure(f"`{DURATION}` is required: a {tool.name} an agent starts is timed",
                           "SCHEMA_VALIDATION_FAILED")
        with seat.keepalive.calling(seat.session):
            # A motion call its client cancels must not leave the robot moving (`motion`).
            send = seat.api.motion if tool.action.motion else seat.api.command
            reply = await send(body)
            if reply.ok:
                self._started(seat, tool, params, reply.body, key=thought_id)
        return result(reply, outcome_note(reply.body), thought_id=thought_id)

    def _started(self, seat: Seat, tool: ToolDef, params: dict[str, Any],
                 body: dict[str, Any], key: str) -> None:
        """Hold the control session for what an executed command left running."""
        spec, keepalive = tool.action, seat.keepalive
        if spec is None or body.get("outcome") != "executed":
            return
        applied = body.get("applied") or {}
        duration = applied.get(DURATION, params.get(DURATION))  # as governed, if it says
        if tool.timed and isinstance(duration, int | float):
            keepalive.hold_for(key, float(duration), seat.session)
        elif spec.starts_goal and isinstance(body.get("goal_id"), str):
            keepalive.hold_goal(key, body["goal_id"], seat.session)

    # -- reads ----------------------------------------------------------------------------

    async def _read(self, seat: Seat, name: str, args: dict[str, Any]
                    ) -> types.CallToolResult:
        api = seat.api
        if name == "get_status":
            return result(await api.status(), "status")
        if name == "get_goals":
            return result(await api.goals(), "goals")
        if name == "get_my_pending_approvals":
            reply = await api.my_pending()
            return result(reply, f"{len(reply.body.get('pending') or ())} held for a human")
        pending_id = args.get("pending_id")
        if not isinstance(pending_id, str) or not pending_id:
            return failure("`pending_id` must be a non-empty string", "SCHEMA_VALIDATION_FAILED")
        if name == "get_pending_approval":
            reply = await api.pending(pending_id)
            return result(reply, str(reply.body.get("state", "")))
        timeout = args.get("timeout_s", 30.0)
        if not isinstance(timeout, int | float) or not 0 < timeout <= WAIT_MAX_S:
            return failure(f"`timeout_s` must be a number in (0, {WAIT_MAX_S:g}]",
                           "SCHEMA_VALIDATION_FAILED")
        return await self._wait(seat, pending_id, float(timeout))

    async def _wait(self, seat: Seat, pending_id: str, timeout_s: float
                    ) -> types.CallToolResult:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while True:
            reply = await seat.api.pending(pending_id)
            state = reply.body.get("state")
            if not reply.ok or state == "resolved":
                break
            if loop.time() >= deadline:
                return result(reply, f"still {state} after {timeout_s:g} s: wait again, or "
                                     "withdraw it over the bridge's API")
            await asyncio.sleep(min(POLL_S, max(0.0, deadline - loop.time())))
        if not reply.ok:
            return result(reply, "")
        return self._resolved(seat, reply)

    def _resolved(self, seat: Seat, reply: Reply) -> types.CallToolResult:
        """A decided command: an error unless it executed; what it started is held."""
        decision = reply.body.get("decision") or {}
        held = (reply.body.get("pending") or {}).get("original_command") or {}
        tool = self._tools.get(str(held.get("action")))
        if tool is not None and isinstance(held.get("params"), dict):
            self._started(seat, tool, held["params"], decision,
                          key=str(reply.body["pending_id"]))
        shown = {"http_status": reply.status, **reply.body,
                 **{k: decision[k] for k in ("outcome", "error_code", "reason") if k in decision}}
        outcome = str(decision.get("outcome", ""))
        return tool_result(shown, outcome, error=outcome != "executed")

    # -- resources ------------------------------------------------------------------------

    async def list_resources(self, ctx: ServerRequestContext[Any],
                             params: types.PaginatedRequestParams | None
                             ) -> types.ListResourcesResult:
        fixed = [types.Resource(uri=r.uri, name=r.name, description=r.description,
                                mime_type=JSON_TYPE) for r in RESOURCES.values()]
        return types.ListResourcesResult(resources=fixed + await self._cameras(ctx))

    async def _cameras(self, ctx: ServerRequestContext[Any]) -> list[types.Resource]:
        """A resource per configured camera (none while the bridge cannot say)."""
        try:
            reply = await self._seat_of(ctx).api.images()
        except BridgeUnavailable:
            return []
        listed = reply.body.get("images") if reply.ok else None
        return [types.Resource(uri=IMAGE_PREFIX + str(entry["name"]),
                               name=f"camera {entry['name']}",
                               description=IMAGE_DESCRIPTION.format(name=entry["name"]))
                for entry in listed or () if isinstance(entry, dict) and "name" in entry]

    async def list_resource_templates(self, ctx: ServerRequestContext[Any],
                                      params: types.PaginatedRequestParams | None
                                      ) -> types.ListResourceTemplatesResult:
        return types.ListResourceTemplatesResult(resource_templates=[types.ResourceTemplate(
            uri_template=IMAGE_TEMPLATE, name="camera",
            description=IMAGE_DESCRIPTION.format(name="{name}"))])

    async def read_resource(self, ctx: ServerRequestContext[Any],
                            params: types.ReadResourceRequestParams
                            ) -> types.ReadResourceResult:
        uri = str(params.uri)
        resource = RESOURCES.get(uri)
        if resource is None and not uri.startswith(IMAGE_PREFIX):
            raise MCPError(RESOURCE_NOT_FOUND, f"no resource {uri!r}: see resources/list")
        api = self._seat_of(ctx).api
        try:
            reply = (await resource.read(api) if resource is not None
                     else await api.image(uri.removeprefix(IMAGE_PREFIX)))
        except BridgeUnavailable as exc:
            raise MCPError(INTERNAL_ERROR, f"BRIDGE_UNAVAILABLE: {exc}") from None
        if isinstance(reply, Blob):
            return types.ReadResourceResult(contents=[types.BlobResourceContents(
                uri=uri, mime_type=reply.mime, blob=base64.b64encode(reply.data).decode())])
        if not reply.ok:
            raise refused(reply)
        assert resource is not None
        return types.ReadResourceResult(contents=[types.TextResourceContents(
            uri=uri, mime_type=JSON_TYPE, text=json.dumps(resource.shape(reply.body)))])


def refused(reply: Reply) -> MCPError:
    """A resource the bridge would not give, as an MCP error naming its RCAN refusal."""
    code = reply.body.get("error_code") or reply.body.get("outcome") or "REFUSED"
    code_number = RESOURCE_NOT_FOUND if reply.status == 404 else INVALID_REQUEST
    reason = reply.body.get("reason") or "no reason given"
    return MCPError(code_number, f"refused: {code}: {reason} (HTTP {reply.status})",
                    {"http_status": reply.status, **reply.body})


def build_server(tools: RobotTools) -> Server[Any]:
    server: Server[Any] = Server(
        "rcan-rtps", version=__version__, instructions=INSTRUCTIONS,
        on_list_tools=tools.list_tools, on_call_tool=tools.call_tool,
        get_tool_input_schema=tools.input_schema, on_list_resources=tools.list_resources,
        on_list_resource_templates=tools.list_resource_templates,
        on_read_resource=tools.read_resource)
    server.add_notification_handler("notifications/cancelled",
                                    types.CancelledNotificationParams, tools.cancelled)
    return server


async def serve_stdio(url: str, token: str, agent: Agent) -> int | None:
    """Serve MCP on stdin/stdout until the client closes them, or SIGINT, SIGTERM or SIGHUP;
    then stop what is still running that this server started (an agent gone must not leave
    the robot moving). The signal that ended it, if one did. A client that closed its end of
    stdout has gone, as one that closed stdin."""
    async with BridgeClient(url, token) as bridge:
        seat = Seat(bridge, agent, Keepalive(bridge))
        tools = RobotTools(lambda ctx: seat)
        server = build_server(tools)
        gc.freeze()  # the SDK's modules live as long as the process: no collection scans them
        replies = Replies()
        # A stop's warnings go to the bridge with it (its audit entry), as /mcp's do.
        door = StdioDoor(lambda call, warnings: stop_reply(
            replace(seat, api=bridge.warning(warnings)), call, warnings), replies.send,
            sdk_unreadable)
        # The SDK's own stdin reader cannot be cancelled: see stdio.py. (The SDK only
        # iterates what it is given.) Every line is screened for a stop first (stdio_door).
        stdin = cast("anyio.AsyncFile[str]", StdinLines(sys.stdin.fileno(), door.screen))
        with anyio.CancelScope() as serving, \
                stop_signals.taking_over(lambda sig: serving.cancel()) as signals:
            try:
                async with stdio_server(stdin=stdin) as (read, write), \
                        anyio.create_task_group() as group:
                    replies.open(write)
                    group.start_soon(seat.keepalive.run)
                    await server.run(read, write, server.create_initialization_options())
                    group.cancel_scope.cancel()
            except Exception as exc:
                if not client_gone(exc):
                    raise
        ended_by = signals.received
        if seat.keepalive.holding:
            why = "MCP client disconnected" if ended_by is None else \
                f"MCP server ended by {signal.Signals(ended_by).name}"
            await stop_left_running(seat, why)
    return ended_by


def sdk_unreadable(text: str) -> Unreadable | None:
    """Why the SDK's stdio transport would drop the line `text` unanswered (it reads each
    line with this adapter, and passes over one it cannot); None when it reads it."""
    try:
        types.jsonrpc_message_adapter.validate_json(text, by_name=False)
    except Exception as exc:  # pydantic's ValidationError, as the SDK's own reader catches
        if isinstance(exc, pydantic.ValidationError) and any(
                e["type"] == "json_invalid" for e in exc.errors(include_url=False)):
            return Unreadable(PARSE_ERROR, "not JSON")
        return Unreadable(INVALID_REQUEST, "not a JSON-RPC 2.0 request, notification or "
                          "response", _request_id(text))
    return None


def _request_id(text: str) -> int | str | None:
    """The `id` of a JSON object, when it is one JSON-RPC allows (the error answers it)."""
    try:
        message = msgspec.json.decode(text)
    except (msgspec.DecodeError, RecursionError):
        return None
    found = message.get("id") if isinstance(message, dict) else None
    return found if isinstance(found, (int, str)) and not isinstance(found, bool) else None


class Replies:
    """The SDK's stream of messages to stdout, once open: the stdio door's answers go out
    through it, so that stdout has one writer (two would tear lines)."""

    def __init__(self) -> None:
        self._stream: asyncio.Future[Any] = asyncio.get_running_loop().create_future()

    def open(self, stream: Any) -> None:
        self._stream.set_result(stream)

    async def send(self, reply: dict[str, Any]) -> None:
        """`reply` written out; logged instead when it cannot be (an id JSON-RPC does not
        allow, the client gone): the stop it answers has run all the same."""
        try:
            message = types.jsonrpc_message_adapter.validate_python(reply)
        except ValueError as exc:  # pydantic's ValidationError is one
            log.warning("a stop ran; its reply cannot be sent: %s", exc)
            return
        stream = await self._stream
        try:
            await stream.send(SessionMessage(message))
        except (anyio.ClosedResourceError, anyio.BrokenResourceError):
            log.warning("a stop ran; its client has gone before its reply")


def client_gone(exc: BaseException) -> bool:
    """Whether `exc` says only that the client closed its end of stdout (a broken pipe),
    wrapped in the task groups' exception groups as it comes out: a disconnect, not an error
    (it printed a traceback)."""
    inner = getattr(exc, "exceptions", None)  # an ExceptionGroup (a backport's on 3.10)
    if inner is not None:
        return bool(inner) and all(client_gone(e) for e in inner)
    return isinstance(exc, (BrokenPipeError, ConnectionResetError))


async def stop_left_running(seat: Seat, reason: str) -> None:
    """Stop the robot as the agent: its client went away while motion it started ran."""
    body = {"action": "stop", "params": {"reason": reason}, **ai_fields(seat.agent)}
    seat.keepalive.release_all()
    try:
        reply = await seat.api.command(body)
    except BridgeUnavailable as exc:
        log.warning("stop (%s): %s", reason, exc)
        return
    log.info("stop (%s, while motion it started ran): %s", reason, reply.body.get("outcome"))
