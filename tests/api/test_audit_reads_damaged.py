"""The audit reads on a log that was edited or damaged on disk while the bridge runs.

The bridge's writer writes only entries, but anyone with write access to the file can append
a line: not JSON, JSON nested thousands of levels deep (msgspec raises RecursionError for
that, not DecodeError), or JSON without an entry's seq and time. The paged reads and the
export answer 503 AUDIT_UNREADABLE naming `rcan-rtps audit verify`; the safety manifest says
what it could not read. Never the middleware's internal error, never a traceback.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

import aiohttp
import pytest

from rcan_rtps.api import _audit_export
from rcan_rtps.api._errors import AuditUnreadable
from tests.api.apihelpers import Api, auth

DEEP = b'{"seq": 3, "timestamp_ms": 1, "x": ' + b"[" * 50_000 + b"]" * 50_000 + b"}"
PLANTED = {
    "deep": DEEP,
    "not JSON": b"garbage",
    "no seq": b'{"timestamp_ms": 1}',
    "an array": b"[3, 1]",
}
READS = ["/api/audit", "/api/audit/mine", "/api/v1/audit", "/api/v1/audit?format=csv"]


async def _with_planted(api: Api, line: bytes, where: str = "audit.jsonl") -> None:
    await api.gov.start()
    assert (await api.command("ops", {"action": "stop"}))[0] == 200
    with open(api.tmp / where, "ab") as file:
        file.write(line + b"\n")


async def _get(api: Api, path: str) -> tuple[int, dict[str, str], Any]:
    async with api.http.get(path, headers=auth("ops")) as resp:
        return resp.status, dict(resp.headers), await resp.json()


def _no_errors_logged(caplog: pytest.LogCaptureFixture) -> None:
    loud = [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]
    assert loud == [], [r.getMessage() for r in loud]


@pytest.mark.parametrize("path", READS)
@pytest.mark.parametrize("line", PLANTED.values(), ids=PLANTED.keys())
async def test_a_read_past_a_planted_line_is_503_audit_unreadable(
        api: Api, path: str, line: bytes, caplog: pytest.LogCaptureFixture) -> None:
    await _with_planted(api, line)
    status, headers, body = await _get(api, path)
    assert status == 503, body
    assert body["error_code"] == "AUDIT_UNREADABLE"
    assert "rcan-rtps audit verify" in body["reason"]
    assert "Retry-After" not in headers  # waiting will not mend the file
    _no_errors_logged(caplog)
    # the bridge goes on governing and writing its log
    assert (await api.command("ops", {"action": "stop"}))[0] == 200


async def test_a_page_before_the_planted_line_is_still_read(api: Api) -> None:
    """A page that ends before the damage does not reach it: only what a read needs counts."""
    await _with_planted(api, DEEP)
    status, _, body = await _get(api, "/api/audit?limit=1")
    assert status == 200
    assert [e["seq"] for e in body["entries"]] == [1]


@pytest.mark.parametrize("line", PLANTED.values(), ids=PLANTED.keys())
async def test_the_safety_manifest_says_the_last_line_is_not_an_entry(
        api: Api, line: bytes, caplog: pytest.LogCaptureFixture) -> None:
    await _with_planted(api, line)
    status, _, manifest = await _get(api, "/api/safety/manifest")
    assert status == 200
    assert manifest["audit_count"] is None and manifest["audit_last_event"] is None
    assert manifest["invariants"]["audit_trail_complete"] is False
    assert "last line is not an audit entry" in manifest["audit"]["problem"]
    assert manifest["audit"]["tree_head"]["tree_size"] == 2  # the tree heads are intact
    _no_errors_logged(caplog)


async def test_the_safety_manifest_says_the_last_tree_head_is_not_one(
        api: Api, caplog: pytest.LogCaptureFixture) -> None:
    await _with_planted(api, DEEP, where="audit.jsonl.sth")
    status, _, manifest = await _get(api, "/api/safety/manifest")
    assert status == 200
    assert manifest["audit_count"] == 2  # the log itself is intact
    assert manifest["audit"]["tree_head"] is None
    assert "last tree head is not one" in manifest["audit"]["problem"]
    assert manifest["invariants"]["audit_trail_complete"] is False
    _no_errors_logged(caplog)


async def test_an_intact_log_has_no_problem_in_the_manifest(api: Api) -> None:
    await api.gov.start()
    _, _, manifest = await _get(api, "/api/safety/manifest")
    assert manifest["audit"]["problem"] is None
    assert manifest["invariants"]["audit_trail_complete"] is True


async def test_an_export_whose_lines_change_under_it_ends_incomplete(
        api: Api, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """A line edited in place between the export's two passes (after its headers went out):
    the body ends without its chunked terminator, so no client takes it as whole."""
    await api.gov.start()
    assert (await api.command("ops", {"action": "stop"}))[0] == 200
    log_file = api.tmp / "audit.jsonl"
    selected = _audit_export.select

    async def select_then_damage(*args: Any) -> Any:
        chosen = await selected(*args)
        lines = log_file.read_bytes().split(b"\n")
        lines[1] = b"#" * len(lines[1])  # the same length: the second pass finds its place
        log_file.write_bytes(b"\n".join(lines))
        return chosen

    monkeypatch.setattr(_audit_export, "select", select_then_damage)
    async with api.http.get("/api/v1/audit", headers=auth("ops")) as resp:
        assert resp.status == 200  # the headers had gone out
        with pytest.raises(aiohttp.ClientPayloadError):
            await asyncio.wait_for(resp.read(), 30)  # (a bound on a hang: the body never ended)
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING] == [
        "audit export of /api/v1/audit cut short: " + AuditUnreadable.REASON]
    _no_errors_logged(caplog)
