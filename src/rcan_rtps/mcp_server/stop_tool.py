"""A stopping tool's call (`estop`, `stop`) run as its tool runs it, with no SDK import.

One path for every stop an MCP door takes: the tool's own call in a session (`server`), and
the stops a door runs itself because the SDK would not run them as sent (`/mcp`'s and the
stdio server's), is not installed or is not running. A stop stops whatever else is wrong.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

from rcan_rtps._transport_warnings import unrecorded

from .ports import BridgeUnavailable
from .results import Result, command_body, failure_json, outcome_note, reply_json, warned_json
from .seat import Seat
from .stops import StopCall

log = logging.getLogger(__name__)
R = TypeVar("R")
PAYLOAD_TOO_LARGE = 413  # the bridge's answer to a body over its `api.max_body_bytes`
TOO_LARGE_STOP = ("$.params.arguments: larger than the bridge takes (its max_body_bytes): the "
                  "stop was sent again without them (no confidence, reasoning or reason)")


async def run_stop(seat: Seat, action: str, args: dict[str, Any], client: str) -> Result:
    """The stop, as the bridge decided it; a stop whose arguments made it larger than the
    bridge takes is sent again without them (the first, refused, is in the audit log too)."""
    body = command_body(seat.agent, client, action, args)
    warnings: tuple[str, ...] = ()
    with seat.keepalive.calling(seat.session):
        reply = await seat.api.command(body)
        if reply.status == PAYLOAD_TOO_LARGE:
            bare = {k: v for k, v in body.items() if k not in ("confidence", "ai_reasoning")}
            reply = await seat.api.command({**bare, "params": {}})
            warnings = (TOO_LARGE_STOP,)
        if reply.ok and reply.body.get("outcome") == "executed":
            seat.keepalive.release_all()  # nothing of the principal's runs on: no heartbeat
    done = reply_json(reply, outcome_note(reply.body), thought_id=body["thought_id"])
    return warned_json(done, warnings) if warnings else done


async def guarded(name: str, call: Callable[[], Awaitable[R]],
                  failed: Callable[[str, str], R]) -> R:
    """`call`'s result; what it raises as a tool error (`failed(message, error_code)`), never
    a traceback to the agent: the SDK's tool calls and the doors' stops alike."""
    try:
        return await call()
    except BridgeUnavailable as exc:
        return failed(str(exc), "BRIDGE_UNAVAILABLE")
    except Exception:  # the log has it
        log.exception("tool %s failed", name)
        return failed(f"{name} failed inside the MCP server (see its log)", "INTERNAL_ERROR")


async def stop_reply(seat: Seat, call: StopCall, warnings: tuple[str, ...] = ()
                     ) -> dict[str, Any]:
    """The JSON-RPC reply to a stop's call a door runs itself; `warnings`, what the door found
    wrong, lead its result's own where the bridge's reply (which has those its audit entry
    recorded) does not carry them."""
    done = await guarded(call.name, lambda: run_stop(seat, call.name, call.arguments,
                                                     "unknown"), failure_json)
    answered = done["structuredContent"].get("warnings") or ()
    missing = unrecorded(warnings, answered if isinstance(answered, list) else ())
    if missing:
        done = warned_json(done, tuple(missing))
    # A complete result, as the SDK's own say (the 2026-07-28 protocol reads it; older
    # clients ignore it).
    return {"jsonrpc": "2.0", "id": call.request_id, "result": {**done, "resultType": "complete"}}
