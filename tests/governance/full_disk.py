"""Child process of test_audit_full_disk: an audit log on a disk that fills up, then frees.

    full_disk.py DIR OUT --tmpfs    DIR is a small tmpfs: a filler file takes its last bytes
    full_disk.py DIR OUT --rlimit   RLIMIT_FSIZE (SIGXFSZ ignored) stops the log growing: EFBIG

Prints one JSON object: what failed while the disk was full, what succeeded after, and copies
the log and its sidecars to OUT for the parent to verify with the real CLI.
"""

from __future__ import annotations

import asyncio
import json
import os
import resource
import shutil
import signal
import sys
from pathlib import Path

from rcan_rtps.governance.audit import AuditEvent, AuditLog, AuditRecord
from rcan_rtps.governance.errors import AuditWriteError


def record(i: int) -> AuditRecord:
    # Same size every time: once one does not fit, none does until space is freed.
    return AuditRecord(event=AuditEvent.COMMAND_DISPATCHED, principal="ops", role="OWNER",
                       message_id=f"m{i:06d}", action_type="move",
                       params={"linear_x": 0.5, "pad": "x" * 300}, outcome="executed")


def fill(directory: Path) -> Path:
    """Take every free byte of the filesystem."""
    filler = directory / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT, 0o600)
    try:
        while True:
            try:
                if os.write(fd, b"\0" * 4096) == 0:
                    break
            except OSError:
                break
        while True:  # the last bytes of a partial page
            try:
                if os.write(fd, b"\0") == 0:
                    break
            except OSError:
                break
    finally:
        os.close(fd)
    return filler


async def failures(log: AuditLog, start: int, n: int) -> list[str]:
    """Append n entries, one at a time then n at once; the outcome of each."""
    out = []
    for i in range(n):
        try:
            await log.append(record(start + i))
            out.append("ok")
        except AuditWriteError as exc:
            out.append(type(exc.__cause__).__name__ + ":" + str(exc.__cause__))
    results = await asyncio.gather(*(log.append(record(start + n + i)) for i in range(n)),
                                   return_exceptions=True)
    out += ["ok" if not isinstance(r, BaseException) else "error" for r in results]
    return out


async def main(directory: Path, out: Path, mode: str) -> dict[str, object]:
    log = await AuditLog.open(directory / "audit.jsonl", directory / "audit.key")
    for i in range(3):
        await log.append(record(i))
    size = (directory / "audit.jsonl").stat().st_size
    if mode == "--tmpfs":
        filler = fill(directory)
        # The log's last page may still hold an entry or two: append until one fails.
        for i in range(20):
            try:
                await log.append(record(100 + i))
            except AuditWriteError:
                break
    else:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of death
        hard = resource.getrlimit(resource.RLIMIT_FSIZE)[1]
        # Room for part of one entry: the write is partial, then fails.
        resource.setrlimit(resource.RLIMIT_FSIZE, (size + 100, hard))
    full_size = (directory / "audit.jsonl").stat().st_size
    while_full = await failures(log, 200, 4)
    size_after_failures = (directory / "audit.jsonl").stat().st_size
    if mode == "--tmpfs":
        filler.unlink()
    else:
        resource.setrlimit(resource.RLIMIT_FSIZE, (hard, hard))
    after = await failures(log, 300, 4)
    head = log.head.last_seq
    healthy = log.healthy
    await log.close()
    for name in ("audit.jsonl", "audit.jsonl.sth", "audit.jsonl.pub",
                 "audit.jsonl.checkpoint"):
        if (directory / name).exists():
            shutil.copy(directory / name, out / name)
    return {"while_full": while_full, "after": after, "full_size": full_size,
            "size_after_failures": size_after_failures, "head": head, "healthy": healthy}


if __name__ == "__main__":
    result = asyncio.run(main(Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]))
    print(json.dumps(result), flush=True)
