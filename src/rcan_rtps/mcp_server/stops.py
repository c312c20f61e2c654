"""What in an MCP JSON-RPC message says stop, and what the SDK would refuse in it: one reading
for both doors, the bridge's `/mcp` (`rcan_rtps.api._mcp.McpEndpoint`, a POST body) and
`rcan-rtps mcp` (`stdio_door.StdioDoor`, a stdin line). No SDK import, nothing of the API:
the stdio process loads only this and what its tools already need.

A request that says stop, stops, whatever else is wrong with it. The SDK refuses a JSON-RPC
body it cannot parse strictly (an unpaired surrogate escape, an integer of more digits than
Python reads), a batch, a `tools/call` whose `arguments` are not an object, and knows tools by
their exact names: such a stop is found here, with what was wrong as its warnings. A tool name
says stop as an RCAN `action` does over REST (`rcan._salvage.stop_intent`: case and blanks
forgiven); any other tool's name stays exact. A body that repeats a key says stop when any
of the values says so (`{"name": "estop", "name": "move"}`), as over REST: the SDK's parser
would take the last and run the move.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import msgspec

from rcan_rtps.rcan._salvage import (
    Pairs,
    count_keys,
    first_duplicate,
    read_leniently,
    stop_intent,
)

INVALID_REQUEST = -32600  # JSON-RPC's code (the SDK's `mcp_types.jsonrpc.INVALID_REQUEST`)
NOT_SERVED = ("a JSON-RPC batch is not served (MCP has had none since 2025-06-18): only the "
              "stops in it were run")


class StopCall(NamedTuple):
    """A JSON-RPC `tools/call` that says stop: the stopping tool's own name, the arguments it
    is run with, its request id (None: a notification) and what the SDK would not take as
    written (each a warning)."""

    name: str
    arguments: dict[str, Any]
    request_id: Any
    notification: bool
    warnings: tuple[str, ...]

    def as_message(self, message: dict[str, Any]) -> dict[str, Any]:
        """`message` (this call's) as the SDK takes it: the tool's own name, object arguments."""
        params = {**message["params"], "name": self.name, "arguments": self.arguments}
        return {**message, "params": params}


def stop_call(message: Any) -> StopCall | None:
    """`message` as a stop's tool call; None when it is none."""
    if not isinstance(message, dict) or message.get("method") != "tools/call":
        return None
    params = message.get("params")
    name = params.get("name") if isinstance(params, dict) else None
    tool = stop_intent([("action", name)])
    if tool is None or not isinstance(params, dict):
        return None
    warnings: list[str] = []
    if name != tool:
        warnings.append(f"$.params.name: {name!r} is the tool {tool!r} (spelt otherwise)")
    arguments = params.get("arguments")
    if arguments is None:
        arguments = {}
    elif not isinstance(arguments, dict):
        warnings.append(f"$.params.arguments: not an object ({type(arguments).__name__}): "
                        "ignored")
        arguments = {}
    return StopCall(tool, arguments, message.get("id"), "id" not in message, tuple(warnings))


def not_served(member: Any) -> dict[str, Any] | None:
    """The reply to a batch's member that is no stop: refused (the SDK refuses a batch whole,
    the doors serve only its stops); none to a notification."""
    if isinstance(member, dict) and "id" not in member:
        return None
    request_id = member.get("id") if isinstance(member, dict) else None
    return {"jsonrpc": "2.0", "id": request_id,
            "error": {"code": INVALID_REQUEST, "message": NOT_SERVED}}


class Rescue(NamedTuple):
    """A POST body that says stop: the body to hand the SDK (strict JSON), what was wrong with
    it as JSON-RPC (every stop's warnings), and either its one stop's call or a batch's
    members (whose stops the bridge runs: the SDK refuses a batch whole)."""

    body: bytes
    warnings: tuple[str, ...]
    call: StopCall | None = None
    batch: list[Any] | None = None


def stop_rescue(body: bytes) -> Rescue | None:
    """The stop in `body`; None when it holds none (the SDK answers it as it would: -32700
    for what it cannot parse)."""
    warnings: tuple[str, ...] = ()
    try:
        message = msgspec.json.decode(body)
    except (msgspec.DecodeError, ValueError, RecursionError):  # ValueError: not UTF-8
        read = read_leniently(body)
        if read is None:
            return None
        message = read.value
        warnings = (read.problem("$: the JSON-RPC body is not strict JSON"),)
    repeated = _repeated(body, message)
    if repeated is not None:
        message, said = repeated
        warnings = (*warnings, said)
    if isinstance(message, list):
        if not any(stop_call(member) for member in message):
            return None
        return Rescue(body, (*warnings, "$: a JSON-RPC batch: only its stops were run"),
                      batch=message)
    call = stop_call(message)
    if call is None:
        return None
    if not warnings and not call.warnings:  # as written: the SDK takes the very body
        return Rescue(body, (), call)
    return Rescue(msgspec.json.encode(call.as_message(message)), warnings, call)


def _repeated(body: bytes, message: Any) -> tuple[Any, str] | None:
    """For a body that repeats a key: the message as a stop reads it (a stop's call, should
    any of its values say stop) and the warning naming the first repeated key; else None.
    Every key is followed by a colon: a body with no more colons than keys repeats none."""
    if body.count(b":") == count_keys(message):
        return None
    read = read_leniently(body, pairs=True)
    if read is None:
        return None
    duplicate = first_duplicate(read.value)
    if duplicate is None:
        return None
    said = f"{duplicate.path}: duplicate key {duplicate.key!r}"
    if isinstance(read.value, list) and not isinstance(read.value, Pairs):  # a batch
        return [_as_stop(member) for member in read.value], said
    return _as_stop(read.value), said


def _as_stop(member: Any) -> Any:
    """A JSON-RPC request read with every occurrence of its keys (`Pairs`), as plain dicts:
    a `tools/call` among its methods whose `params` (any of them) name a stop (any of the
    names) becomes that call; anything else keeps the last of each key, as the SDK would."""
    if not isinstance(member, Pairs):
        return _plain(member)
    plain = _plain(member)
    if "tools/call" not in [v for k, v in member if k == "method"]:
        return plain
    for key, params in member:
        if key != "params" or not isinstance(params, Pairs):
            continue
        names = [v for k, v in params if k == "name" and isinstance(v, str)]
        tool = stop_intent(("action", name) for name in names)
        if tool is not None:
            name = next(n for n in names if stop_intent([("action", n)]) == tool)
            return {**plain, "method": "tools/call",
                    "params": {**_plain(params), "name": name}}
    return plain


def _plain(value: Any) -> Any:
    """`value` with every `Pairs` a dict (the last occurrence of a key wins)."""
    if isinstance(value, Pairs):
        return {k: _plain(v) for k, v in value}
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value

