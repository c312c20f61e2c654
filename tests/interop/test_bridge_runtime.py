"""The whole bridge (`Bridge`: ROS node, governor, API) against real rclpy Jazzy nodes (on
Fast DDS; the representative cases on Cyclone DDS too)."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from oracle.client import OracleEnv, RclpyOracle, both_rmws
from waiting import eventually, take

from rcan_rtps.bridge.runtime import Bridge, BridgeOptions
from rcan_rtps.governance import verify

from .bridge_rig import bridge_config

TOKEN = "t" * 32
ODOM = {"header": {"frame_id": "odom"}, "child_frame_id": "base_link",
        "pose": {"pose": {"position": {"x": 3.25, "y": -1.5, "z": 0.0},
                          "orientation": {"w": 1.0}}},
        "twist": {"twist": {"linear": {"x": 0.2}}}}


class Live:
    def __init__(self, bridge: Bridge, oracle: RclpyOracle, http: aiohttp.ClientSession,
                 audit: Path) -> None:
        self.bridge, self.oracle, self.http, self.audit = bridge, oracle, http, audit

    async def post(self, body: Any) -> tuple[int, Any]:
        async with self.http.post(self.bridge.url + "/api/command", json=body) as resp:
            return resp.status, await resp.json()


@pytest.fixture
async def live(tmp_path: Path, jazzy_oracle: OracleEnv, domain_id: int) -> AsyncIterator[Live]:
    config = bridge_config(tmp_path, domain_id, extra_ros2="match_timeout_s: 1.0")
    bridge = Bridge(config, BridgeOptions(port=0, mdns=False,
                                          env={"RCAN_BRIDGE_TOKEN": TOKEN}))
    await bridge.start()
    headers = {"Authorization": f"Bearer {TOKEN}"}
    try:
        with RclpyOracle(jazzy_oracle, "robot", "/robot1", domain_id=domain_id) as oracle:
            async with aiohttp.ClientSession(headers=headers) as http:
                yield Live(bridge, oracle, http, Path(config.bridge.audit.path))
    finally:
        await bridge.stop()


@both_rmws
async def test_rclpy_telemetry_reaches_the_websocket(live: Live) -> None:
    await live.oracle.acall("publisher", topic="/robot1/odom", type="nav_msgs/msg/Odometry")
    async with live.http.ws_connect(live.bridge.url + "/api/ws") as ws:

        async def status_with_the_odometry() -> dict[str, Any] | None:
            await live.oracle.acall("publish", topic="/robot1/odom",
                                    type="nav_msgs/msg/Odometry", value=ODOM, count=2)
            frame: dict[str, Any] = json.loads((await asyncio.wait_for(ws.receive(), 10)).data)
            position = frame.get("body", {}).get("telemetry", {}).get("position")
            found = frame.get("type") == "status" and position and position["x"] == 3.25
            return frame if found else None

        frame = await eventually(status_with_the_odometry, timeout=120)
        position = frame["body"]["telemetry"]["position"]
        assert position == {"x": 3.25, "y": -1.5, "z": 0.0}
        assert frame["body"]["state"] == "moving" and frame["body"]["ros"]["connected"]


async def test_navigate_without_an_action_server_is_robot_unavailable(live: Live) -> None:
    code, body = await live.post({"action": "navigate", "params": {"x": 1, "y": 1, "yaw": 0}})
    assert code == 503 and body["error_code"] == "ROBOT_UNAVAILABLE"


@both_rmws
async def test_stopping_the_bridge_halts_the_robot(live: Live) -> None:
    await live.oracle.acall("subscribe", topic="/robot1/cmd_vel", type="geometry_msgs/msg/Twist")
    assert live.bridge.dispatcher is not None  # matched first: match_timeout_s is short here
    await live.bridge.dispatcher.cmd_vel.wait_for_subscribers(1, timeout=15)
    code, _ = await live.post({"action": "move", "params": {"linear_x": 0.3}})
    assert code == 200
    assert (await take(live.oracle, "/robot1/cmd_vel"))[0]["linear"]["x"] == 0.3
    await live.bridge.stop()  # what SIGINT/SIGTERM do
    zero = await take(live.oracle, "/robot1/cmd_vel")
    assert zero and zero[-1]["linear"]["x"] == 0.0
    events = [json.loads(line)["event"] for line in live.audit.read_text().splitlines()]
    assert events[0] == "BRIDGE_STARTED" and events[-1] == "BRIDGE_STOPPED"
    verify(live.audit)


@pytest.mark.slow
async def test_500_clients_20_commands_each_on_a_real_graph(tmp_path: Path, jazzy_python: Path,
                                                            domain_id: int) -> None:
    extra = ("rbac:\n  rate_limits_per_min: {OWNER: null}\n")
    config = bridge_config(tmp_path, domain_id, extra=extra)
    bridge = Bridge(config, BridgeOptions(port=0, mdns=False, env={"RCAN_BRIDGE_TOKEN": TOKEN}))
    await bridge.start()
    statuses: list[int] = []
    try:
        with RclpyOracle(jazzy_python, "robot", "/robot1", domain_id=domain_id) as oracle:
            await oracle.acall("subscribe", topic="/robot1/cmd_vel",
                               type="geometry_msgs/msg/Twist")
            assert bridge.dispatcher is not None
            await bridge.dispatcher.cmd_vel.wait_for_subscribers(1, timeout=15)
            connector = aiohttp.TCPConnector(limit=500)
            headers = {"Authorization": f"Bearer {TOKEN}"}
            async with aiohttp.ClientSession(headers=headers, connector=connector) as http:

                async def client(k: int) -> None:
                    for i in range(20):
                        async with http.post(bridge.url + "/api/command", json={
                                "action": "move", "params": {"linear_x": 0.01 * (i % 10)},
                                "message_id": f"00000000-0000-4000-8000-{k:06d}{i:06d}"}) as r:
                            await r.read()
                            statuses.append(r.status)

                await asyncio.wait_for(asyncio.gather(*(client(k) for k in range(500))), 300)
    finally:
        await bridge.stop()
    assert len(statuses) == 10_000 and set(statuses) == {200}
    head = verify(Path(config.bridge.audit.path))
    entries = [json.loads(line) for line in Path(config.bridge.audit.path).read_text()
               .splitlines()]
    dispatched = [e for e in entries if e["event"] == "COMMAND_DISPATCHED"]
    assert len(dispatched) == 10_000 and head.count == len(entries)
