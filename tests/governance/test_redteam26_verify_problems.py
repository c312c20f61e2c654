"""Red team 26: `audit verify` lists a bounded number of problems, and counts the rest.

A file of tree heads with millions of bad lines (or of signed heads that match nothing: a log
rewritten under a long sidecar) gave a report of millions of problems — as many FAIL lines,
and a JSON list as long from GET /api/audit/verify. The first `PROBLEMS_LISTED` of each file,
and of the heads that do not match, are listed; one line counts the others. Where the chain
broke is listed whatever the heads say."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest

from rcan_rtps.governance.audit import (
    AuditEvent,
    AuditLog,
    AuditRecord,
    load_private_key,
    load_public_key,
)
from rcan_rtps.governance.logcheck import PROBLEMS_LISTED, check_log
from rcan_rtps.governance.treehead import sign_tree_head, tree_head_path
from tests.governance.test_audit_cli import run

BAD_LINES = 5000
WRONG_ROOTS = 300


async def _log(directory: Path) -> Path:
    path = directory / "audit.jsonl"
    log = await AuditLog.open(path, directory / "audit.key")
    for i in range(4):
        await log.append(AuditRecord(event=AuditEvent.COMMAND_DISPATCHED, params={"i": i}))
    await log.close()
    return path


def _spoil(path: Path) -> None:
    """Heads signed by the log's key whose roots match nothing, then lines that are no head;
    and one entry of the log edited (the chain breaks at seq 3)."""
    key = load_private_key(path.with_name("audit.key"))
    wrong = b"".join(sign_tree_head(key, 1 + n % 2, bytes(32), 1_800_000_000_000 + n).line()
                     for n in range(WRONG_ROOTS))
    with tree_head_path(path).open("ab") as heads:
        heads.write(wrong + b"not a tree head\n" * BAD_LINES)
    lines = path.read_bytes().splitlines(keepends=True)
    entry = json.loads(lines[2])
    entry["params"] = {"i": 99}
    lines[2] = json.dumps(entry, sort_keys=True, separators=(",", ":")).encode() + b"\n"
    path.write_bytes(b"".join(lines))


def test_a_report_lists_the_first_problems_and_counts_the_rest(tmp_path: Path) -> None:
    path = asyncio.run(_log(tmp_path))
    own_heads = len(tree_head_path(path).read_bytes().splitlines())
    _spoil(path)
    report = check_log(path, load_public_key(path.with_name("audit.jsonl.pub")))
    assert not report.ok and report.bad_seq == 3
    # Each file's first bad lines and the first heads that match nothing, the chain's break,
    # the checkpoint's, and the count of the rest.
    assert 2 * PROBLEMS_LISTED < len(report.problems) <= 2 * PROBLEMS_LISTED + 4
    assert sum("not a tree head" in p for p in report.problems) == PROBLEMS_LISTED
    # Of the heads that match nothing, the first in the file's order are listed, in order.
    unmatched = [int(p.split(" line ")[1].split(":")[0]) for p in report.problems
                 if "another root" in p or "covers more entries" in p]
    assert len(unmatched) == PROBLEMS_LISTED
    assert unmatched == sorted(unmatched) and unmatched[-1] <= own_heads + PROBLEMS_LISTED
    assert any("seq 3" in p and "tree head" not in p for p in report.problems)
    count, rest = report.problems[-1].split(" ", 1)
    assert rest.startswith("more problems with tree heads not listed")
    assert int(count) >= BAD_LINES + WRONG_ROOTS - 2 * PROBLEMS_LISTED


def test_the_cli_prints_a_bounded_report(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    path = asyncio.run(_log(tmp_path))
    _spoil(path)
    assert run("audit", "verify", str(path)) == 1
    failures = [line for line in capsys.readouterr().err.splitlines()
                if line.startswith("FAIL")]
    assert 2 * PROBLEMS_LISTED < len(failures) <= 2 * PROBLEMS_LISTED + 4
    assert "more problems with tree heads not listed" in failures[-1]
