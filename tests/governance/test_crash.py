"""A writer killed with SIGKILL mid-append leaves a log that recovers, verifies and holds
every decision it had reported as returned."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
from pathlib import Path

from rcan_rtps.governance.audit import AuditLog, verify

WRITER = Path(__file__).with_name("crash_writer.py")
ROUNDS = 6


def run_and_kill(path: Path, key: Path, stall: bool, reads: int) -> list[str]:
    """Start a writer, read `reads` lines (or up to its stall), SIGKILL it; returned ids."""
    argv = [sys.executable, str(WRITER), str(path), str(key)] + (["--stall"] if stall else [])
    child = subprocess.Popen(argv, stdout=subprocess.PIPE, text=True)
    assert child.stdout is not None
    returned: list[str] = []
    for _ in range(reads):
        line = child.stdout.readline().strip()
        assert line, "the writer died on its own"
        if line == "HALF":
            break
        returned.append(line)
    os.kill(child.pid, signal.SIGKILL)
    child.wait()
    returned.extend(x.strip() for x in child.stdout if x.strip() not in ("", "HALF"))
    child.stdout.close()
    return returned


async def test_sigkill_mid_append_recovers_with_every_returned_entry(tmp_path: Path) -> None:
    path, key = tmp_path / "audit.jsonl", tmp_path / "audit.key"
    returned: list[str] = []
    recoveries = 0
    rng = random.Random(4)
    for round_ in range(ROUNDS):
        stall = round_ % 2 == 1  # every other round dies with a batch half written
        returned += run_and_kill(path, key, stall, reads=rng.randint(20, 200) if not stall
                                 else 10_000)
        torn = not path.read_bytes().endswith(b"\n")
        assert torn or not stall

        log = await AuditLog.open(path, key)  # cuts a torn tail and audits the cut
        await log.close()
        head = verify(path, log.public_key)
        text = path.read_text()
        if torn:
            recoveries += 1
            assert '"event":"AUDIT_TAIL_RECOVERED"' in text.splitlines()[-1]
        ids = {line.split('"audit_id":"', 1)[1][:71] for line in text.splitlines()}
        assert head.count == len(ids)
        missing = [a for a in returned if a not in ids]
        assert not missing, f"{len(missing)} returned decisions lost"
    assert recoveries >= ROUNDS // 2
