"""Audit chain throughput: verify rate and durable append rate, with and without group commit.

Every number comes from this run on this machine; ratios are against the same run's baseline
(one write+fsync per entry). The result replaces the `## Audit log` section of
docs/benchmarks.md. Usage: .venv/bin/python bench/audit.py [--entries 2000] [--dir DIR]
"""

from __future__ import annotations

import argparse
import asyncio
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

from report import write_section  # bench/report.py (the script's own folder)

from rcan_rtps.governance.audit import AuditEvent, AuditLog, AuditRecord, verify_bytes

ROOT = Path(__file__).resolve().parents[1]
SECTION = "## Audit log"


def record(i: int) -> AuditRecord:
    return AuditRecord(
        event=AuditEvent.COMMAND_DISPATCHED, principal="planner-agent", role="USER",
        message_id=f"{i:08d}-58cd-4bd1-9a51-2f1b2e1d33a0", action_type="move",
        params={"linear_x": 0.5, "angular_z": 0.1}, applied={"linear_x": 0.5, "angular_z": 0.1},
        outcome="executed", ros2_topic="/robot1/cmd_vel",
        ai={"provider": "openai", "model": "gpt-4o", "confidence": 0.94, "thought_id": "t"},
    )


async def append_rate(dir_: Path, n: int, *, concurrency: int, group_commit: bool) -> float:
    """Durable entries per second: `concurrency` writers, each awaiting its own append."""
    path = dir_ / f"append-{concurrency}-{group_commit}.jsonl"
    log = await AuditLog.open(path, dir_ / "bench.key", group_commit=group_commit)
    per_writer = n // concurrency

    async def writer(w: int) -> None:
        for i in range(per_writer):
            await log.append(record(w * per_writer + i))

    start = time.perf_counter()
    await asyncio.gather(*(writer(w) for w in range(concurrency)))
    elapsed = time.perf_counter() - start
    await log.close()
    return per_writer * concurrency / elapsed


def verify_rate(path: Path, pubkey: object | None) -> float:
    data = path.read_bytes()
    start = time.perf_counter()
    head = verify_bytes(data, pubkey)  # type: ignore[arg-type]
    return head.count / (time.perf_counter() - start)


def filesystem(dir_: Path) -> str:
    try:
        out = subprocess.run(["df", "-T", str(dir_)], capture_output=True, text=True, check=True)
        return out.stdout.splitlines()[1].split()[1]
    except (OSError, subprocess.CalledProcessError, IndexError):
        return "unknown"


async def measure(dir_: Path, n: int) -> list[tuple[str, float, str]]:
    base = await append_rate(dir_, n // 4, concurrency=1, group_commit=False)
    rows = [("append, 1 writer, fsync per entry (baseline)", base, "1.0×")]
    for conc in (16, 64):
        for group in (False, True):
            rate = await append_rate(dir_, n, concurrency=conc, group_commit=group)
            label = f"append, {conc} writers, {'group commit' if group else 'fsync per entry'}"
            rows.append((label, rate, f"{rate / base:.1f}×"))
    chain = dir_ / "append-64-True.jsonl"
    log = await AuditLog.open(chain, dir_ / "bench.key")
    pub = log.public_key
    await log.close()
    rows.append(("verify, hashes and Ed25519 signatures", verify_rate(chain, pub), "—"))
    rows.append(("verify, hashes only", verify_rate(chain, None), "—"))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--entries", type=int, default=2000)
    parser.add_argument("--dir", type=Path, default=ROOT / ".cache" / "bench-audit",
                        help="where to write (a real disk: tmpfs makes fsync free)")
    parser.add_argument("--no-write", action="store_true", help="print only")
    args = parser.parse_args()
    args.dir.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(dir=args.dir))
    try:
        rows = asyncio.run(measure(work, args.entries))
        fs = filesystem(work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    lines = [
        SECTION, "",
        f"`bench/audit.py`: {args.entries} entries per case, on {fs}, same machine, same run. "
        "Durable = write + fsync (F_FULLFSYNC on macOS) completed before `append` returns. "
        "Ratio = rate / the single-writer fsync-per-entry baseline; higher is better.", "",
        "| case | entries/s | ratio |", "|---|---|---|",
        *(f"| {label} | {rate:,.0f} | {ratio} |" for label, rate, ratio in rows),
    ]
    markdown = "\n".join(lines)
    print(markdown)
    if not args.no_write:
        write_section(SECTION, markdown)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
