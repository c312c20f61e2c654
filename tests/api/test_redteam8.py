"""Red team 8: what an authenticated principal controls in a body, and what it can do to others.

Each test here failed on main (43f1bcd) before its fix; see each test's docstring.
"""

from __future__ import annotations

import gzip
import json
import logging
import zlib
from typing import Any

import aiohttp
import pytest

from rcan_rtps.api import ApiServer
from rcan_rtps.governance.decision_log import log_entry
from tests.api.apihelpers import Api, auth, next_frame
from tests.api.test_mcp_stop_intake import LEGACY, META, MODERN, headers, post, stopped, warned
from tests.api.test_rcan3_messages import sdk_command

SMALL_WINDOW = "security: {msg_id_cache_size: 100}"


async def test_a_guest_cannot_fill_the_replay_window_for_everyone(tmp_path: Any) -> None:
    """A GUEST (or any principal, rate-limited or not) sending fresh RCAN 3.x messages it may
    not even run filled the one §8.3 id window: from then on every principal's fresh message
    was refused 429 `replay_window_full` until the GUEST's ids went stale — a denial of
    service of every RCAN 3.x client by the least trusted one. A full window is the flooder's
    problem only."""
    api = await Api(tmp_path, bridge_extra=SMALL_WINDOW).start()
    try:
        for _ in range(100):
            status, body = await api.command("viewer", sdk_command(api, "move",
                                                                   {"linear_x": 0.1}))
            assert status == 403, body  # a GUEST may not move: refused, but its id was kept
        status, body = await api.command("viewer", sdk_command(api, "move", {"linear_x": 0.1}))
        assert (status, body.get("reason")) == (429, "replay_window_full"), body
        msg = sdk_command(api, "move", {"linear_x": 0.2, "duration_s": 1.0})
        status, body = await api.command("planner", msg)
        assert (status, body["outcome"]) == (200, "executed"), body
        status, body = await api.command("planner", msg)  # and replays are still caught
        assert (status, body["error_code"]) == (409, "REPLAY_DETECTED"), body
    finally:
        await api.close()


# -- /mcp: a tools/call whose JSON repeats a key, one of whose values says stop --

MOVE_ARGS = '"arguments": {"linear_x": 0.2, "duration_s": 1.0, "confidence": 0.9}'
REPEATS = {
    "name: estop, then move": '{"name": "estop", "name": "move", %s%s}',
    "name: move, then estop": '{"name": "move", "name": "estop", %s%s}',
    "params: estop, then move": '{"name": "estop"}, "params": {"name": "move", %s%s}',
}


@pytest.mark.parametrize("header", ["move", "estop"])
@pytest.mark.parametrize("protocol", [LEGACY, MODERN])
@pytest.mark.parametrize("repeat", list(REPEATS))
async def test_an_mcp_call_that_says_estop_twice_over_is_an_estop(
        api: Api, protocol: str, repeat: str, header: str) -> None:
    """REST runs a body in which any `action` says estop as the e-stop, duplicated keys and
    all (`{"action":"estop","action":"move"}` used to run the move). /mcp read such a body as
    the SDK does, the last key winning: `{"name": "estop", "name": "move", ...}` drove the
    robot (as the planner's move, the latch unset), and over 2026-07-28 an `Mcp-Name: estop`
    header with it was refused -32020 — nothing stopped at all."""
    meta = (', "_meta": ' + json.dumps(META)) if protocol == MODERN else ""
    params = REPEATS[repeat] % (MOVE_ARGS, meta)
    raw = b'{"jsonrpc": "2.0", "id": 2, "method": "tools/call", "params": ' + params.encode() + b"}"
    status, reply = await post(api, raw, await headers(api, "planner", protocol, header))
    assert status == 200, reply
    data = stopped(reply)
    assert api.gov.latch.latched
    assert [a for a, _ in api.dispatcher.calls] == ["estop"]
    warned(data, "duplicate key")
    assert api.entry(data["audit_id"])["warnings"] == data["warnings"]


# -- the server's log: a key the client chose reaches a decision's log line --

FORGED = "a\n2026-11-27 07:00:00 WARNING rcan_rtps.decisions ESTOP_CLEARED by ops \u202e"


async def test_a_key_the_client_chose_cannot_forge_a_log_line(
        api: Api, caplog: pytest.LogCaptureFixture) -> None:
    """A repeated key is refused naming its path (`$.params.<key>`), and that path is the
    entry's deny_reason, which the decision log line carries: a key holding a newline wrote a
    forged line ('ESTOP_CLEARED by ops') into the server's log, and a bidi override reversed
    the rest of the line. The audit entry keeps the path as it was (JSON escapes it)."""
    caplog.set_level(logging.INFO, logger="rcan_rtps.decisions")
    api.gov.audit.audited.subscribe(log_entry)
    key = json.dumps(FORGED)
    raw = f'{{"action": "move", "params": {{{key}: 1, {key}: 2}}}}'.encode()
    status, body = await api.command("planner", raw=raw)
    assert (status, body["path"]) == (400, "$.params." + FORGED), body
    await api.gov.audit.close()  # runs the listeners still scheduled
    lines = [r.getMessage() for r in caplog.records if r.name == "rcan_rtps.decisions"]
    assert len(lines) == 1, lines
    assert lines[0].isprintable(), lines[0]
    entry = api.entry(body["audit_id"])
    assert entry["deny_reason"] == "SCHEMA_VALIDATION_FAILED:$.params." + FORGED


# -- a stop nested too deeply for the parsers --

DEEP = b"[" * 5000 + b"]" * 5000


async def test_an_estop_with_a_deeply_nested_field_stops(api: Api) -> None:
    """A JSON object that says estop at its top, beside a field nested 5000 levels deep (11 kB,
    far below the size limit), was refused 400 'JSON nested too deeply' and nothing stopped:
    both parsers (msgspec and Python's json, the lenient reader) give up past ~1000 levels."""
    raw = b'{"action": "estop", "params": {"reason": "deep"}, "x": ' + DEEP + b"}"
    status, body = await api.command("viewer", raw=raw)
    assert (status, body["outcome"]) == (200, "executed"), body
    assert api.gov.latch.latched and [a for a, _ in api.dispatcher.calls] == ["estop"]
    assert any("nested" in w for w in body["warnings"]), body
    assert api.entry(body["audit_id"])["params"] == {"reason": "deep"}


async def test_a_websocket_estop_with_a_deeply_nested_field_stops(api: Api) -> None:
    raw = b'{"action": "estop", "params": {"reason": "deep"}, "x": ' + DEEP + b"}"
    async with api.http.ws_connect("/api/ws", headers=auth("viewer")) as ws:
        await ws.send_bytes(raw)
        frame = await next_frame(ws, "outcome")
    assert (frame["http_status"], frame["body"]["outcome"]) == (200, "executed"), frame
    assert api.gov.latch.latched and [a for a, _ in api.dispatcher.calls] == ["estop"]


async def test_a_move_with_a_deeply_nested_field_is_still_refused(api: Api) -> None:
    raw = b'{"action": "move", "params": {"linear_x": 0.1}, "x": ' + DEEP + b"}"
    status, body = await api.command("planner", raw=raw)
    assert (status, body["error_code"]) == (400, "SCHEMA_VALIDATION_FAILED"), body
    assert api.dispatcher.calls == []


@pytest.mark.parametrize("protocol", [LEGACY, MODERN])
async def test_an_mcp_estop_with_a_deeply_nested_argument_stops(api: Api, protocol: str) -> None:
    """The SDK's parser refused it (-32700) and the bridge's lenient reader gave up too."""
    meta = (b', "_meta": ' + json.dumps(META).encode()) if protocol == MODERN else b""
    raw = (b'{"jsonrpc": "2.0", "id": 2, "method": "tools/call", "params": {"name": "estop", '
           b'"arguments": {"reason": "deep", "x": ' + DEEP + b"}" + meta + b"}}")
    status, reply = await post(api, raw, await headers(api, "viewer", protocol))
    assert status == 200, reply
    data = stopped(reply)
    assert api.gov.latch.latched and [a for a, _ in api.dispatcher.calls] == ["estop"]
    warned(data, "nested")


# -- Content-Encoding: what aiohttp decompressed by itself, and how it failed --

def no_traceback(log: pytest.LogCaptureFixture) -> None:
    assert not [r for r in log.records if r.exc_info], [r.getMessage() for r in log.records]


async def _post(api: Api, who: str | None, data: bytes, encoding: str) -> tuple[int, Any]:
    sent = {"Content-Type": "application/json", "Content-Encoding": encoding,
            **(auth(who) if who else {})}
    async with api.http.post("/api/command", data=data, headers=sent) as resp:
        assert resp.content_type == "application/json", (resp.status, await resp.text())
        return resp.status, json.loads(await resp.text())


MOVE = b'{"action": "move", "params": {"linear_x": 0.1, "duration_s": 1}}'


@pytest.mark.parametrize(("encoding", "data"), [
    ("gzip", MOVE), ("deflate", b"\x00\x01 not deflate"), ("br", b"not brotli"),
    ("zstd", b"not zstd"), ("compress", MOVE)])
@pytest.mark.parametrize("who", ["planner", None], ids=["authenticated", "unauthenticated"])
async def test_a_body_that_is_not_what_its_encoding_says_is_a_clear_error(
        api: Api, caplog: pytest.LogCaptureFixture, encoding: str, data: bytes,
        who: str | None) -> None:
    """aiohttp decompressed request bodies itself: a body that was not what its
    Content-Encoding said was answered 503 internal_error with a traceback in the log
    (authenticated), or 401 followed by aiohttp's 'Unhandled exception' traceback
    (unauthenticated: anyone could fill the log with them); `br` without Brotli installed was
    a text/plain 400 with a traceback. Now: 400 (or 415 for a coding the API does not take),
    JSON, no traceback, nothing moved."""
    caplog.set_level(logging.DEBUG)
    status, body = await _post(api, who, data, encoding)
    if who is None:
        assert (status, body["error_code"]) == (401, "UNAUTHENTICATED"), body
    else:
        assert status in (400, 415) and body["outcome"] == "denied", (status, body)
        assert "encoding" in body["reason"].lower(), body
    assert api.dispatcher.calls == []
    no_traceback(caplog)


async def test_an_estop_whose_encoding_lies_stops(api: Api,
                                                  caplog: pytest.LogCaptureFixture) -> None:
    """Plain JSON that says estop, sent with `Content-Encoding: gzip`: 503 and not latched."""
    caplog.set_level(logging.DEBUG)
    status, body = await _post(api, "viewer", b'{"action": "estop"}', "gzip")
    assert (status, body["outcome"]) == (200, "executed"), body
    assert api.gov.latch.latched
    assert any("gzip" in w for w in body["warnings"]), body
    no_traceback(caplog)


async def test_compressed_bodies_still_work_within_the_limit(api: Api) -> None:
    status, body = await _post(api, "planner", gzip.compress(MOVE), "gzip")
    assert (status, body["outcome"]) == (200, "executed"), body
    status, body = await _post(api, "planner", zlib.compress(MOVE), "deflate")
    assert (status, body["outcome"]) == (200, "executed"), body
    bomb = gzip.compress(b'{"action": "move", "pad": "' + b"x" * 10_000_000 + b'"}')
    status, body = await _post(api, "planner", bomb, "gzip")
    assert (status, body["error_code"]) == (413, "PAYLOAD_TOO_LARGE"), body


@pytest.mark.parametrize("protocol", [LEGACY, MODERN])
async def test_an_mcp_estop_whose_encoding_lies_stops(
        api: Api, caplog: pytest.LogCaptureFixture, protocol: str) -> None:
    caplog.set_level(logging.DEBUG)
    meta = (', "_meta": ' + json.dumps(META)) if protocol == MODERN else ""
    raw = ('{"jsonrpc": "2.0", "id": 2, "method": "tools/call", "params": {"name": "estop", '
           '"arguments": {}' + meta + "}}").encode()
    sent = {**await headers(api, "viewer", protocol), "Content-Encoding": "gzip"}
    status, reply = await post(api, raw, sent)
    assert status == 200, reply
    data = stopped(reply)
    assert api.gov.latch.latched
    warned(data, "gzip")
    no_traceback(caplog)


@pytest.mark.parametrize("who", ["planner", None], ids=["authenticated", "unauthenticated"])
async def test_the_real_server_answers_a_misencoded_body_quietly(
        tmp_path: Any, caplog: pytest.LogCaptureFixture, who: str | None) -> None:
    """The same through `ApiServer`, whose handlers `run` makes with their own arguments (not
    the app's): a gzip header on a plain body."""
    caplog.set_level(logging.DEBUG)
    api = Api(tmp_path)
    app = await api.build()
    try:
        async with ApiServer(app, host="127.0.0.1", port=0) as server, \
                aiohttp.ClientSession() as session:
            sent = {"Content-Type": "application/json", "Content-Encoding": "gzip",
                    **(auth(who) if who else {})}
            async with session.post(server.url + "/api/command", data=MOVE,
                                    headers=sent) as resp:
                status, body = resp.status, await resp.json()
    finally:
        await api.close()
    assert (status, body["outcome"]) == ((400 if who else 401), "denied"), body
    assert api.dispatcher.calls == []
    no_traceback(caplog)


# -- a UTF-8 byte order mark (what Windows PowerShell 5's UTF8 encoding writes first) --

async def test_an_estop_after_a_byte_order_mark_stops(api: Api) -> None:
    """RFC 8259 lets a parser ignore a BOM; both of ours refuse one, so an e-stop written by
    a tool that puts one first was refused 400 and nothing stopped. A move stays refused."""
    status, body = await api.command("viewer", raw=b'\xef\xbb\xbf{"action": "estop"}')
    assert (status, body["outcome"]) == (200, "executed"), body
    assert api.gov.latch.latched
    assert any("byte order mark" in w for w in body["warnings"]), body
    status, body = await api.command("planner", raw=b"\xef\xbb\xbf" + MOVE)
    assert (status, body["error_code"]) == (400, "SCHEMA_VALIDATION_FAILED"), body


# -- §16.5 thoughts: one principal writing into another's --

async def test_a_guest_cannot_rewrite_another_principals_thought(api: Api) -> None:
    ai = {"ai_provider": "acme", "confidence": 0.9, "thought_id": "th-shared"}
    own = {"action": "move", "params": {"linear_x": 0.1, "duration_s": 1},
           "ai_model": "planner-7b", "ai_reasoning": "the user asked for the door", **ai}
    assert (await api.command("planner", own))[0] == 200
    forged = {**own, "ai_model": "planner-7b-v2",
              "ai_reasoning": "ignore the fence, the owner approved it"}
    status, _ = await api.command("viewer", forged)
    assert status == 403  # a GUEST may not move: refused, yet remembered in the thought
    status, thought = await api.call("GET", "/api/thoughts/th-shared", "ops")
    assert status == 200, thought
    assert (thought["model"], thought["reasoning"]) == (
        "planner-7b", "the user asked for the door"), thought
    assert (thought["principal"], thought["also_named_by"]) == ("planner", ["viewer"]), thought
    assert [c["principal"] for c in thought["commands"]] == ["planner"]
    # The other sender's commands naming the id: a record of their own, asked for by name.
    status, theirs = await api.call("GET", "/api/thoughts/th-shared?principal=viewer", "ops")
    assert status == 200, theirs
    assert (theirs["principal"], theirs["model"], theirs["action"]["outcome"]) == (
        "viewer", "planner-7b-v2", "denied"), theirs
    assert theirs["also_named_by"] == ["planner"], theirs
    status, _ = await api.call("GET", "/api/thoughts/th-shared?principal=nobody", "ops")
    assert status == 404
