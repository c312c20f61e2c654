"""The stops of `rcan-rtps mcp`'s stdin: each line screened, before the SDK reads it, as the
bridge's `/mcp` screens a POST body (`stops.stop_rescue`, the one reading both doors share).

A line that says stop, stops, whatever else is wrong with it. The SDK would refuse a line it
cannot parse strictly (an unpaired surrogate, an integer of 5000 digits: no reply at all),
know no `ESTOP`, refuse arguments that are not an object, and run the last of a repeated
`"name"` (`"name": "estop", "name": "move"` ran the move). So:

- a stop as written (no warnings) is the SDK's, as any call;
- any other stop the door runs itself, as the tool runs it, and answers with its tool result,
  what was wrong with it among its `warnings`;
- a stop sent as a notification (no id) is run and not answered (JSON-RPC answers none);
- a JSON-RPC batch that holds a stop: its stops are run, each answered on its own line; its
  other requests refused (MCP has had no batches since 2025-06-18).

The door awaits each stop before the next line is read: nothing sent after a stop overtakes it.

A line with no stop that the SDK could not read (not JSON: -32700 Parse error; JSON but not a
JSON-RPC message: -32600 Invalid Request) the door answers as JSON-RPC 2.0 asks, with an id
null unless one could be read, and does not hand on: the SDK's stdio transport drops such a
line without a word, and the client waited for a reply that never came. The next line is
served as usual.

No SDK import here: `server.serve_stdio` gives the door its means of running and answering,
and of telling what the SDK cannot read (`Unreadable`: the SDK's own parse, so the two agree).
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from .stops import StopCall, not_served, stop_call, stop_rescue

log = logging.getLogger(__name__)
NOTIFIED = "$: a notification (no id): run, and not answered"
INTERNAL_ERROR = -32603  # JSON-RPC's codes
PARSE_ERROR = -32700
INVALID_REQUEST = -32600
ERROR_MESSAGES = {PARSE_ERROR: "Parse error", INVALID_REQUEST: "Invalid Request"}  # the spec's
STOP_FAILED = "the stop failed inside the MCP server (see its log)"
RunStop = Callable[[StopCall, tuple[str, ...]], Awaitable[dict[str, Any]]]
Answer = Callable[[dict[str, Any]], Awaitable[None]]


@dataclass(frozen=True)
class Unreadable:
    """Why the SDK would drop a line unanswered: JSON-RPC's error code (PARSE_ERROR or
    INVALID_REQUEST), what was wrong in a few words, and the line's id when one was read."""

    code: int
    reason: str
    request_id: int | str | None = None


ReadsLine = Callable[[str], Unreadable | None]  # None: the SDK reads the line


def _readable_to_all(text: str) -> None:
    return None


class StdioDoor:
    """`screen` each stdin line: `run_stop` runs a stop's call with its warnings and gives
    its JSON-RPC reply, which `answer` writes out (with the SDK's own replies); `unreadable`
    tells a line the SDK cannot read, which the door answers with its error."""

    def __init__(self, run_stop: RunStop, answer: Answer,
                 unreadable: ReadsLine = _readable_to_all) -> None:
        self._run_stop = run_stop
        self._answer = answer
        self._unreadable = unreadable

    async def screen(self, line: bytes) -> bytes | None:
        """`line` for the SDK to read; None when the door took it (the stops it ran, a line
        it answered with a parse or request error)."""
        rescue = stop_rescue(line)
        if rescue is None:
            return await self._readable(line)
        if rescue.batch is not None:
            await self._batch(rescue.warnings, rescue.batch)
            return None
        call = rescue.call
        assert call is not None  # a rescue is a batch's or one call's
        warnings = (*rescue.warnings, *call.warnings)
        if not warnings and not call.notification:
            return line  # as written: the SDK takes it as it would any call
        await self._stop(call, warnings)
        return None

    async def _readable(self, line: bytes) -> bytes | None:
        """`line` when the SDK can read it (or it is blank: no message, nothing to answer);
        else None, its error answered."""
        text = line.decode("utf-8", errors="replace")  # as the SDK will read it
        if not text.strip():
            return line
        problem = self._unreadable(text)
        if problem is None:
            return line
        log.info("stdin: a line the MCP server cannot read answered %d: %s", problem.code,
                 problem.reason)
        await self._answer({"jsonrpc": "2.0", "id": problem.request_id, "error": {
            "code": problem.code, "message": ERROR_MESSAGES[problem.code],
            "data": problem.reason}})
        return None

    async def _stop(self, call: StopCall, warnings: tuple[str, ...]) -> None:
        if call.notification:
            warnings = (*warnings, NOTIFIED)
        log.warning("a stop on stdin the MCP server would not run as sent: %s",
                    "; ".join(warnings))
        try:
            reply = await self._run_stop(call, warnings)
        except Exception:  # the log has it; the agent gets an error, never the traceback
            log.exception("a stop on stdin failed")
            reply = {"jsonrpc": "2.0", "id": call.request_id,
                     "error": {"code": INTERNAL_ERROR, "message": STOP_FAILED}}
        if not call.notification:
            await self._answer(reply)

    async def _batch(self, warnings: tuple[str, ...], batch: list[Any]) -> None:
        """A batch's stops run in order, its other requests refused; none answered as a
        batch (the SDK's writer sends one message a line)."""
        for member in batch:
            call = stop_call(member)
            if call is not None:
                await self._stop(call, (*warnings, *call.warnings))
                continue
            refused = not_served(member)
            if refused is not None:
                await self._answer(refused)
