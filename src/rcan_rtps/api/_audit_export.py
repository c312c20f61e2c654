"""GET /api/v1/audit?from=&to=&format=jsonl|csv: the §20 audit trail export.

Who may read it: `rbac.audit_read_role`, as GET /api/audit (403 otherwise, not audited).

- `from`, `to`: Unix seconds (an integer, or up to three decimals), optional; an entry is
  exported when from ≤ its `timestamp_ms`/1000 < to (half-open, so consecutive exports never
  share an entry). `format`: `jsonl` (default) or `csv`. Anything else — an unknown or repeated
  parameter, a value that is not such a number, from > to — is 400 SCHEMA_VALIDATION_FAILED
  naming the parameter (a typo must not export everything).
- The entries go out byte for byte as the log holds them (canonical JSON: each one re-hashes
  to its `audit_id` and verifies with the bridge's key). `jsonl` (application/x-ndjson): a
  header line `{"type": "audit_export", "from", "to", "count", "first_seq", "last_seq",
  "chain_root", "issuer_sig", "kid", "rcan_version"}`, then one entry a line. `csv` (text/csv):
  one row per entry, its scalar fields as columns (objects as JSON text) and the whole line in
  the last column, `entry`.
- `X-Audit-Chain-Root: sha256:<hex>` is the RFC 6962 Merkle root (the hashing of the log's
  tree heads, `governance.merkle`) over the exported entries' lines, in order: an export of a
  whole log has the root of its tree head of that size. `X-Audit-Issuer-Sig: ed25519:<base64>`
  is Ed25519 by the audit key (`kid`, the node manifest's key) over the 32 raw bytes of that
  root. Both are in the JSONL header too. They say what the bridge read from its log; each
  entry still carries its own signature (`rcan-rtps audit verify`, GET /api/audit/verify).
- Large logs are streamed: the log is read twice in chunks of about 1 MiB on the audit reader
  thread (first for the root the headers need, then for the body; decoding, hashing and
  formatting are done there too, off the event loop), never whole into memory; entries
  appended meanwhile are not part of the export. A client that goes away mid-stream is no
  error (the middleware's debug line).
"""

from __future__ import annotations

import asyncio
import csv
import io
import logging
import re
from collections.abc import Awaitable, Callable, Iterable
from pathlib import Path
from typing import Any

import msgspec
from aiohttp import web

from rcan_rtps.governance import AuditRecord, Governor
from rcan_rtps.governance.keyfacts import KeyFacts, signature_text
from rcan_rtps.governance.merkle import CompactTree, leaf_hash
from rcan_rtps.rcan import SPOKEN, ErrorCode, Role, SchemaValidationError

from ._bodies import error_response
from ._errors import AuditUnreadable, ReadsBusy
from ._keys import PRINCIPAL, READS
from ._node_manifest import AUDIT_EXPORT, newest_version
from ._reads import decoded

log = logging.getLogger(__name__)
PATH = AUDIT_EXPORT
CHUNK = 1 << 20
_SECONDS = re.compile(r"([0-9]{1,11})(?:\.([0-9]{1,3}))?")
_PARAMS = ("from", "to", "format")
FORMATS = {"jsonl": "application/x-ndjson", "csv": "text/csv"}
# The log adds these to what a caller states (AuditRecord), around it.
CSV_COLUMNS = ("seq", "timestamp", "timestamp_ms",
               *(f for f in AuditRecord.__struct_fields__),
               "ruri", "bridge", "canonical", "prev_hash", "audit_id", "sig", "entry")


class _Entry(msgspec.Struct):
    seq: int
    timestamp_ms: int


_ENTRY = msgspec.json.Decoder(_Entry)


class Query(msgspec.Struct, frozen=True):
    lo_ms: int
    hi_ms: int | None  # None: no upper bound
    format: str
    given: dict[str, Any]  # from/to as numbers, for the JSONL header


class Selection:
    """Pass one: which lines fall in the range, their Merkle tree, and where they lie."""

    def __init__(self, query: Query) -> None:
        self.query = query
        self.tree = CompactTree()
        self.first_seq: int | None = None
        self.last_seq: int | None = None
        self.start: int | None = None  # byte offset of the first chosen line's chunk
        self.end = 0  # just past the last complete line read

    def chosen(self, line: bytes) -> _Entry | None:
        """The line's seq and time if it falls in the range, else None."""
        entry = decoded(_ENTRY, line)
        q = self.query
        inside = q.lo_ms <= entry.timestamp_ms and (q.hi_ms is None
                                                    or entry.timestamp_ms < q.hi_ms)
        return entry if inside else None

    def add(self, lines: list[bytes], chunk_start: int) -> None:
        for line in lines:
            entry = self.chosen(line)
            if entry is None:
                continue
            self.tree.append(leaf_hash(line))
            self.last_seq = entry.seq
            if self.start is None:
                self.first_seq, self.start = entry.seq, chunk_start


def _ms(name: str, text: str) -> int:
    match = _SECONDS.fullmatch(text)
    if match is None:
        raise SchemaValidationError(f"$.query.{name}",
                                    "expected Unix seconds (digits, up to 3 decimals)")
    return int(match[1]) * 1000 + int((match[2] or "").ljust(3, "0"))


def parse_query(query: Any) -> Query:
    """The export's parameters; SchemaValidationError naming the one at fault."""
    for name in query:
        if name not in _PARAMS:
            raise SchemaValidationError(f"$.query.{name}",
                                        f"unknown parameter (known: {', '.join(_PARAMS)})")
        if len(query.getall(name)) > 1:
            raise SchemaValidationError(f"$.query.{name}", "given more than once")
    lo = _ms("from", query["from"]) if "from" in query else 0
    hi = _ms("to", query["to"]) if "to" in query else None
    if hi is not None and lo > hi:
        raise SchemaValidationError("$.query.from", "after `to`")
    fmt = query.get("format", "jsonl")
    if fmt not in FORMATS:
        raise SchemaValidationError("$.query.format", f"expected one of {', '.join(FORMATS)}")
    given = {"from": lo / 1000 if lo % 1000 else lo // 1000,
             "to": None if hi is None else (hi / 1000 if hi % 1000 else hi // 1000)}
    return Query(lo_ms=lo, hi_ms=hi, format=fmt, given=given)


def read_lines(path: Path, start: int, end: int | None) -> tuple[list[bytes], int]:
    """The complete lines from byte `start` (a line's start), about CHUNK bytes of them (at
    least one), never past `end` (None: the end of the file); and the offset after them."""
    with path.open("rb") as file:
        file.seek(start)
        want = CHUNK
        while True:
            limit = want if end is None else min(want, end - start)
            data = file.read(limit)
            cut = data.rfind(b"\n")
            if cut >= 0 or len(data) < limit or limit == 0:
                break
            file.seek(start)
            want *= 2  # a line longer than a chunk: read it whole
    body = data[: cut + 1]
    return body.split(b"\n")[:-1], start + len(body)


async def _on_reader(request: web.Request, fn: Callable[..., Any], *args: Any) -> Any:
    """`fn` on the audit reader thread; while it is busy, wait our turn (an export that has
    started answering cannot turn into a 429)."""
    while True:
        try:
            return await request.app[READS].get().read(fn, *args)
        except ReadsBusy:
            await asyncio.sleep(0.05)


def _select_chunk(chosen: Selection, path: Path, start: int) -> int:
    """Pass one over one chunk (reader thread): where the next one starts."""
    lines, after = read_lines(path, start, None)
    chosen.add(lines, start)
    return after


def _body_chunk(chosen: Selection, path: Path, start: int, fmt: str) -> tuple[bytes, int]:
    """Pass two over one chunk (reader thread): its chosen entries, formatted."""
    lines, after = read_lines(path, start, chosen.end)
    return _body_of((ln for ln in lines if chosen.chosen(ln)), fmt), after


async def select(request: web.Request, path: Path, query: Query) -> Selection:
    """Decoding, hashing and formatting stay on the reader thread, off the event loop."""
    chosen = Selection(query)
    start = 0
    while True:
        after = await _on_reader(request, _select_chunk, chosen, path, start)
        if after == start:
            chosen.end = start
            return chosen
        start = after


def _csv_rows(lines: Iterable[bytes]) -> bytes:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\r\n")
    for line in lines:
        entry = msgspec.json.decode(line)
        writer.writerow([_cell(entry.get(c)) for c in CSV_COLUMNS[:-1]] + [line.decode()])
    return out.getvalue().encode()


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, (dict, list)):
        return msgspec.json.encode(value, order="sorted").decode()
    return str(value).lower() if isinstance(value, bool) else str(value)


def _csv_header() -> bytes:
    out = io.StringIO()
    csv.writer(out, lineterminator="\r\n").writerow(CSV_COLUMNS)
    return out.getvalue().encode()


def _body_of(lines: Iterable[bytes], fmt: str) -> bytes:
    if fmt == "csv":
        return _csv_rows(lines)
    return b"".join(line + b"\n" for line in lines)


def _cut_short(request: web.Request, response: web.StreamResponse) -> web.StreamResponse:
    """A line read in pass one is no entry in pass two: the file was changed under the export,
    after its headers went out. The connection is closed before the chunked body's end, so
    the client sees an incomplete export, never a short one that looks whole."""
    log.warning("audit export of %s cut short: %s", request.path_qs, AuditUnreadable.REASON)
    if request.transport is not None:
        request.transport.close()
    return response


def handler(governor: Governor, read_role: Role
            ) -> Callable[[web.Request], Awaitable[web.StreamResponse]]:
    key = KeyFacts(governor.audit.public_key)

    async def get_audit_export(request: web.Request) -> web.StreamResponse:
        if request[PRINCIPAL].role < read_role:  # a read: refused 403, not audited
            return error_response(403, ErrorCode.INSUFFICIENT_PRIVILEGES,
                                  reason=f"needs {read_role.name} or higher")
        try:
            query = parse_query(request.query)
        except SchemaValidationError as exc:
            return error_response(400, ErrorCode.SCHEMA_VALIDATION_FAILED, reason=exc.detail,
                                  path=exc.path)
        path = governor.audit.path
        try:
            chosen = await select(request, path, query)
        except AuditUnreadable:
            return error_response(503, "AUDIT_UNREADABLE", reason=AuditUnreadable.REASON)
        root = chosen.tree.root()
        chain_root = "sha256:" + root.hex()
        issuer_sig = signature_text(governor.audit.sign_digest(root))
        response = web.StreamResponse(headers={
            "Content-Type": f"{FORMATS[query.format]}; charset=utf-8",
            "X-Audit-Chain-Root": chain_root, "X-Audit-Issuer-Sig": issuer_sig,
            "X-Audit-Count": str(chosen.tree.size), "X-Audit-Kid": key.kid})
        response.enable_chunked_encoding()
        await response.prepare(request)
        if query.format == "csv":
            await response.write(_csv_header())
        else:
            await response.write(msgspec.json.encode({
                "type": "audit_export", **query.given, "count": chosen.tree.size,
                "first_seq": chosen.first_seq, "last_seq": chosen.last_seq,
                "chain_root": chain_root, "issuer_sig": issuer_sig, "kid": key.kid,
                "rcan_version": newest_version(SPOKEN)}) + b"\n")
        start = chosen.end if chosen.start is None else chosen.start
        while start < chosen.end:
            try:
                body, start = await _on_reader(request, _body_chunk, chosen, path, start,
                                               query.format)
            except AuditUnreadable:
                return _cut_short(request, response)
            await response.write(body)
        await response.write_eof()
        return response

    return get_audit_export
