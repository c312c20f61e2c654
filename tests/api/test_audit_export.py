"""GET /api/v1/audit (issue 24, item 7): the §20 audit export — entries of a time range,
verbatim, as JSON lines or CSV, streamed, with the chain root and the issuer's signature in
X-Audit-Chain-Root and X-Audit-Issuer-Sig; a bad parameter is a 400 JSON body, never a 500."""

from __future__ import annotations

import asyncio
import base64
import csv
import hashlib
import io
import json
from pathlib import Path
from typing import Any

import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey
from rcan.encoding import canonical_json

from rcan_rtps.api import _audit_export
from rcan_rtps.governance.merkle import leaf_hash, root_of
from tests.api.apihelpers import Api, auth

PATH = "/api/v1/audit"
T0 = 1_800_000_000  # the harness's ManualClock starts here


async def export(api: Api, query: str, who: str = "ops") -> tuple[int, dict[str, str], bytes]:
    async with api.http.get(PATH + query, headers=auth(who)) as resp:
        return resp.status, dict(resp.headers), await resp.read()


async def _entries_over_time(api: Api) -> list[bytes]:
    """BRIDGE_STARTED at T0, then a stop at each of T0+10, +20, +30: the log's lines."""
    await api.gov.start()
    for _ in range(3):
        api.clock.advance(10)
        assert (await api.command("planner", {"action": "stop"}))[0] == 200
    return (api.tmp / "audit.jsonl").read_bytes().splitlines()


def _key(api: Api) -> Ed25519PublicKey:
    return api.gov.audit.public_key


def _check_root_and_sig(api: Api, headers: dict[str, str], lines: list[bytes]) -> None:
    root = root_of([leaf_hash(line) for line in lines])
    assert headers["X-Audit-Chain-Root"] == "sha256:" + root.hex()
    sig = headers["X-Audit-Issuer-Sig"]
    assert sig.startswith("ed25519:")
    _key(api).verify(base64.b64decode(sig.removeprefix("ed25519:")), root)


async def test_jsonl_is_a_header_then_the_entries_verbatim(api: Api) -> None:
    lines = await _entries_over_time(api)
    status, headers, body = await export(api, f"?from={T0 + 10}&to={T0 + 30}")
    assert status == 200
    assert headers["Content-Type"].startswith("application/x-ndjson")
    assert headers["Transfer-Encoding"] == "chunked"  # streamed
    header, *exported = body.splitlines()
    chosen = [ln for ln in lines if T0 + 10 <= json.loads(ln)["timestamp_ms"] / 1000 < T0 + 30]
    assert exported == chosen and len(chosen) == 2  # [from, to): the stops at +10 and +20
    meta = json.loads(header)
    assert meta == {"type": "audit_export", "from": T0 + 10, "to": T0 + 30, "count": 2,
                    "first_seq": json.loads(chosen[0])["seq"],
                    "last_seq": json.loads(chosen[1])["seq"],
                    "chain_root": headers["X-Audit-Chain-Root"],
                    "issuer_sig": headers["X-Audit-Issuer-Sig"],
                    "kid": headers["X-Audit-Kid"], "rcan_version": "3.2"}
    assert headers["X-Audit-Count"] == "2"
    _check_root_and_sig(api, headers, chosen)


async def test_a_whole_export_has_the_root_of_the_logs_tree_head(api: Api) -> None:
    lines = await _entries_over_time(api)
    status, headers, body = await export(api, "")
    assert status == 200 and body.splitlines()[1:] == lines
    head = json.loads((api.tmp / "audit.jsonl.sth").read_text().splitlines()[-1])
    assert head["tree_size"] == len(lines)
    assert headers["X-Audit-Chain-Root"] == "sha256:" + head["root_hash"]
    _check_root_and_sig(api, headers, lines)
    for line in body.splitlines()[1:]:  # the SDK recomputes every exported id
        entry = json.loads(line)
        unsigned = {k: v for k, v in entry.items() if k not in ("audit_id", "sig")}
        assert entry["audit_id"] == "sha256:" + hashlib.sha256(
            canonical_json(unsigned)).hexdigest()


async def test_csv_rows_carry_fields_and_the_whole_line(api: Api) -> None:
    lines = await _entries_over_time(api)
    status, headers, body = await export(api, f"?format=csv&from={T0 + 10}")
    assert status == 200 and headers["Content-Type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(body.decode())))
    assert [r["entry"].encode() for r in rows] == lines[1:]
    assert [r["event"] for r in rows] == ["COMMAND_DISPATCHED"] * 3
    assert rows[0]["principal"] == "planner" and rows[0]["seq"] == "2"
    assert json.loads(rows[0]["params"]) == json.loads(lines[1])["params"]
    _check_root_and_sig(api, headers, lines[1:])


async def test_an_empty_range_is_an_empty_tree(api: Api) -> None:
    await _entries_over_time(api)
    status, headers, body = await export(api, f"?from={T0 + 1000}")
    assert status == 200
    assert json.loads(body.splitlines()[0])["count"] == 0 and len(body.splitlines()) == 1
    _check_root_and_sig(api, headers, [])


async def test_large_logs_are_read_in_chunks(api: Api, monkeypatch: pytest.MonkeyPatch) -> None:
    await api.gov.start()
    for _ in range(40):
        assert (await api.command("planner", {"action": "stop"}))[0] == 200
    lines = (api.tmp / "audit.jsonl").read_bytes().splitlines()
    reads: list[int] = []
    real = _audit_export.read_lines

    def counted(path: Path, start: int, end: int | None) -> tuple[list[bytes], int]:
        found, after = real(path, start, end)
        reads.append(len(found))
        return found, after

    monkeypatch.setattr(_audit_export, "CHUNK", 2048)  # a few entries a read
    monkeypatch.setattr(_audit_export, "read_lines", counted)
    status, headers, body = await export(api, "")
    assert status == 200 and body.splitlines()[1:] == lines
    assert len(reads) > 20 and max(reads) < len(lines) / 4  # never the whole log at once
    _check_root_and_sig(api, headers, lines)


@pytest.mark.parametrize(("query", "path"), [
    ("?from=yesterday", "$.query.from"), ("?to=-5", "$.query.to"),
    ("?from=1.5e9", "$.query.from"), ("?to=1800000000.1234", "$.query.to"),
    (f"?from={T0 + 5}&to={T0}", "$.query.from"), ("?format=xml", "$.query.format"),
    ("?form=jsonl", "$.query.form"), ("?from=1&from=2", "$.query.from"),
    ("?since=0", "$.query.since"), ("?from=", "$.query.from"),
])
async def test_bad_parameters_are_400_with_the_parameter(api: Api, query: str,
                                                         path: str) -> None:
    status, body = await api.call("GET", PATH + query, "ops")
    assert (status, body["error_code"], body["path"]) == (400, "SCHEMA_VALIDATION_FAILED",
                                                          path), body


async def test_reading_it_needs_the_audit_read_role(api: Api) -> None:
    status, body = await api.call("GET", PATH, "planner")  # USER < LEASEE
    assert (status, body["error_code"]) == (403, "INSUFFICIENT_PRIVILEGES")
    assert (await api.call("GET", PATH))[0] == 401
    status, _, _ = await export(api, "", "lessee")
    assert status == 200


def test_csv_columns_follow_the_audit_record() -> None:
    from rcan_rtps.governance import AuditRecord

    columns: tuple[Any, ...] = _audit_export.CSV_COLUMNS
    assert set(AuditRecord.__struct_fields__) <= set(columns) and columns[-1] == "entry"


async def test_from_and_to_take_up_to_three_decimals(api: Api) -> None:
    """Milliseconds: the log's own resolution (`timestamp_ms`), so an export can start or end
    between two entries logged within the same second."""
    lines = await _entries_over_time(api)
    status, _, body = await export(api, f"?from={T0 + 9.999}&to={T0 + 20.001}")
    assert status == 200, body
    header, *exported = body.splitlines()
    assert json.loads(header)["from"] == T0 + 9.999 and exported == lines[1:3]
    status, _, body = await export(api, f"?from={T0 + 10.001}")
    assert (status, body.splitlines()[1:]) == (200, lines[2:])


async def test_entries_appended_during_an_export_are_not_in_it(
        api: Api, monkeypatch: pytest.MonkeyPatch) -> None:
    """The headers (count, root, signature) are made in the first pass; an entry appended
    before the second pass reads the body must not go out under a root that does not hold it."""
    lines = await _entries_over_time(api)
    loop = asyncio.get_running_loop()
    real = _audit_export._body_chunk
    appended: list[int] = []

    def body_chunk(*args: Any) -> tuple[bytes, int]:
        if not appended:  # on the reader thread: a stop is logged meanwhile
            stop = api.command("planner", {"action": "stop"})
            appended.append(asyncio.run_coroutine_threadsafe(stop, loop).result(10)[0])
        return real(*args)

    monkeypatch.setattr(_audit_export, "_body_chunk", body_chunk)
    status, headers, body = await export(api, "")
    assert (status, appended) == (200, [200])
    assert len((api.tmp / "audit.jsonl").read_bytes().splitlines()) == len(lines) + 1
    assert body.splitlines()[1:] == lines and headers["X-Audit-Count"] == str(len(lines))
    _check_root_and_sig(api, headers, lines)
