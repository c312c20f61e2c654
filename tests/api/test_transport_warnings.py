"""`RCAN-Transport-Warnings` on POST /api/command (`rcan_rtps._transport_warnings`): what a
client's transport found wrong with a stop, in the stop's audit entry. Attacked here: a
header of the wrong type or too big, control characters, a non-stop carrying it, a GUEST
sending it. None keeps a stop from stopping; none writes unmarked or unbounded text into
the audit log. (The stdio door's use of it: tests/mcp/test_mcp_stdio_stops.py.)"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import pytest

from rcan_rtps._transport_warnings import (
    HEADER,
    MAX_CHARS,
    MAX_COUNT,
    MAX_HEADER_BYTES,
    bounded,
    header_value,
)
from tests.api.apihelpers import Api, auth

ESTOP = {"action": "estop"}
MOVE = {"action": "move", "params": {"linear_x": 0.1}}
NOT_READ = f"{HEADER}: not a JSON array of strings: ignored"


async def _post(api: Api, who: str, body: Any, header: str | bytes
                ) -> tuple[int, dict[str, Any]]:
    if isinstance(header, bytes):  # aiohttp's client sends only text: write the request
        return await _post_raw(api, who, body, header)
    headers = {**auth(who), HEADER: header, "Content-Type": "application/json"}
    async with api.http.post("/api/command", data=json.dumps(body), headers=headers) as resp:
        return resp.status, await resp.json()


async def _post_raw(api: Api, who: str, body: Any, header: bytes
                    ) -> tuple[int, dict[str, Any]]:
    """One HTTP/1.1 request with a header of bytes that are not UTF-8, and its reply."""
    url = api.http.make_url("/")
    reader, writer = await asyncio.open_connection(url.host, url.port)
    data = json.dumps(body).encode()
    writer.write(b"POST /api/command HTTP/1.1\r\nHost: x\r\nConnection: close\r\n"
                 + f"Authorization: {auth(who)['Authorization']}\r\n".encode()
                 + HEADER.encode() + b": " + header + b"\r\nContent-Type: application/json\r\n"
                 + f"Content-Length: {len(data)}\r\n\r\n".encode() + data)
    reply = await reader.read()
    writer.close()
    head, _, payload = reply.partition(b"\r\n\r\n")
    return int(head.split()[1]), json.loads(payload)


async def _estop_entry(api: Api, who: str, header: str | bytes) -> dict[str, Any]:
    """An e-stop sent with `header`: it must stop; its audit entry."""
    status, reply = await _post(api, who, ESTOP, header)
    assert status == 200 and reply["outcome"] == "executed", reply
    assert api.gov.latch.latched
    entry = api.entry(reply["audit_id"])
    assert entry["event"] == "ESTOP", entry
    assert entry.get("warnings") == reply.get("warnings"), (entry, reply)
    return entry


async def test_a_stops_warnings_are_recorded_marked_as_the_clients(tmp_path: Path) -> None:
    api = await Api(tmp_path).start()
    try:
        entry = await _estop_entry(api, "planner", json.dumps(["$.params.name: 'ESTOP'"]))
    finally:
        await api.close()
    assert entry["warnings"] == ["client: $.params.name: 'ESTOP'"]


@pytest.mark.parametrize("header", [
    "not json", '{"a": 1}', "[1, 2]", '["ok", null]', "[" * 3000, '"just a string"',
    '["\\ud800"]', b'["\xff\xfe"]'],
    ids=["not JSON", "an object", "numbers", "a null", "nested deep", "a string",
         "an unpaired surrogate escape", "not UTF-8"])
async def test_a_header_that_is_no_list_of_strings_is_one_warning(
        tmp_path: Path, header: str | bytes) -> None:
    api = await Api(tmp_path).start()
    try:
        entry = await _estop_entry(api, "planner", header)
    finally:
        await api.close()
    assert entry["warnings"] == [NOT_READ], entry


@pytest.mark.parametrize("header, recorded", [
    (json.dumps(["w"] * 1500), [*["client: w"] * MAX_COUNT, f"{HEADER}: {1500 - MAX_COUNT} "
                                f"more warnings not recorded (at most {MAX_COUNT})"]),
    (json.dumps(["x" * 7000]), ["client: " + "x" * (MAX_CHARS - 1) + "…"])],
    ids=["1500 warnings", "7000 characters"])
async def test_too_many_or_too_long_warnings_are_cut(tmp_path: Path, header: str,
                                                     recorded: list[str]) -> None:
    """Within the HTTP parser's 8190 bytes a header can hold a thousand warnings or one of
    7000 characters: the entry keeps `MAX_COUNT` of at most `MAX_CHARS` characters."""
    api = await Api(tmp_path).start()
    try:
        entry = await _estop_entry(api, "planner", header)
    finally:
        await api.close()
    assert entry["warnings"] == recorded, entry


async def test_control_characters_are_escaped(tmp_path: Path) -> None:
    """A warning cannot forge a line, or turn text around, where the log is read as text."""
    api = await Api(tmp_path).start()
    try:
        entry = await _estop_entry(api, "planner", json.dumps(
            ["a\nESTOP_CLEARED by ops\r", "\u202eevil\x00"]))
    finally:
        await api.close()
    assert entry["warnings"] == ["client: a\\nESTOP_CLEARED by ops\\r",
                                 "client: \\u202eevil\\x00"], entry


async def test_the_header_sent_twice_is_one_warning(tmp_path: Path) -> None:
    api = await Api(tmp_path).start()
    try:
        headers = [("Authorization", auth("planner")["Authorization"]),
                   (HEADER, '["a"]'), (HEADER, '["b"]')]
        async with api.http.post("/api/command", json=ESTOP, headers=headers) as resp:
            reply = await resp.json()
        assert resp.status == 200 and api.gov.latch.latched, reply
        entry = api.entry(reply["audit_id"])
    finally:
        await api.close()
    assert entry["warnings"] == [f"{HEADER}: sent 2 times: ignored"], entry


async def test_a_non_stop_carrying_the_header_writes_none_of_it(tmp_path: Path) -> None:
    """A move is no stop: executed or refused, its entry holds nothing of the header."""
    api = await Api(tmp_path).start()
    try:
        done, moved = await _post(api, "planner", MOVE, json.dumps(["INJECTED-1"]))
        refused, guest = await _post(api, "viewer", MOVE, json.dumps(["INJECTED-2"]))
        bad, _ = await _post(api, "planner", MOVE, "not json INJECTED-3")
        log = (tmp_path / "audit.jsonl").read_text()
    finally:
        await api.close()
    assert (done, refused, bad) == (200, 403, 200), (moved, guest)
    assert "INJECTED" not in log and HEADER not in log and "client: " not in log
    assert "warnings" not in moved and "warnings" not in guest


async def test_a_guests_estop_stops_and_its_warnings_are_marked_and_bounded(
        tmp_path: Path) -> None:
    """A GUEST has the e-stop: its header is recorded as any caller's, marked as the
    client's and cut to the bounds (a GUEST can write no more into the log than others)."""
    api = await Api(tmp_path).start()
    try:
        entry = await _estop_entry(api, "viewer", json.dumps(["y" * 700, "\n"] * 5))
    finally:
        await api.close()
    assert entry["principal"] == "viewer" and entry["role"] == "GUEST", entry
    warnings = entry["warnings"]
    assert len(warnings) == MAX_COUNT + 1 and all(len(w) <= len("client: ") + MAX_CHARS
                                                  for w in warnings[:MAX_COUNT]), warnings
    assert warnings[1] == "client: \\n", warnings


def test_the_clients_header_stays_under_its_bound() -> None:
    """However many and however long the door's warnings, `rcan-rtps mcp`'s header fits
    under the HTTP parser's limit (a header field over 8190 bytes fails any request, 431)."""
    worst = ["\U0001f600" * 10_000] * 50  # each char 12 bytes as JSON escapes
    value = header_value(worst)
    assert value is not None and len(value) <= MAX_HEADER_BYTES and value.isascii()
    first = json.loads(value)[0]
    assert first.endswith("…") and worst[0].startswith(first[:-1]) and len(first) > 100
    assert header_value([]) is None
    assert bounded(bounded("a\nb" * 400)) == bounded("a\nb" * 400)
