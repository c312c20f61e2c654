"""MCP tool call → Twist at an rclpy subscriber, against the REST path in the same run.

Three doors to one bridge (`rcan-rtps run`, its own process), each sample a timed `move`
with a value of its own, from the moment the client sends until the rclpy subscriber
(ROS 2 Jazzy from PyPI) has the Twist carrying that value:

- REST: `POST /api/command` on a keep-alive aiohttp session (the baseline);
- HTTP: the bridge's `/mcp`, the official MCP SDK's client (`call_tool`);
- stdio: `rcan-rtps mcp` launched by that client, in front of the REST API.

Samples are paced and taken in alternating blocks (REST, HTTP, stdio, REST, ...) so drift of
the machine hits each alike. Targets (issue 25): HTTP p99 ≤ 1.5× REST p99; stdio reported
(≤ 2×). Run in a private network namespace (DDS):
    scripts/netns .venv/bin/python bench/mcp_latency.py [--samples 300]
Writes the `## MCP` section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import gc
import os
import sys
import tempfile
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import aiohttp
from mcp import Client, StdioServerParameters
from mcp.client.stdio import stdio_client
from mcp.client.streamable_http import streamable_http_client
from mcp.shared._httpx_utils import create_mcp_http_client
from mcp_types import Implementation

sys.path.insert(0, str(Path(__file__).resolve().parent))
import e2e
from oracle.client import RclpyOracle
from report import write_section

TOPIC = "/bench/cmd_vel"
MODEL = {"ai_provider": "bench", "ai_model": "bench-model"}
Send = Callable[[float], Awaitable[None]]


def move(value: float) -> dict[str, float]:
    # timed, as an agent's move must be; long enough to outlast a block
    return {"linear_x": value, "duration_s": 20.0, "confidence": 1.0}


@contextlib.asynccontextmanager
async def rest_door(url: str) -> AsyncIterator[Send]:
    headers = {"Authorization": f"Bearer {e2e.TOKEN}"}
    async with aiohttp.ClientSession(headers=headers) as http:
        async def send(value: float) -> None:
            params = move(value)
            body = {"action": "move", "confidence": params.pop("confidence"),
                    "params": params, **MODEL}
            async with http.post(f"{url}/api/command", json=body) as resp:
                assert resp.status == 200, await resp.text()
                await resp.read()
        yield send


@contextlib.asynccontextmanager
async def raw_door(url: str) -> AsyncIterator[Send]:
    """/mcp from a plain JSON-RPC client (aiohttp, as the SDK's client would send it, on the
    2026-07-28 protocol): the bridge's share of the MCP path, without the SDK client's own."""
    headers = {"Authorization": f"Bearer {e2e.TOKEN}", "RCAN-AI-Provider": MODEL["ai_provider"],
               "RCAN-AI-Model": MODEL["ai_model"], "Accept": "application/json, text/event-stream",
               "MCP-Protocol-Version": "2026-07-28", "Mcp-Method": "tools/call",
               "Mcp-Name": "move"}
    meta = {"io.modelcontextprotocol/protocolVersion": "2026-07-28",
            "io.modelcontextprotocol/clientInfo": {"name": "bench", "version": "1"},
            "io.modelcontextprotocol/clientCapabilities": {}}
    async with aiohttp.ClientSession(headers=headers) as http:
        ids = iter(range(1, 1 << 62))

        async def send(value: float) -> None:
            body = {"jsonrpc": "2.0", "id": next(ids), "method": "tools/call",
                    "params": {"name": "move", "arguments": move(value), "_meta": meta}}
            async with http.post(f"{url}/mcp", json=body) as resp:
                reply = await resp.json()
                assert resp.status == 200 and not reply["result"].get("isError"), reply
        yield send


@contextlib.asynccontextmanager
async def legacy_door(url: str) -> AsyncIterator[Send]:
    async with http_door(url, "legacy") as send:
        yield send


@contextlib.asynccontextmanager
async def http_door(url: str, mode: Any = "auto") -> AsyncIterator[Send]:
    headers = {"Authorization": f"Bearer {e2e.TOKEN}", "RCAN-AI-Provider": MODEL["ai_provider"],
               "RCAN-AI-Model": MODEL["ai_model"]}
    async with create_mcp_http_client(headers=headers) as http, Client(
            streamable_http_client(f"{url}/mcp", http_client=http),
            client_info=Implementation(name="bench", version="1"), mode=mode) as client:
        async def send(value: float) -> None:
            done = await client.call_tool("move", move(value))
            assert not done.is_error, done
        yield send


@contextlib.asynccontextmanager
async def stdio_door(url: str) -> AsyncIterator[Send]:
    server = StdioServerParameters(
        command=sys.executable,
        args=["-m", "rcan_rtps", "mcp", "--url", url, "--token-env", "BENCH_TOKEN",
              "--ai-provider", MODEL["ai_provider"], "--ai-model", MODEL["ai_model"]],
        env={**os.environ, "BENCH_TOKEN": e2e.TOKEN})
    async with Client(stdio_client(server),
                      client_info=Implementation(name="bench", version="1")) as client:
        async def send(value: float) -> None:
            done = await client.call_tool("move", move(value))
            assert not done.is_error, done
        yield send


async def block(send: Send, oracle: RclpyOracle, n: int, first: float) -> list[float]:
    """ms from sending to rclpy holding that Twist; the first 5 of a block warm up."""
    oracle.call("take", topic=TOPIC)
    sent: dict[float, int] = {}
    for i in range(n + 5):
        value = round(first + i * 1e-3, 6)
        before = time.monotonic_ns()
        await send(value)
        sent[value] = before
        await asyncio.sleep(e2e.PACE_S)
    arrivals = await e2e.wait_arrivals(oracle, TOPIC, len(sent))
    return [(arrivals[v] - t) / 1e6 for i, (v, t) in enumerate(sent.items())
            if i >= 5 and v in arrivals]


DOORS = {"REST": rest_door, "MCP HTTP (/mcp)": http_door,
         "MCP HTTP, 2025 sessions": legacy_door, "MCP HTTP, plain JSON-RPC client": raw_door,
         "MCP stdio": stdio_door}


async def measure(url: str, oracle: RclpyOracle, samples: int, blocks: int
                  ) -> dict[str, list[float]]:
    found: dict[str, list[float]] = {name: [] for name in DOORS}
    per_block = max(1, samples // blocks)
    async with contextlib.AsyncExitStack() as stack:
        sends = {name: await stack.enter_async_context(door(url))
                 for name, door in DOORS.items()}
        gc.freeze()  # this process's clients: their collections are not the bridge's latency
        value = 0.001
        for _ in range(blocks):
            for name, send in sends.items():
                found[name] += await block(send, oracle, per_block, value)
                value += 0.001 * (per_block + 10)
    return found


def report(found: dict[str, list[float]], samples: int, blocks: int) -> str:
    rest50, rest99 = e2e.pct(found["REST"], 0.5), e2e.pct(found["REST"], 0.99)
    targets = {"MCP HTTP (/mcp)": 1.5, "MCP HTTP, 2025 sessions": 1.5,
               "MCP HTTP, plain JSON-RPC client": 1.5, "MCP stdio": 2.0}
    lines = ["## MCP", "",
             f"`bench/mcp_latency.py` (same machine, same run, one bridge; {samples} samples "
             f"per door "
             f"in {blocks} alternating blocks, paced {e2e.PACE_S * 1e3:g} ms apart): a timed "
             "`move` sent → its Twist received by an rclpy Jazzy subscriber. REST is a "
             "keep-alive aiohttp session; both MCP doors use the official SDK's client "
             "(`mcp` 2.x).", "",
             "| door | p50 | p99 | p99 ÷ REST p99 | target | verdict |",
             "|---|---|---|---|---|---|",
             f"| REST `POST /api/command` | {rest50:.2f} ms | {rest99:.2f} ms | 1.00× | — | — |"]
    for name, target in targets.items():
        p50, p99 = e2e.pct(found[name], 0.5), e2e.pct(found[name], 0.99)
        lines.append(f"| {name} | {p50:.2f} ms | {p99:.2f} ms | {p99 / rest99:.2f}× | "
                     f"≤ {target:g}× | {e2e.verdict(p99 <= target * rest99)} |")
    lost = {n: samples - len(v) for n, v in found.items() if len(v) < samples}
    sdk = e2e.pct(found["MCP HTTP (/mcp)"], 0.5) - e2e.pct(
        found["MCP HTTP, plain JSON-RPC client"], 0.5)
    lines += ["", f"Samples without a Twist within 30 s: {lost or 'none'}. The first three MCP "
              "rows send the same requests to the same bridge; they differ in the client: "
              f"the SDK's client adds {sdk:.2f} ms at the median over a plain aiohttp client "
              "posting the JSON-RPC body it would send (pydantic models, httpx2). The stdio "
              "door's server is a process of its own, in front of the REST API.", ""]
    return "\n".join(lines)


async def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--oracle", type=Path, default=e2e.ROOT / ".cache/ros-jazzy/bin/python")
    parser.add_argument("--samples", type=int, default=300)
    parser.add_argument("--blocks", type=int, default=5)
    args = parser.parse_args()
    e2e.SESSION_TIMEOUT_S = 30.0  # the doors pause between blocks; no session may lapse
    samples = args.blocks * max(1, args.samples // args.blocks)
    with RclpyOracle(args.oracle, "bench_robot", "/bench", domain_id=e2e.DOMAIN,
                     env={"RCAN_ORACLE_EXECUTOR": "single"}) as oracle:
        oracle.call("subscribe_timed", topic=TOPIC, type="geometry_msgs/msg/Twist")
        with tempfile.TemporaryDirectory() as state:
            bridge = e2e.BridgeProcess(Path(state))
            try:
                oracle.call("wait_publishers", topic=TOPIC, timeout=15)
                await asyncio.sleep(1.0)
                found = await measure(bridge.url, oracle, args.samples, args.blocks)
            finally:
                bridge.stop()
    text = report(found, samples, args.blocks)
    write_section("## MCP", text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
