"""Child process of test_crash: appends forever, printing each audit_id once append returned.

With `--stall`, every batch is written in two halves; after the first half the child prints
HALF and stalls, so the parent can kill it with a batch provably half on disk.
"""

from __future__ import annotations

import asyncio
import os
import sys
import time

from rcan_rtps.governance import audit
from rcan_rtps.governance.audit import AuditEvent, AuditLog, AuditRecord


def stalling_write(fd: int, data: bytes) -> None:
    half = len(data) // 2
    os.write(fd, data[:half])
    print("HALF", flush=True)
    time.sleep(30)  # the parent kills us here
    os.write(fd, data[half:])
    os.fsync(fd)


async def main(path: str, key: str, stall: bool) -> None:
    log = await AuditLog.open(path, key)
    n = 0

    async def one(i: int) -> None:
        receipt = await log.append(AuditRecord(
            event=AuditEvent.COMMAND_DISPATCHED, message_id=str(i),
            params={"pad": "x" * (i % 500)},  # varied sizes: kills land mid-line
        ))
        sys.stdout.write(receipt.audit_id + "\n")
        sys.stdout.flush()

    while True:
        if stall and n >= 40:
            audit._write_durable = stalling_write  # type: ignore[attr-defined]
        await asyncio.gather(*(one(n + i) for i in range(8)))
        n += 8


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1], sys.argv[2], "--stall" in sys.argv))
