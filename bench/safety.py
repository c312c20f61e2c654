"""Safety-kernel benchmarks, all in one run, each against a baseline measured in the same run.

1. E-stop latency, before vs after: the bridge of `--baseline-ref` (599eb3c, where the e-stop
   Bool was published only once the latch file and the audit entry were fsynced; a temporary
   git worktree, its src on PYTHONPATH, same interpreter) and this tree's, in alternating
   blocks. From sending `POST /api/command {"action": "estop"}` to: the rclpy robot receiving
   `emergency_stop: true` (the Bool), the robot receiving the zero Twist, and the HTTP reply
   (the caller); p50/p99 of `--rounds` e-stops each idle and under load (500 clients sending
   `move` plus 6 looping `GET /api/audit/verify` on a log of `--log-entries` entries, from a
   separate load process), each e-stop cleared before the next. Three placements of the state:
   all on the normal disk; the latch file (`safety.estop_state_path`) on a slow disk; latch
   file and audit log both on it. Target (this tree): p99 ≤ 50 ms to the robot under load on
   any disk, and to the caller on the normal disk (on the slow disk the reply waits, by design,
   for the latch file and the entry to be durable: the disk's own time is shown beside it).
2. Memory: bridge RSS before and after 100 k governed commands. Target: growth ≤ 5 MB.
3. Start-up: exec → ready line with 0, 10 k and 100 k audit entries. Target: ≤ 1 s each (the
   start-up after a clean stop; a full re-verification, no checkpoint, is shown for reference).

The slow disk is a real filesystem: `bench/slowfs.py`, a FUSE passthrough (to a directory on
the normal disk) whose every fsync/fsyncdir takes `--fsync-ms` more, one at a time. Set-up,
bench-only (never a product dependency): `ensure_fuse_tools` installs Debian's `libfuse2` with
apt-get and PyPI's `fusepy` into `.cache/bench-tools` (`pip install --target`) when missing;
mounting needs root and /dev/fuse.

The load runs in its own process (so the prober's event loop is not the one that is loaded).
DDS runs here, so run it in a private network namespace (as root):
    scripts/netns .venv/bin/python bench/safety.py
`--estop-only` runs part 1 alone and writes nothing. Otherwise writes the `## Safety kernel`
section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import ctypes.util
import json
import os
import shutil
import signal as signals
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import aiohttp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from e2e import ROOT, TOKEN, BridgeProcess, baseline_tree, pct, rss_mb, verdict
from oracle.client import RclpyOracle
from report import write_section

from rcan_rtps.governance import AuditEvent, AuditLog, AuditRecord
from rcan_rtps.governance._durable import atomic_write
from rcan_rtps.governance.audit import checkpoint_path

HEADERS = {"Authorization": f"Bearer {TOKEN}"}
ESTOP_TOPIC = "/bench/emergency_stop"
CMD_VEL = "/bench/cmd_vel"
TOOLS = ROOT / ".cache" / "bench-tools"
SLOWFS = Path(__file__).resolve().parent / "slowfs.py"
TARGET_MS = 50.0


# -- load (runs in a child process: `bench/safety.py --load URL ...`) --------------------------
async def load(url: str, clients: int, verifiers: int, seconds: float, commands: int) -> None:
    """Commands from `clients` keep-alive clients and `verifiers` looping audit verifications,
    for `seconds`, until `commands` commands were answered or until SIGTERM; prints a JSON
    summary."""
    done = asyncio.Event()
    asyncio.get_running_loop().add_signal_handler(signals.SIGTERM, done.set)
    counts = {"commands": 0, "non_2xx_4xx": 0, "verifies": 0}

    async def commander(http: aiohttp.ClientSession, k: int) -> None:
        i = 0
        while not done.is_set():
            i += 1
            body = {"action": "move", "params": {"linear_x": 0.1 + (k * 1e6 + i) * 1e-9}}
            async with http.post(f"{url}/api/command", json=body) as resp:
                await resp.read()
                counts["non_2xx_4xx"] += resp.status >= 500
            counts["commands"] += 1
            if commands and counts["commands"] >= commands:
                done.set()

    async def verifier(http: aiohttp.ClientSession) -> None:
        while not done.is_set():
            async with http.get(f"{url}/api/audit/verify") as resp:
                await resp.read()
            counts["verifies"] += 1

    async def clock() -> None:
        try:
            await asyncio.wait_for(done.wait(), seconds)
        except asyncio.TimeoutError:
            done.set()

    connector = aiohttp.TCPConnector(limit=clients + verifiers)
    timeout = aiohttp.ClientTimeout(total=None)
    async with aiohttp.ClientSession(headers=HEADERS, connector=connector,
                                     timeout=timeout) as http:
        print("loading", flush=True)
        tasks = [commander(http, k) for k in range(clients)]
        tasks += [verifier(http) for _ in range(verifiers)]
        await asyncio.gather(clock(), *tasks)
    print(json.dumps(counts), flush=True)


class LoadProcess:
    def __init__(self, url: str, *, clients: int, verifiers: int = 0, seconds: float = 3600,
                 commands: int = 0) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, __file__, "--load", url, "--clients", str(clients),
             "--verifiers", str(verifiers), "--seconds", str(seconds),
             "--commands", str(commands)], stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        assert self.proc.stdout.readline().strip() == "loading"

    def result(self, timeout: float = 600) -> dict[str, int]:
        out, _ = self.proc.communicate(timeout=timeout)
        return dict(json.loads(out.strip().splitlines()[-1]))


# -- the slow disk (bench-only tools) ---------------------------------------------------------
def ensure_fuse_tools() -> None:
    """libfuse2 (Debian) and fusepy (PyPI, into TOOLS) for bench/slowfs.py, when missing."""
    if ctypes.util.find_library("fuse") is None:
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        if subprocess.run(["apt-get", "install", "-y", "-qq", "libfuse2"], env=env).returncode:
            subprocess.run(["apt-get", "update", "-qq"], env=env, check=True)
            subprocess.run(["apt-get", "install", "-y", "-qq", "libfuse2"], env=env, check=True)
    if not (TOOLS / "fuse.py").exists():
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--target", str(TOOLS),
                        "fusepy==3.0.1"], check=True)


@dataclass(frozen=True)
class SlowDisk:
    mount: Path  # what the bridge is given
    backing: Path  # the same files, on the normal disk (templates are copied in here)


@contextlib.contextmanager
def slow_disk(root: Path, fsync_ms: float) -> Iterator[SlowDisk]:
    """bench/slowfs.py mounted at root/slow, backed by root/slow-backing."""
    disk = SlowDisk(root / "slow", root / "slow-backing")
    disk.mount.mkdir()
    disk.backing.mkdir()
    log = root / "slowfs.log"
    with log.open("w") as out:
        proc = subprocess.Popen([sys.executable, str(SLOWFS), str(disk.backing), str(disk.mount),
                                 "--fsync-ms", str(fsync_ms)], stdout=out, stderr=out)
    try:
        deadline = time.monotonic() + 15
        while not os.path.ismount(disk.mount):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the slow disk did not mount: {log.read_text()}")
            time.sleep(0.05)
        yield disk
    finally:
        subprocess.run(["umount", str(disk.mount)], check=False)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def latch_write_ms(directory: Path, n: int = 20) -> list[float]:
    """ms per latch-file write as the bridge makes it (atomic_write: write, fsync, rename,
    fsync of the directory) in `directory`."""
    path, times = directory / "floor.state", []
    for _ in range(n):
        started = time.perf_counter()
        atomic_write(path, b'{"latched":true,"by":"bench","at_ms":0}')
        times.append((time.perf_counter() - started) * 1e3)
    path.unlink()
    return times


# -- e-stop latency ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Placement:
    name: str
    latch_slow: bool
    audit_slow: bool


PLACEMENTS = (
    Placement("normal disk", latch_slow=False, audit_slow=False),
    Placement("latch file on the slow disk", latch_slow=True, audit_slow=False),
    Placement("latch file + audit log on the slow disk", latch_slow=True, audit_slow=True),
)
SIGNALS = ("Bool", "zero", "caller")


@dataclass
class Samples:
    """ms per e-stop, one list per signal: Bool and zero Twist at the robot, reply."""

    by_signal: dict[str, list[float]] = field(
        default_factory=lambda: {signal: [] for signal in SIGNALS})

    def add(self, bool_ms: float, zero_ms: float, caller_ms: float) -> None:
        for signal, ms in zip(SIGNALS, (bool_ms, zero_ms, caller_ms), strict=True):
            self.by_signal[signal].append(ms)


@dataclass(frozen=True)
class Version:
    label: str
    src: Path | None  # None: this tree
    template: Path  # a filled audit log written by this version's own code


async def estop_round(http: aiohttp.ClientSession, url: str, oracle: RclpyOracle,
                      samples: Samples) -> None:
    """One e-stop, timed three ways, then cleared (its Bool `false` received)."""
    oracle.call("take", topic=ESTOP_TOPIC)
    oracle.call("take", topic=CMD_VEL)
    sent = time.monotonic_ns()
    async with http.post(f"{url}/api/command", json={"action": "estop"}) as resp:
        await resp.read()
        assert resp.status == 200, await resp.text()
    caller = (time.monotonic_ns() - sent) / 1e6
    arrived = await _arrivals(oracle, sent, {ESTOP_TOPIC: True, CMD_VEL: 0.0})
    samples.add((arrived[ESTOP_TOPIC] - sent) / 1e6, (arrived[CMD_VEL] - sent) / 1e6, caller)
    cleared = time.monotonic_ns()
    async with http.post(f"{url}/api/command", json={"action": "clear_estop"}) as resp:
        assert resp.status == 200, await resp.text()
    await _arrivals(oracle, cleared, {ESTOP_TOPIC: False})
    await asyncio.sleep(0.05)


async def _arrivals(oracle: RclpyOracle, since: int, wanted: dict[str, object],
                    timeout: float = 30.0) -> dict[str, int]:
    """When each topic's first message with the wanted value (Bool data, Twist linear.x)
    reached rclpy at or after `since` (monotonic ns, same host)."""
    found: dict[str, int] = {}
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for topic, value in wanted.items():
            for arrived, got in oracle.call("take", topic=topic):
                if topic not in found and got == value and arrived >= since:
                    found[topic] = int(arrived)
        if len(found) == len(wanted):
            return found
        await asyncio.sleep(0.002)
    raise TimeoutError(f"never reached the robot: {set(wanted) - set(found)}")


def place_state(run: Path, version: Version, placement: Placement,
                slow: SlowDisk | None) -> tuple[Path, Path]:
    """Copies the version's filled log where `placement` says; (audit dir, latch file path)
    as the bridge is to see them. Slow-disk files are copied in through the backing dir."""
    def on(slow_side: bool) -> tuple[Path, Path]:  # (as the bridge sees it, where to copy)
        if not slow_side:
            return run, run
        assert slow is not None
        return slow.mount / run.name, slow.backing / run.name

    (audit_dir, audit_copy), (latch_dir, latch_copy) = on(placement.audit_slow), on(
        placement.latch_slow)
    for directory in (run, audit_copy, latch_copy):
        directory.mkdir(parents=True, exist_ok=True)
    for item in version.template.iterdir():
        if item.name != "estop.state":
            shutil.copy2(item, audit_copy / item.name)
    shutil.copy2(version.template / "estop.state", latch_copy / "estop.state")
    return audit_dir, latch_dir / "estop.state"


async def estop_block(root: Path, version: Version, placement: Placement,
                      slow: SlowDisk | None, oracle: RclpyOracle, rounds: int,
                      idle: Samples, busy: Samples, loads: list[dict[str, int]],
                      unclean: list[str]) -> None:
    """One bridge of `version`: `rounds` e-stops idle, then `rounds` under load."""
    run = root / f"run-{len(list(root.glob('run-*')))}"
    audit_dir, latch = place_state(run, version, placement, slow)
    bridge = BridgeProcess(run, version.src, audit_dir=audit_dir, latch_path=latch)
    try:
        oracle.call("wait_publishers", topic=ESTOP_TOPIC, timeout=15)
        oracle.call("wait_publishers", topic=CMD_VEL, timeout=15)
        await asyncio.sleep(1.0)
        LoadProcess(bridge.url, clients=64, commands=500).result()  # warm-up
        async with aiohttp.ClientSession(headers=HEADERS) as http:
            # The warm-up's last move is still streaming: stop it, so the idle e-stops find
            # the robot at rest (an e-stop ends a stream at once: its zero would not be the
            # one the idle rows are about).
            async with http.post(f"{bridge.url}/api/command", json={"action": "stop"}) as resp:
                assert resp.status == 200, await resp.text()
            await asyncio.sleep(1.0)
            for _ in range(rounds):
                await estop_round(http, bridge.url, oracle, idle)
            loader = LoadProcess(bridge.url, clients=500, verifiers=6)
            try:
                await asyncio.sleep(2.0)  # the load is on
                for _ in range(rounds):
                    await estop_round(http, bridge.url, oracle, busy)
            finally:
                loader.proc.terminate()
                out, _ = loader.proc.communicate(timeout=60)
            if out.strip():
                loads.append(json.loads(out.strip().splitlines()[-1]))
        oracle.call("take", topic=CMD_VEL)
    finally:
        if not stop_bridge(bridge):
            unclean.append(version.label)


def stop_bridge(bridge: BridgeProcess, grace_s: float = 30.0) -> bool:
    """SIGINT, as `BridgeProcess.stop`; a bridge still running `grace_s` later is killed
    with its children (False)."""
    bridge.proc.send_signal(signals.SIGINT)
    try:
        bridge.proc.wait(timeout=grace_s)
        return True
    except subprocess.TimeoutExpired:
        children = []
        for tasks in Path(f"/proc/{bridge.proc.pid}/task").glob("*/children"):
            with contextlib.suppress(OSError):
                children += [int(pid) for pid in tasks.read_text().split()]
        for pid in [bridge.proc.pid, *children]:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signals.SIGKILL)
        bridge.proc.wait()
        return False


def filled_template(directory: Path, entries: int, src: Path | None) -> Path:
    """A log of `entries` entries written by the code of `src` (None: this tree's)."""
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(src), env.get("PYTHONPATH", "")])
    directory.mkdir(parents=True)
    subprocess.run([sys.executable, __file__, "--fill", str(directory), "--log-entries",
                    str(entries)], env=env, check=True)
    return directory


@dataclass
class EstopResults:
    samples: dict[tuple[str, str, bool], Samples]  # (version, placement, loaded)
    versions: tuple[str, str]  # (before, after) labels
    latch_floor: dict[str, list[float]]  # disk name → ms per latch-file write
    loads: list[dict[str, int]]
    machine_load: tuple[tuple[float, float], tuple[float, float]]  # loadavg at start, at end
    unclean: list[str]  # per bridge that had to be killed after SIGINT, its version


async def estop_matrix(oracle: RclpyOracle, args: argparse.Namespace) -> EstopResults:
    ensure_fuse_tools()
    load_start = os.getloadavg()[:2]
    with tempfile.TemporaryDirectory() as tmp, baseline_tree(args.baseline_ref) as base_src:
        root = Path(tmp)
        before = Version(f"before ({args.baseline_ref})", base_src,
                         filled_template(root / "template-before", args.log_entries, base_src))
        after = Version("after", None,
                        filled_template(root / "template-after", args.log_entries, None))
        samples = {(v.label, p.name, loaded): Samples() for v in (before, after)
                   for p in PLACEMENTS for loaded in (False, True)}
        loads: list[dict[str, int]] = []
        unclean: list[str] = []  # a version's label per bridge killed after SIGINT
        with slow_disk(root, args.fsync_ms) as slow:
            floor = {"normal disk": latch_write_ms(root),
                     "slow disk": latch_write_ms(slow.mount)}
            per_block = -(-args.rounds // args.blocks)
            for placement in (PLACEMENTS[i] for i in args.placements):
                for block in range(args.blocks):
                    for version in (before, after) if block % 2 == 0 else (after, before):
                        print(f"{time.strftime('%H:%M:%S')} load {os.getloadavg()[0]:.2f} "
                              f"e-stop: {version.label}, {placement.name}, block {block}",
                              flush=True)
                        await estop_block(
                            root, version, placement, slow, oracle, per_block,
                            samples[(version.label, placement.name, False)],
                            samples[(version.label, placement.name, True)], loads,
                            unclean)
    return EstopResults(samples, (before.label, after.label), floor, loads,
                        (load_start, os.getloadavg()[:2]), unclean)


def estop_report(results: EstopResults, args: argparse.Namespace) -> list[str]:
    before, after = results.versions
    names = {"Bool": "Bool `true` → robot", "zero": "zero Twist → robot",
             "caller": "reply → caller"}

    def cell(values: list[float]) -> str:
        return f"{pct(values, 0.5):.1f} / {pct(values, 0.99):.1f} ms"

    def judged(placement: Placement, signal: str, values: list[float]) -> str:
        if signal == "caller" and placement.latch_slow:
            return "— (waits for the disk, by design) | —"
        return f"p99 ≤ {TARGET_MS:g} ms | {verdict(pct(values, 0.99) <= TARGET_MS)}"

    rows = []
    for placement in (PLACEMENTS[i] for i in args.placements):
        for loaded in (False, True):
            for signal in SIGNALS:
                b = results.samples[(before, placement.name, loaded)].by_signal[signal]
                a = results.samples[(after, placement.name, loaded)].by_signal[signal]
                rows.append(f"| {placement.name} | {'500 clients' if loaded else 'idle'} | "
                            f"{names[signal]} | {cell(b)} | {cell(a)} | "
                            f"{judged(placement, signal, a)} |")
    floor = results.latch_floor
    n = len(results.samples[(after, PLACEMENTS[args.placements[0]].name, False)].by_signal["Bool"])
    commands = sum(load.get("commands", 0) for load in results.loads)
    verifies = sum(load.get("verifies", 0) for load in results.loads)
    errors = sum(load.get("non_2xx_4xx", 0) for load in results.loads)
    (load1_start, load5_start), (load1_end, load5_end) = results.machine_load
    return [
        f"E-stop latency, before vs after, from sending `POST /api/command "
        f'{{"action": "estop"}}` to the robot (an rclpy Jazzy node; arrival times from its '
        f"callbacks, same clock) receiving `emergency_stop: true` and the zero Twist, and to "
        f"the caller's HTTP reply. The bridge of `{args.baseline_ref}` (a temporary git "
        "worktree, same interpreter and packages) and this tree's, each as `rcan-rtps run` in "
        f"its own process, in {args.blocks} alternating blocks per disk; {n} e-stops per row "
        "and version, idle and then under load (500 keep-alive clients sending `move` plus 6 "
        f"looping `GET /api/audit/verify` on a {args.log_entries:,}-entry log, from a separate "
        "load process); each e-stop is cleared before the next. All processes share the "
        "machine's 2 cores.", "",
        f"The slow disk is a real filesystem: `bench/slowfs.py`, a FUSE passthrough whose every "
        f"fsync and directory fsync takes {args.fsync_ms:g} ms more, one at a time, like a "
        f"small robot computer's SD card. A latch-file write as the bridge makes it (write, "
        f"fsync, rename, fsync of the directory) took p50 / p99 {cell(floor['normal disk'])} on "
        f"the normal disk and {cell(floor['slow disk'])} on the slow one. The audit log stays "
        "on the normal disk except in the last placement.", "",
        f"| state | load | signal | before (`{args.baseline_ref}`) p50 / p99 | after p50 / p99 "
        "| target (after) | verdict |",
        "|---|---|---|---|---|---|---|",
        *rows, "",
        f"Load: {commands:,} `move` commands and {verifies} audit verifications answered over "
        f"the loaded phases ({errors} 5xx). The machine's load average (1 / 5 min) was "
        f"{load1_start:.2f} / {load5_start:.2f} as the e-stop runs began and {load1_end:.2f} / "
        f"{load5_end:.2f} as they ended. The reply waits for the latch file and the audit "
        "entry to be durable (a stop's entry is on disk by its reply): on the slow disk it "
        "cannot come before the latch-file write above, whatever the bridge does.", "",
        f"Bridges still running 30 s after SIGINT (then killed with their children), of "
        f"{len(args.placements) * args.blocks} per version: before {results.unclean.count(before)}"
        f", after {results.unclean.count(after)}.", "",
    ]


# -- memory and start-up (this tree) --------------------------------------------------------
async def fill_log(state: Path, entries: int) -> None:
    """A log of `entries` signed entries, as a bridge would leave it (checkpoint included)."""
    log = await AuditLog.open(state / "audit.jsonl", state / "audit.key",
                              ruri="rcan://registry.local/bench/rover/bench-0001")
    for start in range(0, entries, 2000):
        await asyncio.gather(*(log.append(AuditRecord(
            event=AuditEvent.COMMAND_DISPATCHED, principal="bench", role="CREATOR",
            action_type="move", params={"linear_x": i * 1e-6}, applied={"linear_x": i * 1e-6},
            outcome="executed", ros2_topic="/bench/cmd_vel"))
            for i in range(start, min(entries, start + 2000))))
    await log.close()
    (state / "estop.state").write_text('{"latched":false}')  # as a bridge leaves it


def ready_time(state: Path) -> float:
    bridge = BridgeProcess(state)
    try:
        return bridge.ready_s
    finally:
        bridge.stop()


async def startup_times(sizes: list[int]) -> list[tuple[int, float, float]]:
    """(entries, ready s after a clean stop, ready s with no checkpoint) per log size."""
    rows = []
    for size in sizes:
        with tempfile.TemporaryDirectory() as tmp:
            state = Path(tmp)
            await fill_log(state, size)
            ready_time(state)  # first start: writes the latch file, and warms the caches
            clean = ready_time(state)
            checkpoint_path(state / "audit.jsonl").unlink()
            full = ready_time(state)
            rows.append((size, clean, full))
    return rows


async def memory(oracle: RclpyOracle, commands: int) -> tuple[float, float, dict[str, int]]:
    """Bridge RSS (MB) before and after `commands` governed commands, and the load's counts."""
    with tempfile.TemporaryDirectory() as tmp:
        bridge = BridgeProcess(Path(tmp))
        try:
            oracle.call("wait_publishers", topic=CMD_VEL, timeout=15)
            await asyncio.sleep(1.0)
            LoadProcess(bridge.url, clients=64, commands=2000).result()
            oracle.call("take", topic=CMD_VEL)
            before = rss_mb(bridge.proc.pid)
            counts = LoadProcess(bridge.url, clients=64, commands=commands).result(3600)
            after = rss_mb(bridge.proc.pid)
            oracle.call("take", topic=CMD_VEL)
        finally:
            bridge.stop()
    return before, after, counts


async def main(args: argparse.Namespace) -> int:
    with RclpyOracle(args.oracle, "bench_robot", "/bench", domain_id=77,
                     env={"RCAN_ORACLE_EXECUTOR": "single"}) as oracle:
        oracle.call("subscribe_timed", topic=CMD_VEL, type="geometry_msgs/msg/Twist")
        oracle.call("subscribe_timed", topic=ESTOP_TOPIC, type="std_msgs/msg/Bool",
                    field="data")
        results = await estop_matrix(oracle, args)
        if args.raw:
            args.raw.write_text(json.dumps({" / ".join(map(str, key)): samples.by_signal
                                            for key, samples in results.samples.items()}))
        estop = estop_report(results, args)
        if args.estop_only:
            print("\n".join(estop))
            return 0
        rss_before, rss_after, counts = await memory(oracle, args.commands)
    starts = await startup_times(args.start_sizes)

    growth = rss_after - rss_before
    lines = [
        "## Safety kernel", "",
        "`bench/safety.py` (same machine, same run).", "",
        *estop,
        "| measure | before | after | growth | target | verdict |",
        "|---|---|---|---|---|---|",
        f"| bridge RSS around {counts['commands']:,} governed commands "
        f"({counts['non_2xx_4xx']} 5xx) | {rss_before:.1f} MB | "
        f"{rss_after:.1f} MB | {growth:+.1f} MB | ≤ 5 MB | {verdict(growth <= 5)} |",
        "",
        "| audit entries | exec → ready (after a clean stop) | no checkpoint (full verify) | "
        "target | verdict |",
        "|---|---|---|---|---|",
        *(f"| {size:,} | {clean:.2f} s | {full:.2f} s | ≤ 1 s | {verdict(clean <= 1.0)} |"
          for size, clean, full in starts),
        "",
    ]
    if args.note:
        lines += [args.note, ""]
    report = "\n".join(lines)
    write_section("## Safety kernel", report)
    print(report)
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--oracle", type=Path, default=ROOT / ".cache/ros-jazzy/bin/python")
    parser.add_argument("--rounds", type=int, default=100,
                        help="e-stops per version, disk and load")
    parser.add_argument("--blocks", type=int, default=2,
                        help="alternating before/after blocks per disk")
    parser.add_argument("--baseline-ref", default="599eb3c",
                        help="git ref whose bridge is the 'before' (default 599eb3c)")
    parser.add_argument("--fsync-ms", type=float, default=80.0,
                        help="what the slow disk adds to each fsync")
    parser.add_argument("--estop-only", action="store_true",
                        help="the e-stop latency alone, printed, docs untouched")
    parser.add_argument("--note", default="", help="a line added under the section")
    parser.add_argument("--placements", type=int, nargs="+", default=[0, 1, 2],
                        help="which state placements (0 normal disk, 1 latch file on the slow "
                        "disk, 2 latch file + audit log on it)")
    parser.add_argument("--raw", type=Path, help="write every e-stop sample (ms) here, JSON")
    parser.add_argument("--log-entries", type=int, default=30_000)
    parser.add_argument("--commands", type=int, default=100_000)
    parser.add_argument("--start-sizes", type=int, nargs="+", default=[0, 10_000, 100_000])
    parser.add_argument("--fill", metavar="DIR", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--load", metavar="URL", help=argparse.SUPPRESS)
    parser.add_argument("--clients", type=int, default=500, help=argparse.SUPPRESS)
    parser.add_argument("--verifiers", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--seconds", type=float, default=3600, help=argparse.SUPPRESS)
    parsed = parser.parse_args()
    if parsed.fill:
        asyncio.run(fill_log(parsed.fill, parsed.log_entries))
        sys.exit(0)
    if parsed.load:
        asyncio.run(load(parsed.load, parsed.clients, parsed.verifiers, parsed.seconds,
                         parsed.commands))
        sys.exit(0)
    sys.exit(asyncio.run(main(parsed)))
