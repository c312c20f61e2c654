"""Safety-kernel benchmarks, all in one run, each against a baseline measured in the same run.

1. E-stop latency, p50/p99, to the robot (rclpy receives `emergency_stop: true`) and to the
   caller (HTTP reply), idle versus under load: 500 clients sending commands plus 6 concurrent
   `GET /api/audit/verify` on a log of `--log-entries` entries. Target: p99 ≤ 50 ms for both.
2. Memory: bridge RSS before and after 100 k governed commands. Target: growth ≤ 5 MB.
3. Start-up: exec → ready line with 0, 10 k and 100 k audit entries. Target: ≤ 1 s each (the
   start-up after a clean stop; a full re-verification, no checkpoint, is shown for reference).

The load runs in its own process (so the prober's event loop is not the one that is loaded).
DDS runs here, so run it in a private network namespace (as root):
    scripts/netns .venv/bin/python bench/safety.py
Writes the `## Safety kernel` section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import aiohttp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from e2e import ROOT, TOKEN, BridgeProcess, pct, rss_mb, verdict
from oracle.client import RclpyOracle
from report import write_section

from rcan_rtps.governance import AuditEvent, AuditLog, AuditRecord
from rcan_rtps.governance.audit import checkpoint_path

HEADERS = {"Authorization": f"Bearer {TOKEN}"}
ESTOP_TOPIC = "/bench/emergency_stop"


# -- load (runs in a child process: `bench/safety.py --load URL ...`) --------------------------
async def load(url: str, clients: int, verifiers: int, seconds: float, commands: int) -> None:
    """Commands from `clients` keep-alive clients and `verifiers` looping audit verifications,
    for `seconds` or until `commands` commands were answered; prints a JSON summary."""
    done = asyncio.Event()
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


# -- measurements ----------------------------------------------------------------------------
async def estop_latency(url: str, oracle: RclpyOracle, rounds: int) -> tuple[list[float],
                                                                                list[float]]:
    """(ms to the robot, ms to the caller) for `rounds` e-stops, each cleared afterwards."""
    robot, caller = [], []
    async with aiohttp.ClientSession(headers=HEADERS) as http:
        for _ in range(rounds):
            oracle.call("take", topic=ESTOP_TOPIC)
            sent = time.monotonic_ns()
            async with http.post(f"{url}/api/command", json={"action": "estop"}) as resp:
                await resp.read()
                assert resp.status == 200, await resp.text()
            caller.append((time.monotonic_ns() - sent) / 1e6)
            arrived = await _arrival(oracle, True)
            robot.append((arrived - sent) / 1e6)
            async with http.post(f"{url}/api/command", json={"action": "clear_estop"}) as resp:
                assert resp.status == 200, await resp.text()
            await _arrival(oracle, False)
            await asyncio.sleep(0.05)
    return robot, caller


async def _arrival(oracle: RclpyOracle, value: bool, timeout: float = 30.0) -> int:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for arrived, got in oracle.call("take", topic=ESTOP_TOPIC):
            if got is value:
                return int(arrived)
        await asyncio.sleep(0.002)
    raise TimeoutError(f"emergency_stop={value} never reached the robot")


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


async def main(args: argparse.Namespace) -> int:
    with RclpyOracle(args.oracle, "bench_robot", "/bench", domain_id=77,
                     env={"RCAN_ORACLE_EXECUTOR": "single"}) as oracle:
        oracle.call("subscribe", topic="/bench/cmd_vel", type="geometry_msgs/msg/Twist")
        oracle.call("subscribe_timed", topic=ESTOP_TOPIC, type="std_msgs/msg/Bool",
                    field="data")
        with tempfile.TemporaryDirectory() as tmp:
            state = Path(tmp)
            await fill_log(state, args.log_entries)
            bridge = BridgeProcess(state)
            try:
                oracle.call("wait_publishers", topic=ESTOP_TOPIC, timeout=15)
                await asyncio.sleep(1.0)
                warm = LoadProcess(bridge.url, clients=64, commands=2000)
                warm.result()
                rss_before = rss_mb(bridge.proc.pid)
                heavy = LoadProcess(bridge.url, clients=64, commands=args.commands)
                counts = heavy.result(timeout=3600)
                rss_after = rss_mb(bridge.proc.pid)
                oracle.call("take", topic="/bench/cmd_vel")
                idle_robot, idle_caller = await estop_latency(bridge.url, oracle, args.rounds)
                loader = LoadProcess(bridge.url, clients=500, verifiers=args.verify_readers)
                await asyncio.sleep(2.0)  # the load is on
                busy_robot, busy_caller = await estop_latency(bridge.url, oracle, args.rounds)
                loader.proc.terminate()
                loader.proc.wait(60)
                oracle.call("take", topic="/bench/cmd_vel")
            finally:
                bridge.stop()
    starts = await startup_times(args.start_sizes)

    def row(name: str, idle: list[float], busy: list[float]) -> str:
        i50, i99, b50, b99 = (pct(idle, 0.5), pct(idle, 0.99), pct(busy, 0.5), pct(busy, 0.99))
        return (f"| e-stop → {name} | {i50:.1f} / {i99:.1f} ms | {b50:.1f} / {b99:.1f} ms | "
                f"{b99 / i99:.1f}× | p99 ≤ 50 ms | {verdict(b99 <= 50 and i99 <= 50)} |")

    growth = rss_after - rss_before
    lines = [
        "## Safety kernel", "",
        f"`bench/safety.py` (same machine, same run). E-stop: {args.rounds} e-stops each idle "
        f"and under load (500 clients sending `move` plus 6 looping `GET /api/audit/verify` on "
        f"a {args.log_entries:,}-entry log, from a separate load process; after the memory "
        "run); each e-stop is "
        "cleared before the next. The robot is an rclpy Jazzy node; the bridge is "
        "`rcan-rtps run` in its own process. All processes share 2 cores.", "",
        "| measure | idle p50 / p99 | under load p50 / p99 | load / idle (p99) | target | "
        "verdict |",
        "|---|---|---|---|---|---|",
        row("robot (rclpy receives `true`)", idle_robot, busy_robot),
        row("caller (HTTP reply)", idle_caller, busy_caller),
        "",
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
    report = "\n".join(lines)
    write_section("## Safety kernel", report)
    print(report)
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--oracle", type=Path, default=ROOT / ".cache/ros-jazzy/bin/python")
    parser.add_argument("--rounds", type=int, default=100)
    parser.add_argument("--log-entries", type=int, default=30_000)
    parser.add_argument("--commands", type=int, default=100_000)
    parser.add_argument("--verify-readers", type=int, default=6)
    parser.add_argument("--start-sizes", type=int, nargs="+", default=[0, 10_000, 100_000])
    parser.add_argument("--load", metavar="URL", help=argparse.SUPPRESS)
    parser.add_argument("--clients", type=int, default=500, help=argparse.SUPPRESS)
    parser.add_argument("--verifiers", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--seconds", type=float, default=3600, help=argparse.SUPPRESS)
    parsed = parser.parse_args()
    if parsed.load:
        asyncio.run(load(parsed.load, parsed.clients, parsed.verifiers, parsed.seconds,
                         parsed.commands))
        sys.exit(0)
    sys.exit(asyncio.run(main(parsed)))
