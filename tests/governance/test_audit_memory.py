"""What reading the audit log back holds in memory: a line at a time, never the part it reads.

A start verifies what its checkpoint does not cover; that part may be long — a run whose
checkpoints were not written (their write failing only costs the next start time), or whose
checkpoint no longer matches — and it was read whole, then joined: twice its size at once
(200 000 entries, 139 MB: a 321 MB start; a board's start ended out of memory, again at each
restart). Each bound here is a quarter of what is read, far above a line and a read chunk.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
from pathlib import Path
from typing import Any

import pytest
from govhelpers import fresh_copy, peak_of

from rcan_rtps.governance import audit as audit_mod
from rcan_rtps.governance.audit import (
    AuditEvent,
    AuditLog,
    AuditRecord,
    ChainHead,
    Checkpoint,
    check_log_contents,
    checkpoint_path,
)
from rcan_rtps.governance.clock import ManualClock
from rcan_rtps.governance.treehead import TreeHeadFile, tree_head_path

ENTRIES = 3000
# A command's parameters of some size: the megabytes of a long run from fewer entries.
PARAMS = {"linear_x": 0.2, "note": "x" * 2000}


def record(i: int) -> AuditRecord:
    return AuditRecord(event=AuditEvent.COMMAND_DISPATCHED, principal="planner", role="USER",
                       message_id=f"m-{i}", action_type="move", params=PARAMS,
                       applied=PARAMS, outcome="executed", ros2_topic="/cmd_vel")


async def _write_run(directory: Path) -> None:
    """A run of ENTRIES commands whose only checkpoint is the one after its first entry."""
    path = directory / "audit.jsonl"
    log = await AuditLog.open(path, directory / "audit.key", clock=ManualClock())
    await log.append(AuditRecord(event=AuditEvent.BRIDGE_STARTED,
                                 params={"estop_latched": False, "locks": {}}))
    await log.checkpoint()
    first = checkpoint_path(path).read_bytes()
    for start in range(0, ENTRIES, 100):
        await asyncio.gather(*(log.append(record(i)) for i in range(start, start + 100)))
    await log.close()
    (directory / "closing.checkpoint").write_bytes(checkpoint_path(path).read_bytes())
    checkpoint_path(path).write_bytes(first)  # the later ones were never written


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("run")
    asyncio.run(_write_run(directory))
    return directory


@pytest.fixture
def run_log(written: Path, tmp_path: Path) -> Path:
    """A fresh copy of the run's files (a start appends to them); the log's path."""
    return fresh_copy(written, tmp_path)


def past_first_checkpoint(path: Path) -> int:
    return path.stat().st_size - json.loads(checkpoint_path(path).read_bytes())["end"]


def opened(path: Path) -> ChainHead:
    """A start's open of the log (and its close); the head it verified."""

    async def open_and_close() -> ChainHead:
        log = await AuditLog.open(path, path.with_name("audit.key"))
        await log.close()
        return log.head

    return asyncio.run(open_and_close())


def entries_of(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_bytes().splitlines()]


def test_the_start_verifies_the_part_past_its_checkpoint_a_line_at_a_time(
        run_log: Path) -> None:
    past = past_first_checkpoint(run_log)
    head, peak = peak_of(lambda: opened(run_log))
    assert head.last_seq == ENTRIES + 1  # every entry past the checkpoint was verified
    assert peak < past / 4, (peak, past)


def test_a_long_torn_tail_is_measured_and_hashed_never_held(run_log: Path) -> None:
    """The tail's entry says how long it was and its SHA-256, as before, from the file."""
    torn = b'{"seq":' + b"7" * (4 << 20)  # no newline: an append the crash cut, or junk
    with run_log.open("ab") as file:
        file.write(torn)
    _, peak = peak_of(lambda: opened(run_log))
    recovered = entries_of(run_log)[-1]
    assert recovered["event"] == "AUDIT_TAIL_RECOVERED"
    assert recovered["params"] == {"after_seq": ENTRIES + 1, "cut_bytes": len(torn),
                                   "cut_sha256": hashlib.sha256(torn).hexdigest()}
    assert peak < len(torn) / 4, (peak, len(torn))


def test_an_older_checkpoint_s_tree_is_hashed_a_line_at_a_time(run_log: Path) -> None:
    """A checkpoint of an older version has no tree peaks: the lines it vouches for (here
    the whole log) are hashed again for the tree, not verified, nor held."""
    cp = json.loads((run_log.with_name("closing.checkpoint")).read_bytes())
    audit_mod._write_checkpoint(checkpoint_path(run_log),
                                audit_mod.load_private_key(run_log.with_name("audit.key")),
                                Checkpoint(seq=cp["seq"], audit_id=cp["audit_id"],
                                           start=cp["start"], end=cp["end"]))
    head, peak = peak_of(lambda: opened(run_log))
    assert head.last_seq == ENTRIES + 1
    assert peak < run_log.stat().st_size / 4, (peak, run_log.stat().st_size)


def test_config_check_reads_the_log_back_a_line_at_a_time(run_log: Path) -> None:
    past = past_first_checkpoint(run_log)
    note, peak = peak_of(lambda: check_log_contents(run_log, run_log.with_name("audit.key")))
    assert note is None  # read back (it is below READ_BACK_LIMIT), and found whole
    assert peak < past / 4, (peak, past)


def test_a_tree_head_file_without_a_newline_in_megabytes_is_cut_by_blocks(
        run_log: Path) -> None:
    heads = tree_head_path(run_log)
    whole = heads.stat().st_size
    junk = b"7" * (2 << 20)
    with heads.open("ab") as file:
        file.write(junk)
    sidecar, peak = peak_of(lambda: TreeHeadFile(heads))
    sidecar.close()
    assert heads.stat().st_size == whole  # cut back to its last whole head
    assert peak < len(junk) / 4, (peak, len(junk))
