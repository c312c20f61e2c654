"""REST handlers of what a bridge serves all the time: command (stops included), status,
heartbeat and goals. The rest (HiTL, audit reads, images, thoughts, skills) is in
`_rare_routes`, loaded by its first request."""

from __future__ import annotations

import functools

from aiohttp import web

from rcan_rtps import _transport_warnings as transport
from rcan_rtps.governance import Governor, Principal
from rcan_rtps.governance.clock import SystemClock, now_ms
from rcan_rtps.governance.governor import ClientCancel

from ._bodies import (
    ApiError,
    CommandCancelAck,
    GoalList,
    HeartbeatAck,
    error_body,
    json_response,
)
from ._commands import CommandBody, read_command, read_limited, run_command, too_large
from ._errors import BodyEncoding
from ._intake import intake
from ._keys import (
    CHECKS,
    DEADLINES,
    GOVERNOR,
    INVOCATIONS,
    OBSERVE,
    PRINCIPAL,
    ROBOT,
    SETTINGS,
    STATUS,
)
from .ports import GoalView, RobotView

_WALL = SystemClock()


async def read_body(request: web.Request) -> bytes | None:
    """The request's body, or None when it is over the configured size (a command's is read
    by `read_command`: a stop may be larger)."""
    settings = request.app[SETTINGS]
    return await read_limited(request, settings.max_body_bytes, settings.body_timeout_s)


async def post_command(request: web.Request) -> web.Response:
    # Each request is its own task and no read shares an executor with the audit writer
    # (`_reads`), so nothing queues a REST stop or e-stop behind anything else.
    governor, principal = request.app[GOVERNOR], request[PRINCIPAL]
    # What the client's transport found wrong with a stop (`rcan-rtps mcp`'s door): a stop's
    # audit entry records it, bounded and marked as the client's; any other command drops it.
    warnings = transport.recorded(request.headers.getall(transport.HEADER, ()))
    settings = request.app[SETTINGS]
    try:
        read = await read_command(request, settings.max_body_bytes, settings.body_timeout_s)
    except BodyEncoding as exc:
        # A stop always stops: bytes that say stop, whatever their header says they are.
        if not intake(exc.raw, len(exc.raw)).stopping:
            raise
        read, warnings = CommandBody(exc.raw), (*warnings, f"$: {exc.reason}: read as sent")
    if read is None:
        status, body = await too_large(governor, principal)
        response = json_response(body, status)
        response.force_close()  # large by its shape: the rest is not worth reading
        return response
    # An INVOKE is answered when its skill is done: a client that hangs up before that is
    # gone, and its skill's motion is stopped (aiohttp runs the handler on, telling no one).
    deadlines = request.app.get(DEADLINES)
    hung_up = None if deadlines is None else functools.partial(deadlines.hung_up, request)
    status, body = await run_command(governor, principal, read.data, request.app[OBSERVE],
                                     request.app[CHECKS], request.app[INVOCATIONS],
                                     (*warnings, *read.warnings), hung_up,
                                     limit=settings.max_body_bytes, skimmed=read.skimmed)
    return json_response(body, status)


async def post_command_cancel(request: web.Request) -> web.Response:
    """A client cancelled a motion command of its principal's before its answer (`rcan-rtps
    mcp`, for its MCP client): that principal's motion stops, nobody else's. No body."""
    governor, principal = request.app[GOVERNOR], request[PRINCIPAL]
    return json_response(await cancel_acked(governor.motion_cancelled(principal), principal))


async def cancel_acked(cancelled: ClientCancel, principal: Principal) -> CommandCancelAck:
    """`Governor.motion_cancelled`'s outcome (called by the caller, in its own step): what it
    stopped, and what held for a human it withdrew (that is not `stopped`: it never moved)."""
    stopped = await cancelled.stopping
    return CommandCancelAck(principal=principal.name, stopped=stopped is not None,
                            decision=None if stopped is None else stopped.body(),
                            withdrawn=list(cancelled.withdrawn))


async def get_status(request: web.Request) -> web.Response:
    return json_response(request.app[STATUS].snapshot())


def heartbeat(governor: Governor, principal: Principal) -> HeartbeatAck:
    governor.heartbeat(principal)
    return HeartbeatAck(principal=principal.name, timestamp_ms=now_ms(_WALL))


async def post_heartbeat(request: web.Request) -> web.Response:
    return json_response(heartbeat(request.app[GOVERNOR], request[PRINCIPAL]))


async def get_goals(request: web.Request) -> web.Response:
    return json_response(GoalList(goals=request.app[ROBOT].goals()))


def goal_view(robot: RobotView, goal_id: str) -> tuple[int, GoalView | ApiError]:
    goal = robot.goal(goal_id)
    if goal is None:
        return 404, error_body("NOT_FOUND", reason="goal_not_found")
    return 200, goal


async def get_goal(request: web.Request) -> web.Response:
    status, body = goal_view(request.app[ROBOT], request.match_info["goal_id"])
    return json_response(body, status)
