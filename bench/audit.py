"""Audit chain throughput: verify rate and durable append rate, with and without group commit.

Every number comes from this run on this machine; ratios are against the same run's baseline
(one write+fsync per entry). The result replaces the `## Audit log` section of
docs/benchmarks.md. Usage: .venv/bin/python bench/audit.py [--entries 2000] [--dir DIR]
[--baseline-ref REF [--rounds 5]]: with a baseline ref, that ref's audit log (a temporary git
worktree) and this tree's are measured alternately, each run in a fresh interpreter.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from report import ROOT, baseline_tree, write_section  # bench/report.py (the script's folder)

from rcan_rtps.governance.audit import AuditEvent, AuditLog, AuditRecord, verify_bytes

SECTION = "## Audit log"
BASELINE_CASE = "append, 1 writer, fsync per entry (baseline)"


def record(i: int) -> AuditRecord:
    return AuditRecord(
        event=AuditEvent.COMMAND_DISPATCHED, principal="planner-agent", role="USER",
        message_id=f"{i:08d}-58cd-4bd1-9a51-2f1b2e1d33a0", action_type="move",
        params={"linear_x": 0.5, "angular_z": 0.1}, applied={"linear_x": 0.5, "angular_z": 0.1},
        outcome="executed", ros2_topic="/robot1/cmd_vel",
        ai={"provider": "openai", "model": "gpt-4o", "confidence": 0.94, "thought_id": "t"},
    )


async def append_rate(dir_: Path, n: int, *, concurrency: int, group_commit: bool
                      ) -> tuple[float, float]:
    """Durable entries per second, `concurrency` writers each awaiting its own append, and
    the process's CPU µs per entry (every thread's: the loop's and the writer's)."""
    path = dir_ / f"append-{concurrency}-{group_commit}.jsonl"
    log = await AuditLog.open(path, dir_ / "bench.key", group_commit=group_commit)
    per_writer = n // concurrency

    async def writer(w: int) -> None:
        for i in range(per_writer):
            await log.append(record(w * per_writer + i))

    start, cpu = time.perf_counter(), time.process_time()
    await asyncio.gather(*(writer(w) for w in range(concurrency)))
    elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
    await log.close()
    entries = per_writer * concurrency
    return entries / elapsed, cpu / entries * 1e6


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


Row = tuple[str, float, float | None]  # case, entries/s, CPU µs per entry (appends only)


async def measure(dir_: Path, n: int) -> list[Row]:
    rows: list[Row] = [(BASELINE_CASE, *await append_rate(dir_, n // 4, concurrency=1,
                                                          group_commit=False))]
    for conc in (16, 64):
        for group in (False, True):
            label = f"append, {conc} writers, {'group commit' if group else 'fsync per entry'}"
            rows.append((label, *await append_rate(dir_, n, concurrency=conc,
                                                   group_commit=group)))
    chain = dir_ / "append-64-True.jsonl"
    log = await AuditLog.open(chain, dir_ / "bench.key")
    pub = log.public_key
    await log.close()
    rows.append(("verify, hashes and Ed25519 signatures", verify_rate(chain, pub), None))
    rows.append(("verify, hashes only", verify_rate(chain, None), None))
    return rows


def child(args: argparse.Namespace) -> int:
    """One side's measurement (the rcan_rtps on PYTHONPATH), as JSON on stdout."""
    import rcan_rtps  # which tree's: the parent checks it is the side's

    args.dir.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(dir=args.dir))
    try:
        rows = asyncio.run(measure(work, args.entries))
        fs = filesystem(work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(json.dumps({"module": rcan_rtps.__file__, "fs": fs,
                      "rows": [list(row) for row in rows]}))
    return 0


def run_side(src: Path, args: argparse.Namespace) -> dict[str, Any]:
    """Runs `child` in a fresh interpreter whose rcan_rtps is the one under `src`."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(src), str(Path(__file__).parent)]))
    out = subprocess.run([sys.executable, __file__, "--child", "--entries", str(args.entries),
                          "--dir", str(args.dir)], env=env, capture_output=True, text=True,
                         check=True)
    result: dict[str, Any] = json.loads(out.stdout.splitlines()[-1])
    if not Path(result["module"]).resolve().is_relative_to(src.resolve()):
        raise SystemExit(f"side {src} imported rcan_rtps from {result['module']}")
    return result


Samples = dict[str, dict[str, list[tuple[float, float | None]]]]  # side → case → per round


def interleaved(sides: dict[str, Path], args: argparse.Namespace) -> tuple[Samples, str]:
    """Each side's (rate, CPU) per case, over `--rounds` rounds, each round in the other
    order (so that neither side always runs on a cache or disk the other warmed)."""
    samples: Samples = {name: {} for name in sides}
    fs = "unknown"
    names = list(sides)
    for round_ in range(args.rounds):
        for name in names if round_ % 2 == 0 else names[::-1]:
            result = run_side(sides[name], args)
            fs = result["fs"]
            for label, rate, cpu in result["rows"]:
                samples[name].setdefault(label, []).append((rate, cpu))
    return samples, fs


def median_of(values: list[float | None]) -> float | None:
    present = [v for v in values if v is not None]
    return statistics.median(present) if present else None


def cpu_cell(value: float | None) -> str:
    return "—" if value is None else f"{value:.0f}"


def markdown(samples: Samples, fs: str, args: argparse.Namespace) -> str:
    after = {label: (statistics.median(r for r, _ in runs), median_of([c for _, c in runs]))
             for label, runs in samples["after"].items()}
    base = after[BASELINE_CASE][0]
    head = [SECTION, "",
            f"`bench/audit.py`: {args.entries} entries per case, on {fs}, same machine, same run; "
            f"each figure is the median of {args.rounds} runs, each in a fresh interpreter. "
            "Durable = write + fsync (F_FULLFSYNC on macOS) completed before `append` returns. "
            "Ratio = rate / the single-writer fsync-per-entry baseline; higher is better. "
            "CPU = the process's CPU time (all threads) per entry appended, in µs: the part of "
            "the cost that is ours, which a busy disk does not blur as it blurs the rates."]
    if args.baseline_ref is None:
        return "\n".join([*head, "", "| case | entries/s | CPU µs/entry | ratio |",
                          "|---|---|---|---|",
                          *(f"| {label} | {rate:,.0f} | {cpu_cell(cpu)} "
                            f"| {ratio(label, rate, base)} |"
                            for label, (rate, cpu) in after.items())])
    head[-1] += (f" Before = `{args.baseline_ref}` (a temporary git worktree, same interpreter "
                 "and packages), run alternately with this tree (after), each round in the "
                 "other order; after / before is the median of the rounds' own ratios (each "
                 "round runs both sides back to back), with their lowest and highest.")
    rows = []
    for label, (rate, cpu) in after.items():
        before = samples["before"][label]
        paired = sorted(a[0] / b[0] for a, b in zip(samples["after"][label], before,
                                                    strict=True))
        rows.append(f"| {label} | {statistics.median(r for r, _ in before):,.0f} | {rate:,.0f} "
                    f"| {statistics.median(paired):.2f} ({paired[0]:.2f}–{paired[-1]:.2f}) "
                    f"| {cpu_cell(median_of([c for _, c in before]))} / {cpu_cell(cpu)} "
                    f"| {ratio(label, rate, base)} |")
    return "\n".join([
        *head, "", f"| case | before (`{args.baseline_ref}`) entries/s | after entries/s "
        "| after / before (range) | CPU µs/entry before / after | ratio (after) |",
        "|---|---|---|---|---|---|", *rows])


def ratio(label: str, rate: float, base: float) -> str:
    return "—" if label.startswith("verify") else f"{rate / base:.1f}×"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--entries", type=int, default=2000)
    parser.add_argument("--dir", type=Path, default=ROOT / ".cache" / "bench-audit",
                        help="where to write (a real disk: tmpfs makes fsync free)")
    parser.add_argument("--baseline-ref", default=None,
                        help="also measure this git ref's audit log (before), alternately")
    parser.add_argument("--rounds", type=int, default=5, help="runs per side (median)")
    parser.add_argument("--no-write", action="store_true", help="print only")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        return child(args)
    with contextlib.ExitStack() as stack:
        sides = {"after": ROOT / "src"}
        if args.baseline_ref is not None:
            sides = {"before": stack.enter_context(baseline_tree(args.baseline_ref)), **sides}
        load_before = os.getloadavg()
        samples, fs = interleaved(sides, args)
        load_after = os.getloadavg()
    text = markdown(samples, fs, args) + (
        "\n\nThe machine's load average (1 / 5 min) was {:.2f} / {:.2f} as the runs began and "
        "{:.2f} / {:.2f} as they ended.".format(*load_before[:2], *load_after[:2]))
    print(text)
    if not args.no_write:
        write_section(SECTION, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
