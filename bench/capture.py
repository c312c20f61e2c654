"""What Cyclone's packet capture (docs/design/rpc-identity.md) costs a receiving process.

Every domain we create writes each UDP datagram it sends or receives to a tmpfs file that a
thread of ours tails for the related sample identity of Fast DDS replies. This measures, in
the same run, a process (this script with `--receive`) that subscribes to a 640×480 rgb8
`sensor_msgs/Image` at 30 Hz and a `geometry_msgs/Twist` at 1 kHz, both published by an
rclpy Jazzy node on rmw_fastrtps, for `--seconds` each: CPU time of the whole process (user
+ sys, all threads, from `os.times()`), RSS (VmRSS at the end, VmHWM), and what the capture
file holds in tmpfs at the end. Four configurations, interleaved over `--rounds` rounds in
rotating order: capture off (RCAN_RTPS_RPC_IDENTITY=off) and on, each without and with a
Fast DDS-mapping `ServiceClient` alive (calling the oracle's echo server every 100 ms, so
its replies are looked up in the capture).

DDS runs here, so run it in a private network namespace (as root):
    scripts/netns .venv/bin/python bench/capture.py [--oracle .cache/ros-jazzy/bin/python]
Writes the `## Packet capture cost` section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import subprocess
import sys
import threading
from collections import Counter
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from e2e import DOMAIN, ROOT
from oracle.client import RclpyOracle
from report import write_section

from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.services import RequestMapping, ServiceClient

IMAGE = "sensor_msgs/msg/Image"
TWIST = "geometry_msgs/msg/Twist"
ECHO = "test_msgs/srv/BasicTypes"
IMAGE_HZ, TWIST_HZ, CALL_PERIOD = 30.0, 1000.0, 0.1
WARMUP = 2.0  # s of streaming before the window
CONFIGS = [("off", False), ("on", False), ("off", True), ("on", True)]


def _status(field: str) -> int:
    """A /proc/self/status field in KiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def _thread_cpu(thread: threading.Thread | None) -> float:
    """User + sys seconds of one thread of this process (Linux /proc)."""
    if thread is None or thread.native_id is None:
        return 0.0
    stat = Path(f"/proc/self/task/{thread.native_id}/stat").read_text()
    fields = stat.rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


# -- the measured process: `--receive` ----------------------------------------------------------
async def receive(seconds: float, client_alive: bool, share: Path) -> dict[str, Any]:
    counts: Counter[str] = Counter()
    with RosNode("capture_bench", "/", domain_id=DOMAIN, distro="jazzy",
                 idl_paths=[share]) as node:
        node.create_subscription("/bench/image", IMAGE, raw=True,
                                 callback=lambda _s: counts.update(("image",)))
        node.create_subscription("/bench/twist", TWIST, raw=True,
                                 callback=lambda _s: counts.update(("twist",)))
        client = ServiceClient(node, "/echo", ECHO, mapping=RequestMapping.FASTDDS) \
            if client_alive else None
        if client is not None:
            await client.call({"string_value": "hello"}, timeout=15)
        await asyncio.sleep(WARMUP)
        loop = asyncio.get_running_loop()
        counts.clear()
        drain_before = _thread_cpu(node.identities._thread) if node.identities else 0.0
        before, end = os.times(), loop.time() + seconds
        while loop.time() < end:
            if client is not None:
                reply = await client.call({"string_value": f"c{counts['call']}"}, timeout=5)
                counts["call" if reply.string_value == f"c{counts['call']}" else "wrong"] += 1
            await asyncio.sleep(CALL_PERIOD)
        after = os.times()
        capture = node.identities
        drain = _thread_cpu(capture._thread) if capture else 0.0
        return {"cpu": after.user - before.user + after.system - before.system,
                "rss_kib": _status("VmRSS"), "hwm_kib": _status("VmHWM"),
                "drain_cpu": drain - drain_before, "held": capture.held() if capture else 0,
                "identified": capture.identified if capture else 0, **counts}


# -- the run ---------------------------------------------------------------------------------
def measure(capture: str, client: bool, args: argparse.Namespace) -> dict[str, Any]:
    env = {**os.environ, "ROS_DOMAIN_ID": str(DOMAIN), "RCAN_RTPS_RPC_IDENTITY": capture}
    done = subprocess.run(
        [sys.executable, __file__, "--receive", "--seconds", str(args.seconds),
         "--oracle", str(args.oracle), *(["--client"] if client else [])],
        stdout=subprocess.PIPE, text=True, env=env, timeout=args.seconds + 120, check=True)
    result: dict[str, Any] = json.loads(done.stdout.splitlines()[-1])
    return result


def main(args: argparse.Namespace) -> int:
    runs: dict[tuple[str, bool], list[dict[str, Any]]] = {c: [] for c in CONFIGS}
    image = {"height": 480, "width": 640, "encoding": "rgb8", "step": 640 * 3,
             "data": [k % 251 for k in range(640 * 480 * 3)]}
    with RclpyOracle(args.oracle, "capture_pub", "/", domain_id=DOMAIN) as oracle:
        oracle.call("echo_server", name="/echo")
        oracle.call("publisher", topic="/bench/image", type=IMAGE)
        oracle.call("publisher", topic="/bench/twist", type=TWIST)
        oracle.call("publish_periodic", topic="/bench/image", type=IMAGE, value=image,
                    rate=IMAGE_HZ)
        oracle.call("publish_periodic", topic="/bench/twist", type=TWIST,
                    value={"linear": {"x": 0.5}}, rate=TWIST_HZ)
        try:
            for k in range(args.rounds):
                shift = k % len(CONFIGS)
                for config in CONFIGS[shift:] + CONFIGS[:shift]:
                    result = measure(*config, args)
                    print(config, result, flush=True)
                    runs[config].append(result)
        finally:
            published = {t: oracle.call("stop_periodic", topic=t)
                         for t in ("/bench/image", "/bench/twist")}
    report = render(runs, args, published)
    write_section("## Packet capture cost", report)
    print(report)
    return 0


def _median(results: list[dict[str, Any]], key: str) -> float:
    return statistics.median(float(r.get(key, 0)) for r in results)


def render(runs: dict[tuple[str, bool], list[dict[str, Any]]], args: argparse.Namespace,
           published: dict[str, int]) -> str:
    lines = [
        "## Packet capture cost", "",
        "`bench/capture.py` (same machine, same run): a process subscribes to a 640×480 rgb8 "
        f"Image at {IMAGE_HZ:g} Hz (~{640 * 480 * 3 * IMAGE_HZ / 1e6:.0f} MB/s) and a Twist at "
        f"{TWIST_HZ:g} Hz, both from an rclpy Jazzy publisher on rmw_fastrtps, for "
        f"{args.seconds:g} s per run; medians of {args.rounds} interleaved rounds. CPU = the "
        "whole process's user + sys over the window (Cyclone's threads included: they write "
        "the capture); RSS = VmRSS at the end (peak VmHWM); tmpfs = what the capture file "
        "holds at the end (not counted in RSS). Client: a Fast DDS-mapping `ServiceClient` "
        f"calling an rclpy echo server every {CALL_PERIOD * 1e3:.0f} ms. All processes share "
        "2 cores.", "",
        "| Fast DDS client | capture | CPU (s per s; runs' range) | vs off | of it: drain thread "
        "| RSS / peak (MB) | RSS vs off | tmpfs (MB) | images / twists per s | "
        "calls right / wrong |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for client in (False, True):
        off = runs[("off", client)]
        for capture in ("off", "on"):
            got = runs[(capture, client)]
            cpu, rss = _median(got, "cpu") / args.seconds, _median(got, "rss_kib") / 1024
            lines.append(
                f"| {'alive' if client else 'none'} | {capture} | {cpu:.3f} "
                f"({min(r['cpu'] for r in got) / args.seconds:.3f}–"
                f"{max(r['cpu'] for r in got) / args.seconds:.3f}) | "
                f"{cpu / (_median(off, 'cpu') / args.seconds):.2f}× | "
                f"{_median(got, 'drain_cpu') / args.seconds:.3f} | "
                f"{rss:.1f} / {_median(got, 'hwm_kib') / 1024:.1f} | "
                f"{rss - _median(off, 'rss_kib') / 1024:+.1f} MB | "
                f"{_median(got, 'held') / 1e6:.1f} | "
                f"{_median(got, 'image') / args.seconds:.1f} / "
                f"{_median(got, 'twist') / args.seconds:.0f} | "
                f"{sum(r.get('call', 0) for r in got)} / {sum(r.get('wrong', 0) for r in got)} |")
    lines += ["", f"Published over the whole run: {published}."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--oracle", type=Path, default=ROOT / ".cache/ros-jazzy/bin/python")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--receive", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--client", action="store_true", help=argparse.SUPPRESS)
    parsed = parser.parse_args()
    if parsed.receive:
        share = parsed.oracle.parent.parent / "share"
        print(json.dumps(asyncio.run(receive(parsed.seconds, parsed.client, share))))
    else:
        sys.exit(main(parsed))
