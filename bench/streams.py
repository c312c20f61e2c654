"""Velocity-stream period jitter (issue 11), against a baseline measured in the same run.

A held `move` streams its Twist at `cmd_rate_hz`; an rclpy Jazzy subscriber timestamps every
arrival. Achieved rate = arrival intervals per second, against `cmd_rate_hz` (here, not in the
tests: they check counts, never wall-clock rates). Jitter = |arrival interval − period|,
p50/p99, and the longest gap (what a robot's command timeout, 0.5 s for ros2_control's diff
drive, has to tolerate). At 20 Hz and 100 Hz, idle and while 100 keep-alive clients load the
API with governed commands (moves of a lower priority, each refused and audited: they go
through the whole governor without touching the stream under test). Baseline: a plain asyncio
timer loop (`loop.call_at`, same schedule) writing the same Twist with cyclonedds to the same
subscriber, in its own process, during the same idle and loaded phases.

DDS runs here, so run it in a private network namespace (as root):
    scripts/netns .venv/bin/python bench/streams.py [--oracle .cache/ros-jazzy/bin/python]
Writes the `## Velocity streams` section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import aiohttp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from e2e import DOMAIN, ROOT, free_port, pct, verdict
from oracle.client import RclpyOracle
from report import write_section

from rcan_rtps.ros.participant import RosNode

TOKEN, LOADER_TOKEN = "bench-token-0123456789abcdef0123", "load-token-0123456789abcdef01234"
VALUE = 0.5
MAX_GAP_S = 0.25  # half a 0.5 s command timeout
CONFIG = """\
robot:
  ruri: rcan://registry.local/bench/rover/bench-0001
bridge:
  ros2: {{namespace: /bench, node_name: rcan_bridge, domain_id: {domain}, cmd_rate_hz: {rate},
         match_timeout_s: 15}}
  api:
    host: 127.0.0.1
    port: {port}
    principals:
      - {{name: bench, role: USER, token_env: RCAN_BENCH_TOKEN}}
      - {{name: loader, role: CREATOR, token_env: RCAN_LOADER_TOKEN}}
  safety: {{max_linear_vel: 1.0, max_angular_vel: 1.0, session_timeout_s: 600}}
  motion: {{principal_priorities: {{bench: 10, loader: 0}}}}
  audit: {{path: {state}/audit.jsonl, key_path: {state}/audit.key}}
"""


# -- child processes: `--load URL` and `--baseline RATE` --------------------------------------
async def load(url: str, clients: int) -> None:
    """`clients` keep-alive clients sending lower-priority moves until terminated."""
    headers = {"Authorization": f"Bearer {LOADER_TOKEN}"}

    async def client(http: aiohttp.ClientSession, k: int) -> None:
        i = 0
        while True:
            i += 1
            body = {"action": "move", "params": {"linear_x": 0.1 + (k * 1e6 + i) * 1e-9}}
            async with http.post(f"{url}/api/command", json=body) as resp:
                await resp.read()

    connector = aiohttp.TCPConnector(limit=clients)
    async with aiohttp.ClientSession(headers=headers, connector=connector) as http:
        print("loading", flush=True)
        await asyncio.gather(*(client(http, k) for k in range(clients)))


async def baseline(rate_hz: float, seconds: float) -> None:
    """The same Twist on the same schedule as a stream, from a bare timer loop."""
    with RosNode("floor", "/floor", domain_id=DOMAIN) as node:
        pub = node.create_publisher("cmd_vel", "geometry_msgs/msg/Twist")
        await pub.wait_for_subscribers(1, timeout=15)
        await asyncio.sleep(1.0)
        vec = node.types.struct("geometry_msgs/msg/Vector3")
        twist = node.types.struct("geometry_msgs/msg/Twist")
        loop, period, done = asyncio.get_running_loop(), 1.0 / rate_hz, asyncio.Event()
        end = loop.time() + seconds

        def tick(due: float) -> None:
            pub.publish(twist(linear=vec(VALUE, 0.0, 0.0), angular=vec(0.0, 0.0, 0.0)))
            now = loop.time()
            if now >= end:
                done.set()
                return
            nxt = max(due + period, now + period / 2)
            loop.call_at(nxt, tick, nxt)

        print("streaming", flush=True)
        tick(loop.time())
        await done.wait()


# -- the run --------------------------------------------------------------------------------
class Child:
    """This script in a child process (`args`), once it printed `ready_word`."""

    def __init__(self, *args: str, ready_word: str) -> None:
        self.proc = subprocess.Popen([sys.executable, __file__, *args], stdout=subprocess.PIPE,
                                     text=True, env={**os.environ, "ROS_DOMAIN_ID": str(DOMAIN)})
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if ready_word not in line:
            raise RuntimeError(f"{args}: {line}")

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(60)


class Bridge:
    def __init__(self, state: Path, rate_hz: float) -> None:
        config = state / f"streams-{rate_hz:g}.rcan.yaml"
        config.write_text(CONFIG.format(domain=DOMAIN, rate=rate_hz, port=free_port(),
                                        state=state))
        env = {**os.environ, "RCAN_BENCH_TOKEN": TOKEN, "RCAN_LOADER_TOKEN": LOADER_TOKEN,
               "ROS_DOMAIN_ID": str(DOMAIN)}
        with (state / "bridge.log").open("a") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "rcan_rtps", "run", "--config", str(config)],
                stdout=subprocess.PIPE, stderr=log, text=True, env=env)
        assert self.proc.stdout is not None
        found = re.match(r"rcan-rtps ready api=(\S+)", self.proc.stdout.readline())
        if not found:
            raise RuntimeError(f"bridge did not start: {(state / 'bridge.log').read_text()}")
        self.url = found.group(1)

    async def command(self, body: dict[str, object]) -> None:
        async with aiohttp.ClientSession(
                headers={"Authorization": f"Bearer {TOKEN}"}) as http, \
                http.post(f"{self.url}/api/command", json=body) as resp:
            assert resp.status == 200, await resp.text()

    def stop(self) -> None:
        self.proc.send_signal(2)
        self.proc.wait(timeout=30)


def intervals(oracle: RclpyOracle, topic: str) -> list[float]:
    """Seconds between consecutive arrivals of VALUE on `topic` since the last call."""
    times = [t for t, v in oracle.call("take", topic=topic) if v == VALUE]
    return [(b - a) / 1e9 for a, b in itertools.pairwise(times)]


async def measure_stream(bridge: Bridge, oracle: RclpyOracle, seconds: float) -> list[float]:
    await bridge.command({"action": "move", "params": {"linear_x": VALUE}})  # held
    await asyncio.sleep(0.5)
    oracle.call("take", topic="/bench/cmd_vel")  # from here on
    await asyncio.sleep(seconds)
    got = intervals(oracle, "/bench/cmd_vel")
    await bridge.command({"action": "stop"})
    return got


async def measure_baseline(oracle: RclpyOracle, rate_hz: float, seconds: float) -> list[float]:
    oracle.call("take", topic="/floor/cmd_vel")
    child = Child("--baseline", str(rate_hz), "--seconds", str(seconds + 1.5),
                  ready_word="streaming")
    await asyncio.to_thread(child.proc.wait, seconds + 60)
    return intervals(oracle, "/floor/cmd_vel")[round(1.0 * rate_hz):]  # skip the first second


Stats = tuple[float, float, float, float]


def jitter(gaps: list[float], rate_hz: float) -> Stats:
    """(p50, p99 of |interval − period| in ms, longest interval in ms, achieved rate in Hz:
    intervals per second of arrivals, so skipped or bunched ticks show against the rate)."""
    dev = [abs(g - 1.0 / rate_hz) * 1e3 for g in gaps]
    return pct(dev, 0.5), pct(dev, 0.99), max(gaps) * 1e3, len(gaps) / sum(gaps)


async def phase(rate: float, bridge: Bridge, oracle: RclpyOracle,
                seconds: float) -> list[Stats]:
    stream = await measure_stream(bridge, oracle, seconds)
    floor = await measure_baseline(oracle, rate, seconds)
    return [jitter(stream, rate), jitter(floor, rate)]


async def main(args: argparse.Namespace) -> int:
    rows = []
    with RclpyOracle(args.oracle, "bench_robot", "/bench", domain_id=DOMAIN,
                     env={"RCAN_ORACLE_EXECUTOR": "single"}) as oracle:
        for topic in ("/bench/cmd_vel", "/floor/cmd_vel"):
            oracle.call("subscribe_timed", topic=topic, type="geometry_msgs/msg/Twist")
        for rate in args.rates:
            with tempfile.TemporaryDirectory() as tmp:
                bridge = Bridge(Path(tmp), rate)
                try:
                    oracle.call("wait_publishers", topic="/bench/cmd_vel", timeout=15)
                    idle = await phase(rate, bridge, oracle, args.seconds)
                    loader = Child("--load", bridge.url, "--clients", str(args.clients),
                                   ready_word="loading")
                    await asyncio.sleep(2.0)  # the load is on
                    try:
                        busy = await phase(rate, bridge, oracle, args.seconds)
                    finally:
                        loader.stop()
                finally:
                    bridge.stop()
            rows.append((rate, "idle", *idle))
            rows.append((rate, f"{args.clients} clients", *busy))
    report = render(rows, args)
    write_section("## Velocity streams", report)
    print(report)
    return 0


def render(rows: list[tuple[float, str, Stats, Stats]], args: argparse.Namespace) -> str:
    lines = [
        "## Velocity streams", "",
        f"`bench/streams.py` (same machine, same run): a held `move` streamed for "
        f"{args.seconds:g} s per phase; an rclpy Jazzy subscriber timestamps each Twist. Jitter "
        "= |arrival interval − period|; achieved rate = arrival intervals per second, against "
        "the configured `cmd_rate_hz`. Baseline: a bare asyncio `call_at` loop writing the same "
        "Twist with cyclonedds on the same schedule, in its own process, in the same phase. "
        f"Load: {args.clients} keep-alive clients sending lower-priority moves (each refused "
        "and audited). All processes share 2 cores.", "",
        "| configured rate | API load | achieved rate (stream / baseline) | "
        "stream jitter p50 / p99 | baseline p50 / p99 | p99 vs baseline | "
        "longest gap (stream / baseline) | "
        f"target: gap ≤ {MAX_GAP_S * 1e3:.0f} ms |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for rate, load_name, (s50, s99, smax, shz), (b50, b99, bmax, bhz) in rows:
        lines.append(
            f"| {rate:g} Hz | {load_name} | {shz:.2f} / {bhz:.2f} Hz "
            f"| {s50:.2f} / {s99:.2f} ms | {b50:.2f} / {b99:.2f} ms "
            f"| {s99 / max(b99, 1e-3):.1f}× | {smax:.0f} / {bmax:.0f} ms | "
            f"{verdict(smax <= MAX_GAP_S * 1e3)} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--oracle", type=Path, default=ROOT / ".cache/ros-jazzy/bin/python")
    parser.add_argument("--rates", type=float, nargs="+", default=[20.0, 100.0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--clients", type=int, default=100)
    parser.add_argument("--load", metavar="URL", help=argparse.SUPPRESS)
    parser.add_argument("--baseline", type=float, metavar="RATE", help=argparse.SUPPRESS)
    parsed = parser.parse_args()
    if parsed.load:
        asyncio.run(load(parsed.load, parsed.clients))
    elif parsed.baseline:
        asyncio.run(baseline(parsed.baseline, parsed.seconds))
    else:
        sys.exit(asyncio.run(main(parsed)))
