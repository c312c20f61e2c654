"""A stop over `/mcp` stops whatever is wrong with its JSON (issue 23 item 1, the MCP door).

The SDK's own parser refused an `estop` tools/call holding an unpaired surrogate escape or an
integer of 5000 digits (HTTP 400, -32700) before the bridge saw it, and the robot was not
stopped; over the 2026-07-28 protocol the surrogate reached the tool, which failed with a
traceback. The SDK client cannot send such bodies: these are raw POSTs, in both protocols.
What was wrong comes back in the tool result's `warnings` and is in the audit entry.
"""

from __future__ import annotations

import json
import logging
from typing import Any

import pytest

from tests.api.apihelpers import TOKENS, Api

LEGACY, MODERN = "2025-06-18", "2026-07-28"
META = {"io.modelcontextprotocol/protocolVersion": MODERN,
        "io.modelcontextprotocol/clientInfo": {"name": "raw", "version": "1"},
        "io.modelcontextprotocol/clientCapabilities": {}}
SURROGATE = rb'"reason": "\ud800 person"'
HUGE = b'"confidence": ' + b"9" * 5000  # more digits than Python's int() reads
JUNK = [("an unpaired surrogate", SURROGATE, "an unpaired surrogate escape as U+FFFD"),
        ("an integer of 5000 digits", HUGE, "an integer of 5000 digits as null")]


@pytest.fixture
def log(caplog: pytest.LogCaptureFixture) -> pytest.LogCaptureFixture:
    caplog.set_level(logging.DEBUG)
    return caplog


def no_traceback(log: pytest.LogCaptureFixture) -> None:
    assert not [r for r in log.records if r.exc_info], [r.getMessage() for r in log.records]


def call(name: str, arguments: bytes, protocol: str, request_id: int = 2) -> bytes:
    """A tools/call with `arguments` (the inside of a JSON object, any bytes) as written."""
    meta = b', "_meta": ' + json.dumps(META).encode() if protocol == MODERN else b""
    return (b'{"jsonrpc": "2.0", "id": %d, "method": "tools/call", "params": {"name": "%s", '
            b'"arguments": {%s}%s}}' % (request_id, name.encode(), arguments, meta))


async def headers(api: Api, who: str, protocol: str, tool: str = "estop") -> dict[str, str]:
    """Headers for a tools/call: of a session opened as the SDK's client would (2025), or
    the sessionless protocol's own."""
    sent = {"Authorization": f"Bearer {TOKENS[who]}", "Content-Type": "application/json",
            "Accept": "application/json, text/event-stream", "RCAN-AI-Model": "m-1"}
    if protocol == MODERN:
        return {**sent, "Mcp-Protocol-Version": MODERN, "Mcp-Method": "tools/call",
                "Mcp-Name": tool}
    initialize = {"jsonrpc": "2.0", "id": 1, "method": "initialize", "params": {
        "protocolVersion": LEGACY, "capabilities": {}, "clientInfo": {"name": "raw",
                                                                      "version": "1"}}}
    async with api.http.post("/mcp", data=json.dumps(initialize), headers=sent) as resp:
        assert resp.status == 200, await resp.text()
        session = resp.headers["Mcp-Session-Id"]
    sent = {**sent, "Mcp-Session-Id": session, "Mcp-Protocol-Version": LEGACY}
    initialized = b'{"jsonrpc": "2.0", "method": "notifications/initialized"}'
    async with api.http.post("/mcp", data=initialized, headers=sent) as resp:
        assert resp.status == 202
    return sent


async def post(api: Api, raw: bytes, sent: dict[str, str]) -> tuple[int, Any]:
    async with api.http.post("/mcp", data=raw, headers=sent) as resp:
        assert resp.content_type == "application/json", (resp.status, await resp.text())
        return resp.status, json.loads(await resp.text())


def stopped(reply: Any, request_id: int = 2) -> dict[str, Any]:
    """The tool result of an executed stop (a valid JSON-RPC reply to `request_id`)."""
    assert (reply["jsonrpc"], reply["id"]) == ("2.0", request_id), reply
    result = reply["result"]
    assert result["isError"] is False, result
    data: dict[str, Any] = result["structuredContent"]
    assert data["outcome"] == "executed", data
    assert json.loads(result["content"][0]["text"].split("\n", 1)[1]) == data
    return data


@pytest.mark.parametrize("protocol", [LEGACY, MODERN])
@pytest.mark.parametrize(("what", "junk", "said"), JUNK, ids=[w for w, _, _ in JUNK])
async def test_a_malformed_estop_latches_for_a_guest(api: Api, log: pytest.LogCaptureFixture,
                                                     protocol: str, what: str, junk: bytes,
                                                     said: str) -> None:
    status, reply = await post(api, call("estop", junk, protocol),
                               await headers(api, "viewer", protocol))
    assert status == 200, reply
    data = stopped(reply)
    assert api.gov.latch.latched
    assert [a for a, _ in api.dispatcher.calls] == ["estop"]
    assert said in data["warnings"][0] and "not strict JSON" in data["warnings"][0], data
    entry = api.entry(data["audit_id"])
    assert (entry["event"], entry["principal"]) == ("ESTOP", "viewer")
    assert entry["warnings"] == data["warnings"]
    no_traceback(log)


@pytest.mark.parametrize("protocol", [LEGACY, MODERN])
async def test_a_malformed_stop_halts(api: Api, log: pytest.LogCaptureFixture,
                                      protocol: str) -> None:
    status, reply = await post(api, call("stop", SURROGATE + b", " + HUGE, protocol),
                               await headers(api, "planner", protocol, "stop"))
    assert status == 200, reply
    data = stopped(reply)
    assert [a for a, _ in api.dispatcher.calls] == ["stop"] and not api.gov.latch.latched
    assert ("an unpaired surrogate escape as U+FFFD" in data["warnings"][0]
            and "5000 digits" in data["warnings"][0]), data
    entry = api.entry(data["audit_id"])
    assert entry["params"] == {"reason": "\ufffd person"}
    assert entry["warnings"] == data["warnings"]
    no_traceback(log)


@pytest.mark.parametrize("junk", [SURROGATE, b'"reason": "x"'], ids=["malformed", "valid"])
async def test_the_stops_of_a_batch_run_and_nothing_else(api: Api, log: pytest.LogCaptureFixture,
                                                         junk: bytes) -> None:
    """The SDK refuses a JSON-RPC batch whole (-32602, even a valid one): its stop ran not."""
    move = call("move", b'"linear_x": 0.2, "duration_s": 5, "confidence": 0.9', LEGACY, 3)
    batch = b"[" + call("estop", junk, LEGACY) + b", " + move + b"]"
    status, replies = await post(api, batch, await headers(api, "planner", LEGACY))
    assert status == 200 and len(replies) == 2, replies
    data = stopped(replies[0])
    assert (replies[1]["id"], replies[1]["error"]["code"]) == (3, -32600), replies
    assert api.gov.latch.latched
    assert [a for a, _ in api.dispatcher.calls] == ["estop"]
    assert any("batch" in w for w in data["warnings"]), data
    assert api.entry(data["audit_id"])["warnings"] == data["warnings"]
    no_traceback(log)


@pytest.mark.parametrize("protocol", [LEGACY, MODERN])
@pytest.mark.parametrize(("what", "junk", "said"), JUNK, ids=[w for w, _, _ in JUNK])
async def test_any_other_malformed_call_moves_nothing(api: Api, log: pytest.LogCaptureFixture,
                                                      protocol: str, what: str, junk: bytes,
                                                      said: str) -> None:
    args = b'"linear_x": 0.2, "duration_s": 5, ' + junk.replace(b'"reason"', b'"reasoning"')
    if junk is HUGE:
        args = args.replace(b'"confidence"', b'"linear_y"')
    status, reply = await post(api, call("move", args, protocol),
                               await headers(api, "planner", protocol, "move"))
    if protocol == LEGACY or junk is HUGE:  # the SDK's parser refuses it, as before
        assert (status, reply["error"]["code"]) == (400, -32700), reply
    else:  # Python's json (the 2026 transport's) reads a surrogate: the bridge refuses it
        assert reply["result"]["isError"] is True, reply
        refused = reply["result"]["structuredContent"]
        assert (refused["http_status"], refused["error_code"]) == (
            400, "SCHEMA_VALIDATION_FAILED"), refused
        assert "unpaired surrogate" in refused["reason"]
    assert api.dispatcher.calls == [] and not api.gov.latch.latched
    no_traceback(log)


async def test_an_unauthenticated_malformed_estop_is_refused(api: Api) -> None:
    sent = await headers(api, "viewer", LEGACY)
    sent["Authorization"] = "Bearer not-a-token-0123456789abcdef"
    status, body = await post(api, call("estop", SURROGATE, LEGACY), sent)
    assert (status, body["error_code"]) == (401, "UNAUTHENTICATED"), body
    assert not api.gov.latch.latched and api.dispatcher.calls == []


# -- a stop the SDK would refuse for what is around it: its session, its arguments, its name --

def tool_call(name: str, arguments: bytes, protocol: str, request_id: int | None = 2) -> bytes:
    """A tools/call of `name` (as written) with `arguments` (any JSON, as written); without
    `request_id`, a notification."""
    meta = b', "_meta": ' + json.dumps(META).encode() if protocol == MODERN else b""
    head = b'{"jsonrpc": "2.0", ' + (b'"id": %d, ' % request_id if request_id else b"")
    return head + (b'"method": "tools/call", "params": {"name": %s, "arguments": %s%s}}'
                   % (json.dumps(name).encode(), arguments, meta))


def warned(data: dict[str, Any], *said: str) -> str:
    """The stop's warning that says all of `said` (in any case)."""
    found = [w for w in data.get("warnings") or ()
             if all(s.lower() in w.lower() for s in said)]
    assert found, data
    return found[0]


SESSIONS = ["missing", "unknown", "another principal's"]


@pytest.mark.parametrize("session", SESSIONS)
@pytest.mark.parametrize("tool", ["estop", "stop"])
async def test_a_stop_without_a_valid_session_stops(api: Api, log: pytest.LogCaptureFixture,
                                                    session: str, tool: str) -> None:
    """The SDK refused it (400 without a session id, 404 for one it does not know or that is
    another credential's) and the robot was not stopped."""
    who = "viewer" if tool == "estop" else "planner"  # a guest may e-stop, not halt
    sent = await headers(api, who, LEGACY, tool)
    if session == "missing":
        del sent["Mcp-Session-Id"]
    elif session == "unknown":
        sent["Mcp-Session-Id"] = "0123456789abcdef0123456789abcdef"
    else:
        sent["Mcp-Session-Id"] = (await headers(api, "ops", LEGACY))["Mcp-Session-Id"]
    status, reply = await post(api, tool_call(tool, b'{"reason": "r"}', LEGACY), sent)
    assert status == 200, reply
    data = stopped(reply)
    assert [a for a, _ in api.dispatcher.calls] == [tool]
    assert api.gov.latch.latched == (tool == "estop")
    warning = warned(data, "session")
    assert ("400" if session == "missing" else "404") in warning, warning
    entry = api.entry(data["audit_id"])
    assert (entry["principal"], entry["params"]) == (who, {"reason": "r"})
    assert entry["warnings"] == data["warnings"]
    # Anything else is answered as the SDK answers it: refused, nothing moves.
    move = tool_call("move", b'{"linear_x": 0.1, "duration_s": 1, "confidence": 0.9}', LEGACY)
    status, refused = await post(api, move, sent)
    assert (status, refused["id"], refused["error"]["code"]) == (
        400 if session == "missing" else 404, None, -32600), refused
    assert [a for a, _ in api.dispatcher.calls] == [tool]
    no_traceback(log)


@pytest.mark.parametrize("protocol", [LEGACY, MODERN])
@pytest.mark.parametrize("arguments", [b'"junk"', b"[1, 2]", b"5"], ids=["str", "list", "int"])
async def test_an_estop_whose_arguments_are_no_object_stops(
        api: Api, log: pytest.LogCaptureFixture, protocol: str, arguments: bytes) -> None:
    """The SDK answered -32602 and the robot was not stopped."""
    status, reply = await post(api, tool_call("estop", arguments, protocol),
                               await headers(api, "viewer", protocol))
    assert status == 200, reply
    data = stopped(reply)
    assert api.gov.latch.latched and [a for a, _ in api.dispatcher.calls] == ["estop"]
    warned(data, "arguments", "not an object", "ignored")
    assert api.entry(data["audit_id"])["warnings"] == data["warnings"]
    no_traceback(log)


@pytest.mark.parametrize("protocol", [LEGACY, MODERN])
@pytest.mark.parametrize(("name", "tool"), [("ESTOP", "estop"), (" estop ", "estop"),
                                            ("Stop", "stop"), ("STOP\t", "stop")])
async def test_a_stop_spelt_otherwise_stops(api: Api, log: pytest.LogCaptureFixture,
                                            protocol: str, name: str, tool: str) -> None:
    """Stops forgive case and blanks over REST; at /mcp the name was UNKNOWN_TOOL. Other
    tools' names stay exact."""
    move = tool_call("MOVE", b'{"linear_x": 0.1, "duration_s": 1, "confidence": 0.9}',
                     protocol, 3)
    status, reply = await post(api, move, await headers(api, "planner", protocol, "MOVE"))
    assert reply["result"]["isError"] is True, reply
    assert reply["result"]["structuredContent"]["error_code"] == "UNKNOWN_TOOL"
    assert api.dispatcher.calls == []
    status, reply = await post(api, tool_call(name, b"{}", protocol),
                               await headers(api, "planner", protocol, name))
    assert status == 200, reply
    data = stopped(reply)
    assert [a for a, _ in api.dispatcher.calls] == [tool]
    warned(data, repr(name), repr(tool))
    assert api.entry(data["audit_id"])["warnings"] == data["warnings"]
    no_traceback(log)


@pytest.mark.parametrize("protocol", [LEGACY, MODERN])
async def test_an_estop_notification_stops(api: Api, log: pytest.LogCaptureFixture,
                                           protocol: str) -> None:
    """A tools/call without an id: JSON-RPC allows no reply, the stop runs all the same."""
    sent = await headers(api, "viewer", protocol)
    async with api.http.post("/mcp", data=tool_call("estop", b"{}", protocol, None),
                             headers=sent) as resp:
        assert resp.status == 202, await resp.text()
        assert await resp.read() == b""
    assert api.gov.latch.latched and [a for a, _ in api.dispatcher.calls] == ["estop"]
    [entry] = [e for e in api.entries if e["event"] == "ESTOP"]
    assert any("notification" in w for w in entry["warnings"]), entry
    no_traceback(log)


@pytest.mark.parametrize("mode", ["auto", "legacy"])
async def test_the_sdk_clients_stop_spelt_otherwise_stops(api: Api, log: pytest.LogCaptureFixture,
                                                          mode: str) -> None:
    """The official client, over both protocols (a session over 2025-06-18): `Stop` halts,
    with its warning; the same client's `stop` is the SDK's to run, as before (no warning)."""
    from tests.api.test_mcp_http import agent, data

    async with agent(api, mode=mode) as client:
        plain = data(await client.call_tool("stop", {"reason": "a"}))
        respelt = data(await client.call_tool("Stop", {"reason": "b"}))
    assert (plain["outcome"], respelt["outcome"]) == ("executed", "executed")
    assert "warnings" not in plain, plain
    assert respelt["warnings"] == ["$.params.name: 'Stop' is the tool 'stop' (spelt otherwise)"]
    assert [a for a, _ in api.dispatcher.calls] == ["stop", "stop"]
    assert api.entry(respelt["audit_id"])["warnings"] == respelt["warnings"]
    assert api.entry(respelt["audit_id"])["ai"]["client"] == "test-agent/1.2"  # the SDK ran it
    no_traceback(log)
