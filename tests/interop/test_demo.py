"""The README tour against `rcan-rtps run --sim` as a real subprocess."""

from __future__ import annotations

import asyncio
import os
import re
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from waiting import eventually, take


@dataclass
class Demo:
    url: str
    user: str
    owner: str
    audit: Path
    domain_id: int


def _read_until(proc: subprocess.Popen[str], pattern: str, lines: list[str]) -> re.Match[str]:
    assert proc.stdout is not None
    for line in proc.stdout:
        lines.append(line)
        found = re.search(pattern, line)
        if found:
            return found
    raise AssertionError("demo exited early:\n" + "".join(lines) + (proc.stderr.read()
                                                                      if proc.stderr else ""))


@pytest.fixture
def demo(tmp_path: Path, domain_id: int) -> Iterator[Demo]:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    env.pop("RCAN_BRIDGE_TOKEN", None)
    proc = subprocess.Popen(
        [sys.executable, "-m", "rcan_rtps", "run", "--sim", "--port", "0", "--no-mdns",
         "--state-dir", str(tmp_path / "state")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    lines: list[str] = []
    try:
        url = _read_until(proc, r"^rcan-rtps ready api=(\S+)$", lines).group(1)
        user = _read_until(proc, r"USER \(operator\) (\S+)", lines).group(1)
        owner = _read_until(proc, r"OWNER \(owner\)\s+(\S+)", lines).group(1)
        audit = Path(_read_until(proc, r"audit log: (\S+)", lines).group(1))
        yield Demo(url, user, owner, audit, domain_id)
    finally:
        proc.send_signal(2)  # SIGINT: the graceful path
        try:
            proc.wait(timeout=20)
        finally:
            proc.kill()
    assert proc.returncode == 0, proc.stderr.read() if proc.stderr else ""
    assert '"event":"BRIDGE_STOPPED"' in (tmp_path / "state" / "audit.jsonl").read_text()


@pytest.fixture
async def http() -> AsyncIterator[aiohttp.ClientSession]:
    async with aiohttp.ClientSession() as session:
        yield session


async def call(http: aiohttp.ClientSession, demo: Demo, token: str, method: str, path: str,
               body: Any = None) -> tuple[int, Any]:
    async with http.request(method, demo.url + path, json=body,
                            headers={"Authorization": f"Bearer {token}"}) as resp:
        return resp.status, await resp.json()


async def wait_status(http: aiohttp.ClientSession, demo: Demo, predicate: Any,
                      timeout: float = 20.0) -> dict[str, Any]:
    async def matching() -> dict[str, Any] | None:
        _, status = await call(http, demo, demo.user, "GET", "/api/status")
        return status if predicate(status) else None

    status: dict[str, Any] = await eventually(matching, timeout=timeout, what="a STATUS")
    return status


async def test_readme_tour(demo: Demo, http: aiohttp.ClientSession) -> None:
    status = await wait_status(http, demo, lambda s: s["ros"]["connected"])
    assert status["state"] == "idle" and status["ruri"].startswith("rcan://")

    # move: executed, and the simulated robot's odometry moves forward
    code, body = await call(http, demo, demo.user, "POST", "/api/command",
                            {"action": "move", "params": {"linear_x": 0.5}})
    assert code == 200 and body["outcome"] == "executed", body
    moved = await wait_status(http, demo,
                              lambda s: (s["telemetry"]["position"] or {}).get("x", 0) > 0.1)
    assert moved["telemetry"]["position"]["x"] > 0.1

    # over the limit (1.0 m/s, +10 %): refused, nothing moves
    code, body = await call(http, demo, demo.user, "POST", "/api/command",
                            {"action": "move", "params": {"linear_x": 2.0}})
    assert code == 409 and body["outcome"] == "safety_violation"

    # HiTL: the arm needs the owner's approval
    code, held = await call(http, demo, demo.user, "POST", "/api/command", {
        "action": "arm_joint", "params": {"joints": ["elbow"], "positions": [0.8],
                                          "duration_s": 0.5}})
    assert code == 202 and held["outcome"] == "pending_auth"
    code, pending = await call(http, demo, demo.owner, "GET", "/api/hitl/pending")
    assert code == 200 and [p["pending_id"] for p in pending["pending"]] == [held["pending_id"]]
    code, body = await call(http, demo, demo.user, "POST", "/api/hitl/authorize",
                            {"pending_id": held["pending_id"]})
    assert code == 403  # the operator may not approve
    code, body = await call(http, demo, demo.owner, "POST", "/api/hitl/authorize",
                            {"pending_id": held["pending_id"]})
    assert code == 200 and body["outcome"] == "executed", body

    def elbow(s: dict[str, Any]) -> float:
        joints = s["telemetry"]["joints"] or {"names": [], "positions": []}
        return dict(zip(joints["names"], joints["positions"], strict=True)).get("elbow", 0.0)

    assert abs(elbow(await wait_status(http, demo, lambda s: abs(elbow(s) - 0.8) < 1e-6))
               - 0.8) < 1e-6

    # navigate: a NavigateToPose goal the simulated robot drives to
    code, body = await call(http, demo, demo.user, "POST", "/api/command",
                            {"action": "navigate", "params": {"x": 1.0, "y": 0.5, "yaw": 0.0}})
    assert code == 200 and body["outcome"] == "executed", body
    goal_id = body["goal_id"]
    code, goals = await call(http, demo, demo.user, "GET", "/api/goals")
    assert goal_id in [g["goal_id"] for g in goals["goals"]]
    async def finished() -> dict[str, Any] | None:
        _, goal = await call(http, demo, demo.user, "GET", f"/api/goals/{goal_id}")
        return goal if goal["state"] in ("succeeded", "aborted", "canceled", "lost") else None

    goal = await eventually(finished, timeout=60, what=f"goal {goal_id} finished")
    assert goal["state"] == "succeeded", goal
    assert goal["feedback"]["distance_remaining"] < 0.1
    at = (await wait_status(http, demo, lambda s: True))["telemetry"]["position"]
    assert abs(at["x"] - 1.0) < 0.1 and abs(at["y"] - 0.5) < 0.1

    # `rcan-rtps topic echo` of the odometry, as a ROS user would (the demo keeps to
    # loopback discovery, so the tool does too)
    env = {**os.environ, "ROS_DOMAIN_ID": str(demo.domain_id)}
    echo = await asyncio.to_thread(subprocess.run, [
        sys.executable, "-m", "rcan_rtps", "--localhost", "topic", "echo", "/robot1/odom",
        "--once", "--json", "--timeout", "20"], capture_output=True, text=True, env=env,
        timeout=60)
    assert echo.returncode == 0, echo.stderr
    assert '"child_frame_id": "base_link"' in echo.stdout

    # the audit log verifies
    verify = await asyncio.to_thread(subprocess.run, [
        sys.executable, "-m", "rcan_rtps", "audit", "verify", str(demo.audit)],
        capture_output=True, text=True, timeout=60)
    assert verify.returncode == 0, verify.stdout + verify.stderr


async def test_rclpy_on_localhost_sees_the_demo_robot(demo: Demo, jazzy_python: Path) -> None:
    """The demo speaks loopback-only discovery; rclpy in LOCALHOST mode finds it."""
    from oracle.client import RclpyOracle

    env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    with RclpyOracle(jazzy_python, "watcher", domain_id=demo.domain_id, env=env) as oracle:
        await oracle.acall("subscribe", topic="/robot1/odom", type="nav_msgs/msg/Odometry")
        odom = await take(oracle, "/robot1/odom")
        assert odom and odom[-1]["child_frame_id"] == "base_link"

        async def both_listed() -> bool:
            names = await oracle.acall("node_names")
            return ["sim_robot", "/robot1"] in names and ["rcan_bridge", "/robot1"] in names

        await eventually(both_listed)


def _example(name: str, demo: Demo, token: str, *args: str) -> subprocess.CompletedProcess[str]:
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "RCAN_URL": demo.url, "RCAN_TOKEN": token}
    return subprocess.run([sys.executable, str(root / "examples" / name), *args],
                          capture_output=True, text=True, env=env, timeout=120)


async def test_examples_agent_and_operator(demo: Demo, http: aiohttp.ClientSession) -> None:
    await wait_status(http, demo, lambda s: s["ros"]["connected"])
    agent = await asyncio.to_thread(_example, "agent_client.py", demo, demo.user)
    assert agent.returncode == 0, agent.stderr
    lines = agent.stdout.splitlines()
    assert any(line.startswith("move") and "→ 200 executed" in line for line in lines)
    assert any("→ 409 safety_violation" in line for line in lines)
    assert any("→ 202 pending_auth" in line for line in lines)  # the low-confidence move
    assert "navigate goal" in agent.stdout and ": succeeded" in agent.stdout
    operator = await asyncio.to_thread(_example, "operator_approve.py", demo, demo.owner,
                                       "--yes")
    assert operator.returncode == 0, operator.stderr
    assert "authorize: 200 executed" in operator.stdout
    entries = [line for line in demo.audit.read_text().splitlines() if '"ai":' in line]
    assert entries and all('"model":"planner-7b"' in line for line in entries)
