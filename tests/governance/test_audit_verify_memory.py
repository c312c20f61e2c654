"""Checking a whole audit log holds a line at a time, never the log, and finds what it found
when it read the log whole.

`rcan-rtps audit verify`, `governance.audit.verify`, GET /api/audit/verify's worker and the
proofs read the whole file and split it: a month-long log of 700 MB took 1.4 GB, out of memory
on a robot computer of 4 GB. The sidecar of tree heads (a head per commit: as many as entries
on a quiet robot) was read and parsed whole too. Each bound here is a quarter of what is read.
"""

from __future__ import annotations

import asyncio
import base64
import json
from collections.abc import Callable
from pathlib import Path

import msgspec
import pytest
from govhelpers import fresh_copy, peak_of

from rcan_rtps.api._reads import verify_file
from rcan_rtps.governance.audit import (
    AuditEvent,
    AuditLog,
    AuditRecord,
    load_private_key,
    load_public_key,
    verify,
    verify_bytes,
)
from rcan_rtps.governance.clock import ManualClock
from rcan_rtps.governance.errors import AuditIntegrityError
from rcan_rtps.governance.logcheck import (
    check_consistency,
    check_inclusion,
    check_log,
    prove_consistency,
    prove_inclusion,
)
from rcan_rtps.governance.merkle import CompactTree, leaf_hash
from rcan_rtps.governance.treehead import sign_tree_head, tree_head_path
from tests.governance.test_audit_cli import run

ENTRIES = 3000
NOTE = "x" * 2000  # a command's parameters of some size: megabytes from fewer entries


def record(i: int) -> AuditRecord:
    return AuditRecord(event=AuditEvent.COMMAND_DISPATCHED, principal="planner", role="USER",
                       message_id=f"m-{i}", action_type="move",
                       params={"linear_x": 0.1 * i, "note": NOTE}, outcome="executed")


async def _write(directory: Path) -> None:
    log = await AuditLog.open(directory / "audit.jsonl", directory / "audit.key",
                              clock=ManualClock())
    for start in range(0, ENTRIES, 100):
        await asyncio.gather(*(log.append(record(i)) for i in range(start, start + 100)))
    await log.close()


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("log")
    asyncio.run(_write(directory))
    return directory


@pytest.fixture
def log_path(written: Path, tmp_path: Path) -> Path:
    """A fresh copy of the log and its files; the log's path."""
    return fresh_copy(written, tmp_path)


def pubkey_of(path: Path) -> object:
    return load_public_key(path.with_name(path.name + ".pub"))


# -- memory ----------------------------------------------------------------------------------


def test_audit_verify_reads_the_log_a_line_at_a_time(log_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    size = log_path.stat().st_size
    code, peak = peak_of(lambda: run("audit", "verify", str(log_path)))
    assert code == 0 and f"{ENTRIES} entries" in capsys.readouterr().out
    assert peak < size / 4, (peak, size)


def test_verify_reads_the_log_a_line_at_a_time(log_path: Path) -> None:
    size = log_path.stat().st_size
    head, peak = peak_of(lambda: verify(log_path, pubkey_of(log_path)))  # type: ignore[arg-type]
    assert head.last_seq == ENTRIES
    assert peak < size / 4, (peak, size)


def test_the_api_verifier_reads_the_log_a_line_at_a_time(log_path: Path) -> None:
    """What GET /api/audit/verify's worker process runs."""
    size = log_path.stat().st_size
    key = load_private_key(log_path.with_name("audit.key")).public_key().public_bytes_raw()
    report, peak = peak_of(lambda: verify_file(str(log_path), key))
    assert report.ok and report.last_seq == ENTRIES and report.tree_size == ENTRIES
    assert peak < size / 4, (peak, size)


def test_proofs_read_the_log_a_line_at_a_time(log_path: Path) -> None:
    size = log_path.stat().st_size
    key = pubkey_of(log_path)
    proof, peak = peak_of(lambda: prove_inclusion(log_path, 1234, key))  # type: ignore[arg-type]
    assert check_inclusion(proof, key).startswith("entry 1234 is in")  # type: ignore[arg-type]
    assert peak < size / 4, (peak, size)
    proof, peak = peak_of(
        lambda: prove_consistency(log_path, 1000, None, key))  # type: ignore[arg-type]
    assert proof["new_size"] == ENTRIES
    assert check_consistency(proof, key).startswith(  # type: ignore[arg-type]
        f"the tree of {ENTRIES} entries extends")
    assert peak < size / 4, (peak, size)


QUIET_ENTRIES = 12_000


async def _write_quiet(directory: Path) -> None:
    """Short entries; then the tree heads a quiet robot's log has: one per entry (each commit
    a single entry), as many bytes as the entries (written here, signed, in one go)."""
    path = directory / "audit.jsonl"
    log = await AuditLog.open(path, directory / "audit.key", clock=ManualClock())
    for start in range(0, QUIET_ENTRIES, 500):
        await asyncio.gather(*(log.append(AuditRecord(event=AuditEvent.COMMAND_DISPATCHED))
                               for _ in range(start, start + 500)))
    await log.close()
    key = load_private_key(directory / "audit.key")
    tree, lines = CompactTree(), []
    for line in path.read_bytes().splitlines():
        tree.append(leaf_hash(line))
        lines.append(sign_tree_head(key, tree.size, tree.root(), 1_800_000_000_000).line())
    tree_head_path(path).write_bytes(b"".join(lines))


def test_a_head_per_entry_is_checked_a_line_at_a_time(tmp_path: Path) -> None:
    asyncio.run(_write_quiet(tmp_path))
    path = tmp_path / "audit.jsonl"
    heads = tree_head_path(path).stat().st_size
    report, peak = peak_of(lambda: check_log(path, pubkey_of(path)))  # type: ignore[arg-type]
    assert report.ok and report.heads == QUIET_ENTRIES
    assert peak < heads / 4, (peak, heads)


# -- the same findings -----------------------------------------------------------------------


def _edit(path: Path, index: int, old: bytes, new: bytes) -> None:
    lines = path.read_bytes().split(b"\n")
    assert old in lines[index]
    lines[index] = lines[index].replace(old, new)
    path.write_bytes(b"\n".join(lines))


def torn(path: Path) -> None:
    with path.open("ab") as file:
        file.write(b'{"seq":3001,"prev_')


def last_edited(path: Path) -> None:
    _edit(path, ENTRIES - 1, b"executed", b"EXECUTED")


def middle_edited(path: Path) -> None:
    _edit(path, 1500, b"executed", b"EXECUTED")


def middle_resigned(path: Path) -> None:
    """An entry whose id was recomputed but not re-signed (no key to do it with)."""
    lines = path.read_bytes().split(b"\n")
    entry = json.loads(lines[700])
    entry["sig"] = base64.b64encode(b"\x01" * 64).decode()
    lines[700] = msgspec.json.encode(entry, order="sorted")
    path.write_bytes(b"\n".join(lines))


def untouched(path: Path) -> None:
    pass


@pytest.mark.parametrize("damage", [untouched, torn, last_edited, middle_edited,
                                    middle_resigned])
def test_verify_finds_what_verifying_the_bytes_whole_finds(log_path: Path,
                                                           damage: Callable[[Path], None]
                                                           ) -> None:
    """`verify_bytes` checks bytes held whole (the old way): a line at a time finds the
    same seq, for the same reason."""
    damage(log_path)
    key = pubkey_of(log_path)
    found: dict[str, object] = {}
    for name, check in (("whole", lambda: verify_bytes(log_path.read_bytes(), key)),
                        ("lines", lambda: verify(log_path, key))):
        try:
            found[name] = check()  # type: ignore[no-untyped-call]
        except AuditIntegrityError as exc:
            found[name] = (exc.seq, exc.detail)
    assert found["lines"] == found["whole"]
    if damage is not untouched:
        assert isinstance(found["lines"], tuple)


@pytest.mark.parametrize("damage,seq,detail", [
    (torn, ENTRIES + 1, "incomplete last line (torn tail)"),
    (last_edited, ENTRIES, "the last line is damaged"),
    (middle_edited, 1501, "audit_id does not match"),
    (middle_resigned, 701, "bad signature"),
])
def test_audit_verify_reports_a_break_where_it_is(log_path: Path,
                                                  damage: Callable[[Path], None], seq: int,
                                                  detail: str) -> None:
    """The report of a damaged log: the entries before the break valid (and the tree heads
    up to them matching), the break named, the heads (and checkpoint) past it named as
    covering more."""
    damage(log_path)
    sizes = [json.loads(line)["tree_size"]
             for line in tree_head_path(log_path).read_bytes().splitlines()]
    report = check_log(log_path, pubkey_of(log_path))  # type: ignore[arg-type]
    assert report.bad_seq == seq and report.entries == seq - 1
    assert report.problems[0].startswith(f"audit chain broken at seq {seq}: ")
    assert detail in report.problems[0]
    assert report.heads == sum(size < seq for size in sizes)
    assert report.newest is not None
    assert report.newest.tree_size == max(size for size in sizes if size < seq)
    past = [n for n, size in enumerate(sizes, start=1) if size >= seq]
    assert report.problems[1:] == [
        f"tree heads line {n}: tree head of size {sizes[n - 1]} (timestamp_ms "
        f"1800000000000) covers more entries than the log's {seq - 1} valid ones: the log "
        f"is truncated or damaged after seq {seq - 1}" for n in past] + [
        f"start-up checkpoint names seq {ENTRIES}, beyond the log's {seq - 1} valid "
        "entries: the log is truncated"] * (seq <= ENTRIES)  # (the close's checkpoint)


def test_heads_out_of_order_are_checked_as_in_order(log_path: Path) -> None:
    """The log writes its heads in the order of their sizes; a file that is not (an edited
    sidecar, a witness's copy appended to) is still checked head by head, reported in its
    lines' order."""
    sth = tree_head_path(log_path)
    lines = sth.read_bytes().splitlines(keepends=True)
    expected = check_log(log_path, pubkey_of(log_path))  # type: ignore[arg-type]
    assert expected.ok and expected.heads == len(lines)
    shuffled = lines[::-1] + lines[:5]
    sth.write_bytes(b"".join(shuffled))
    report = check_log(log_path, pubkey_of(log_path))  # type: ignore[arg-type]
    assert report.ok and report.heads == len(shuffled)
    assert report.newest == expected.newest
    # A head of another root, out of order: named by its line.
    other = json.loads(lines[3])
    forged = json.loads(lines[9])
    forged["tree_size"] = other["tree_size"]
    shuffled[2] = msgspec.json.encode(forged, order="sorted") + b"\n"
    sth.write_bytes(b"".join(shuffled))
    report = check_log(log_path, None)
    assert report.problems == [
        f"tree heads line 3: tree head of size {other['tree_size']} (timestamp_ms "
        f"{forged['timestamp_ms']}) has another root than the log's first "
        f"{other['tree_size']} entries: the log was rewritten"]
