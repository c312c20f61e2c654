"""Start time against the length of the last run: a run of N entries that crashed (no
BRIDGE_STOPPED), written with the project's own AuditLog (valid, signed), then started on.

Measured for each N: in-process `AuditLog.open` and `resume` (each in a fresh interpreter, the
log's files copied fresh each round so every round is a start after that crash) and that
interpreter's peak memory (ru_maxrss), and, with `--run`, `rcan-rtps run` from its launch to its
ready line and its peak memory then (VmHWM; run it in the network namespace: scripts/netns).
With `--unchecked`, the run's checkpoints after its first entry were never written (nor its start
points): the start verifies and replays the whole run. The result replaces the `## Start after a
long run` section of docs/benchmarks.md. Usage: .venv/bin/python bench/startup.py [--entries
10000,100000,1000000] [--rounds 3] [--run] [--unchecked] [--dir DIR] [--baseline-ref REF]:
with a baseline ref, that ref's `src` (a temporary git worktree) is measured on the same logs,
alternately with this tree's.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

from report import ROOT, baseline_tree, write_section  # bench/report.py (the script's folder)

SECTION = "## Start after a long run"
LOG_FILES = ("audit.jsonl", "audit.jsonl.checkpoint", "audit.jsonl.resume", "audit.jsonl.sth",
             "audit.jsonl.pub", "audit.key", "estop.state")
TOKEN = "bench-token-0123456789abcdef0123"
ARM = {"group": "left", "joints": ["l_shoulder", "l_elbow"], "positions": [1.0, 2.0],
       "duration_s": 2.0}
CONFIG = """\
robot:
  ruri: rcan://registry.local/bench/rover/bench-0001
bridge:
  ros2: {{namespace: /bench, node_name: rcan_bridge, domain_id: 78}}
  api:
    host: 127.0.0.1
    port: {port}
    principals: [{{name: bench, role: CREATOR, token_env: RCAN_BENCH_TOKEN}}]
  safety: {{max_linear_vel: 1.0, max_angular_vel: 1.0}}
  audit: {{path: {audit}/audit.jsonl, key_path: {audit}/audit.key}}
"""

# -- writing a run (a child process, killed in effect: it exits without closing the log) ----

WRITER = r"""
import asyncio, os, sys, uuid
sys.path.insert(0, sys.argv[3])
from startup import records
from rcan_rtps.governance.audit import AuditLog

async def main(path, n, unchecked):
    log = await AuditLog.open(path, os.path.join(os.path.dirname(path), "audit.key"))
    # Start points, as Governor.from_config has them written (not where checkpoints fail).
    if not unchecked and hasattr(log, "on_checkpoint"):
        import functools
        from pathlib import Path
        from rcan_rtps.governance.governor import _write_start_point
        log.on_checkpoint(functools.partial(_write_start_point, Path(path), log.public_key,
                                            log.sign_resume_point))
    run = records(n)
    await log.append(next(run))
    if unchecked:  # the checkpoint after it is the last one written
        await log.checkpoint()
        with open(path + ".checkpoint", "rb") as f:
            first = f.read()
    batch = []
    for record in run:
        batch.append(log.append(record))
        if len(batch) == 64:
            await asyncio.gather(*batch)
            batch = []
    await asyncio.gather(*batch)
    if unchecked:  # the later checkpoints were never written
        with open(path + ".checkpoint", "wb") as f:
            f.write(first)
    os._exit(0)  # a crash: no BRIDGE_STOPPED, no closing checkpoint

asyncio.run(main(sys.argv[1], int(sys.argv[2]), sys.argv[4] == "1"))
"""


def records(n: int) -> Any:
    """A run of `n` entries: its BRIDGE_STARTED, then velocity streams that end, arm
    trajectories, goals that finish, and a stop every 100 entries (a start after it has
    nothing to take back, so the ready line waits for no robot)."""
    from rcan_rtps.governance.audit import AuditEvent, AuditRecord

    yield AuditRecord(event=AuditEvent.BRIDGE_STARTED, params={"estop_latched": False,
                                                               "locks": {}})
    i = 1
    while i < n:
        kind = i % 100
        if kind == 99 or i == n - 1:
            yield _command(f"stop-{i}", "stop", {}, "/bench/cmd_vel", principal="ops")
        elif kind % 4 == 0:
            yield _command(f"move-{i}", "move", {"linear_x": 0.2, "angular_z": 0.1},
                           "/bench/cmd_vel")
        elif kind % 4 == 1:
            yield AuditRecord(event=AuditEvent.STREAM_ENDED, message_id=f"move-{i - 1}",
                              params={"reason": "ended"})
        elif kind % 4 == 2:
            yield _command(f"arm-{i}", "arm_joint", ARM, "/bench/left_arm/joint_trajectory")
        else:
            goal_id = str(uuid.UUID(int=i))
            yield _command(f"nav-{i}", "navigate", {"x": 1.0, "y": 2.0, "yaw": 0.0},
                           "/bench/navigate_to_pose", goal_id=goal_id)
            i += 1
            yield AuditRecord(event=AuditEvent.GOAL_FINISHED, message_id=f"nav-{i - 1}",
                              params={"goal_id": goal_id}, outcome="succeeded")
        i += 1


def _command(message_id: str, action: str, params: dict[str, Any], topic: str, *,
             principal: str = "planner", goal_id: str | None = None) -> Any:
    from rcan_rtps.governance.audit import AuditEvent, AuditRecord

    return AuditRecord(event=AuditEvent.COMMAND_DISPATCHED, principal=principal, role="USER",
                       message_id=message_id, action_type=action, params=params,
                       applied=params, outcome="executed", ros2_topic=topic, goal_id=goal_id)


def write_run(directory: Path, n: int, src: Path, *, unchecked: bool = False) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(src), os.environ.get(
        "PYTHONPATH", "")])}
    subprocess.run([sys.executable, "-c", WRITER, str(directory / "audit.jsonl"), str(n),
                    str(Path(__file__).parent), "1" if unchecked else "0"], check=True, env=env)


def fresh_copy(written: Path, into: Path) -> Path:
    """The crashed run's files as it left them (a start appends to them)."""
    shutil.rmtree(into, ignore_errors=True)
    into.mkdir(parents=True)
    for name in LOG_FILES:
        if (written / name).exists():
            shutil.copy2(written / name, into / name)
    return into


# -- measuring a start -----------------------------------------------------------------------

IN_PROCESS = r"""
import asyncio, json, resource, sys, time
from pathlib import Path

async def main(directory):
    from rcan_rtps.governance.audit import AuditLog
    from rcan_rtps.governance import resume as replay
    path = Path(directory) / "audit.jsonl"
    started = time.perf_counter()
    log = await AuditLog.open(path, Path(directory) / "audit.key")
    opened = time.perf_counter()
    kwargs = {"pubkey": log.public_key} if "pubkey" in replay.resume.__code__.co_varnames else {}
    found = replay.resume(path, **kwargs)
    resumed = time.perf_counter()
    times = {"open_s": opened - started, "resume_s": resumed - opened,
             "start_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
    if hasattr(replay, "write_point"):  # what the running bridge does at each checkpoint
        from rcan_rtps.governance.audit import checkpoint_path, read_checkpoint
        cp = read_checkpoint(checkpoint_path(path), log.public_key)
        before_point = time.perf_counter()
        replay.write_point(path, cp, log.public_key, log.sign_resume_point)
        times["point_s"] = time.perf_counter() - before_point
    await log.close()
    assert found.crashed and not found.left, found
    print(json.dumps(times))

asyncio.run(main(sys.argv[1]))
"""


def in_process(directory: Path, src: Path) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(src)}
    out = subprocess.run([sys.executable, "-c", IN_PROCESS, str(directory)], check=True,
                         env=env, capture_output=True, text=True)
    result: dict[str, float] = json.loads(out.stdout)
    return result


def run_to_ready(directory: Path, src: Path) -> tuple[float, float]:
    """Seconds from launching `rcan-rtps run` to its ready line, and its peak memory (MB) then."""
    config = directory / "bench.rcan.yaml"
    config.write_text(CONFIG.format(audit=directory, port=free_port()))
    env = {**os.environ, "PYTHONPATH": str(src), "RCAN_BENCH_TOKEN": TOKEN}
    started = time.monotonic()
    with (directory / "bridge.log").open("w") as log:
        proc = subprocess.Popen([sys.executable, "-m", "rcan_rtps", "run", "--config",
                                 str(config), "--no-mdns", "--localhost"],
                                stdout=subprocess.PIPE, stderr=log, text=True, env=env)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    ready = time.monotonic() - started
    peak_mb = _peak_mb(proc.pid)
    proc.send_signal(2)
    proc.wait(timeout=60)
    if not re.match(r"rcan-rtps ready api=", line):
        raise RuntimeError(f"bridge did not start: {line}{(directory / 'bridge.log').read_text()}")
    return ready, peak_mb


def _peak_mb(pid: int) -> float:
    """A running process's peak resident memory so far (VmHWM), in MB."""
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmHWM for {pid}")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Side:
    def __init__(self, name: str, src: Path) -> None:
        self.name, self.src = name, src
        self.samples: dict[tuple[int, str], list[float]] = {}

    def add(self, n: int, what: str, value: float) -> None:
        self.samples.setdefault((n, what), []).append(value)

    def median(self, n: int, what: str) -> float | None:
        values = self.samples.get((n, what))
        return statistics.median(values) if values else None


def measure(args: argparse.Namespace, sides: list[Side], base: Path) -> dict[int, int]:
    sizes: dict[int, int] = {}
    for n in args.entries:
        written = base / f"run-{n}"
        write_run(written, n, sides[-1].src, unchecked=args.unchecked)
        sizes[n] = (written / "audit.jsonl").stat().st_size
        for r in range(args.rounds):
            for side in sides if r % 2 == 0 else reversed(sides):
                copy = fresh_copy(written, base / "start")
                for what, value in in_process(copy, side.src).items():
                    side.add(n, what, value)
                if args.run:
                    ready, peak_mb = run_to_ready(fresh_copy(written, base / "start"), side.src)
                    side.add(n, "ready_s", ready)
                    side.add(n, "ready_mb", peak_mb)
        shutil.rmtree(written)
        print(n, {s.name: {k[1]: round(statistics.median(v), 4) for k, v in s.samples.items()
                           if k[0] == n} for s in sides}, flush=True)
    return sizes


def report(args: argparse.Namespace, sides: list[Side], sizes: dict[int, int]) -> str:
    whats = [("open_s", "`AuditLog.open`", "s"), ("resume_s", "`resume`", "s"),
             ("start_mb", "open + resume, peak", "MB"), ("point_s", "a start point written", "s")]
    if args.run:
        whats += [("ready_s", "`run` → ready line", "s"), ("ready_mb", "`run`, peak", "MB")]
    head = "| entries of the last run | log size |" + "".join(
        f" {label} {side.name} ({unit}) |" for _, label, unit in whats for side in sides)
    rows = [head, "|" + "---|" * (2 + len(whats) * len(sides))]
    for n in args.entries:
        cells = [f"{n:,}", f"{sizes[n] / 1e6:.0f} MB"]
        for what, _, unit in whats:
            for side in sides:
                value = side.median(n, what)
                cells.append("—" if value is None else f"{value:.0f}" if unit == "MB"
                             else f"{value:.3f}")
        rows.append("| " + " | ".join(cells) + " |")
    load = os.getloadavg()
    return "\n".join([
        SECTION, "",
        "`bench/startup.py`: a run of N entries written with the project's `AuditLog` (signed, "
        "chained; a BRIDGE_STARTED, then velocity streams that end, arm trajectories, goals "
        "that finish, a stop every 100 entries) that crashed (its writer exits without "
        "closing the log: no BRIDGE_STOPPED, no closing checkpoint"
        + ("; nor were its checkpoints after its first entry written, nor its start points: "
           "the start verifies and replays the whole run" if args.unchecked else "")
        + "); each start is made on a "
        "fresh copy of its files (warm page cache), in a fresh interpreter. `AuditLog.open`: "
        "the lock, the check of what the audit checkpoint does not cover, the tree head; "
        "`resume`: the replay of the last run for the e-stop latch, the locks and the motion "
        "a crash left running; peak: the most resident memory of the interpreter doing both "
        "(ru_maxrss), and of `run` at its ready line (VmHWM); `run` → ready line: `rcan-rtps "
        "run --no-mdns --localhost` from launch to "
        "its ready line (a DDS participant in a private network namespace); a start point "
        "written: what the running bridge does on its audit writer thread at each checkpoint "
        "(every 1 000 entries), `resume.write_point` from the crashed run's last point (up to "
        "~1 000 entries before the end) to the end. Medians of "
        f"{args.rounds} rounds, sides alternating.", "",
        *rows, "",
        f"The machine's load average (1 / 5 min) was {load[0]:.2f} / {load[1]:.2f} as the "
        "runs ended.",
    ])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--entries", default="10000,100000,1000000",
                        type=lambda s: [int(x) for x in s.split(",")])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--run", action="store_true", help="also `run` to its ready line")
    parser.add_argument("--unchecked", action="store_true",
                        help="the run's checkpoints after its first entry were not written")
    parser.add_argument("--dir", type=Path, default=None)
    parser.add_argument("--baseline-ref", default=None)
    parser.add_argument("--no-write", action="store_true", help="print, leave the doc alone")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(dir=args.dir, prefix="rcan-startup-") as tmp:
        after = Side("after" if args.baseline_ref else "", ROOT / "src")
        if args.baseline_ref:
            with baseline_tree(args.baseline_ref) as before_src:
                sides = [Side(f"before (`{args.baseline_ref}`)", before_src), after]
                sizes = measure(args, sides, Path(tmp))
        else:
            sides = [after]
            sizes = measure(args, sides, Path(tmp))
    markdown = report(args, sides, sizes)
    print(markdown)
    if not args.no_write:
        write_section(SECTION, markdown)


if __name__ == "__main__":
    main()
