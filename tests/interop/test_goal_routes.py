"""Each goal action reaches its own server, and what spans goals spans every server
(issue 23, item 4), through the whole bridge (`Bridge`: config, API, governor, dispatcher).

The robot side is a second DDS participant serving nav2 NavigateToPose on
`/robot1/navigate_to_pose` and DockRobot on `/robot1/dock_robot`; each server records every
goal it receives. A goal's x (navigate) or dock id (dock) picks how it ends: 1.0 / `home`
succeed after a few feedback steps, 0.5 after one, 3.0 / `far` run until cancelled.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from waiting import eventually

from rcan_rtps.bridge.runtime import Bridge, BridgeOptions
from rcan_rtps.ros.actions import ActionClient, ActionServer, GoalState, ServerGoal
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.rostime import duration_msg

from .bridge_rig import bridge_config

TOKEN = "t" * 32
NAV = "nav2_msgs/action/NavigateToPose"
DOCK = "nav2_msgs/action/DockRobot"
NAV_SERVER, DOCK_SERVER = "/robot1/navigate_to_pose", "/robot1/dock_robot"


@dataclass
class Robot:
    """What each action server was sent: NavigateToPose x's, DockRobot dock ids."""

    navigated: list[float] = field(default_factory=list)
    docked: list[str] = field(default_factory=list)
    node: RosNode | None = None

    async def navigate(self, goal: ServerGoal) -> dict[str, Any]:
        x = float(goal.goal.pose.pose.position.x)
        self.navigated.append(x)
        return await _run(goal, x in (1.0, 0.5), lambda step: {
            "distance_remaining": max(0.0, 1.0 - 0.2 * step),
            "navigation_time": duration_msg(0.05 * step)}, {}, steps=0 if x == 0.5 else 5)

    async def dock(self, goal: ServerGoal) -> dict[str, Any]:
        self.docked.append(str(goal.goal.dock_id))
        return await _run(goal, goal.goal.dock_id == "home", lambda step: {
            "state": 1 if step < 3 else 3, "docking_time": duration_msg(0.05 * step)},
            {"success": True})


async def _run(goal: ServerGoal, succeeds: bool, feedback: Any,
               result: dict[str, Any], steps: int = 5) -> dict[str, Any]:
    for step in range(100_000):
        if goal.cancel_requested.is_set():
            goal.canceled()
            return {}
        goal.publish_feedback(feedback(step))
        if succeeds and step == steps:
            return result
        await asyncio.sleep(0.05)
    raise AssertionError("the goal was never cancelled")


@dataclass
class Live:
    bridge: Bridge
    robot: Robot
    http: aiohttp.ClientSession
    audit: Path

    async def command(self, body: Any) -> dict[str, Any]:
        async with self.http.post(self.bridge.url + "/api/command", json=body) as resp:
            reply: dict[str, Any] = await resp.json()
            assert resp.status == 200, reply
            return reply

    async def get(self, path: str) -> Any:
        async with self.http.get(self.bridge.url + path) as resp:
            assert resp.status == 200
            return await resp.json()

    def finished(self) -> dict[str, tuple[str, str]]:
        """GOAL_FINISHED entries: goal id → (outcome, server)."""
        entries = [json.loads(line) for line in self.audit.read_text().splitlines()]
        return {e["params"]["goal_id"]: (e["outcome"], e["ros2_topic"])
                for e in entries if e["event"] == "GOAL_FINISHED"}


@pytest.fixture
async def live(tmp_path: Path, domain_id: int) -> AsyncIterator[Live]:
    config = bridge_config(tmp_path, domain_id)
    robot = Robot()
    with RosNode("robot", "/robot1", domain_id=domain_id) as node:
        robot.node = node
        servers = [ActionServer(node, "navigate_to_pose", NAV, robot.navigate),
                   ActionServer(node, "dock_robot", DOCK, robot.dock)]
        bridge = Bridge(config, BridgeOptions(port=0, mdns=False,
                                              env={"RCAN_BRIDGE_TOKEN": TOKEN}))
        await bridge.start()
        try:
            headers = {"Authorization": f"Bearer {TOKEN}"}
            async with aiohttp.ClientSession(headers=headers) as http:
                beat = asyncio.create_task(_heartbeat(http, bridge.url))
                try:
                    yield Live(bridge, robot, http, Path(config.bridge.audit.path))
                finally:
                    beat.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await beat
        finally:
            await bridge.stop()
            for server in servers:
                await server.close()


async def _heartbeat(http: aiohttp.ClientSession, url: str) -> None:
    while True:  # the control session (1 s here) must outlive the goals
        async with http.post(url + "/api/heartbeat") as resp:
            await resp.read()
        await asyncio.sleep(0.2)


async def _goal(live: Live, goal_id: str, state: str) -> dict[str, Any]:
    async def reached() -> dict[str, Any] | None:
        view: dict[str, Any] = await live.get(f"/api/goals/{goal_id}")
        return view if view["state"] == state else None

    found: dict[str, Any] = await eventually(reached, timeout=30, what=f"{goal_id} {state}")
    return found


async def _frames(ws: aiohttp.ClientWebSocketResponse, into: list[dict[str, Any]]) -> None:
    async for msg in ws:
        if msg.type is aiohttp.WSMsgType.TEXT:
            into.append(json.loads(msg.data))


async def test_each_goal_action_reaches_its_own_server(live: Live) -> None:
    frames: list[dict[str, Any]] = []
    async with live.http.ws_connect(live.bridge.url + "/api/ws") as ws:
        reader = asyncio.create_task(_frames(ws, frames))
        nav = await live.command({"action": "navigate", "params": {"x": 1.0, "y": 0, "yaw": 0}})
        assert nav["ros2_topic"] == NAV_SERVER and nav["goal_id"]
        await _goal(live, nav["goal_id"], "succeeded")
        dock = await live.command({"action": "dock", "params": {"dock_id": "home"}})
        assert dock["ros2_topic"] == DOCK_SERVER and dock["goal_id"]
        status = await live.get("/api/status")
        assert status["active_goals"] == [dock["goal_id"]]
        assert status["navigation"] is None  # STATUS navigation is NavigateToPose's alone
        docked = await _goal(live, dock["goal_id"], "succeeded")
        await eventually(lambda: any(f["type"] == "goal" and f["body"]["goal_id"] ==
                                     dock["goal_id"] and f["body"]["state"] == "succeeded"
                                     for f in frames), what="the dock goal's end on the socket")
        reader.cancel()
    # neither went to the other's server
    assert (live.robot.navigated, live.robot.docked) == ([1.0], ["home"])
    assert docked["result"] == {"success": True, "error_code": 0, "num_retries": 0,
                                "error_msg": ""}
    assert docked["feedback"]["state"] == 3
    # GET /api/goals lists both, each with its own action
    views = {g["goal_id"]: g for g in (await live.get("/api/goals"))["goals"]}
    assert {k: (v["action"], v["action_type"], v["command"]) for k, v in views.items()} == {
        nav["goal_id"]: (NAV_SERVER, NAV, "navigate"),
        dock["goal_id"]: (DOCK_SERVER, DOCK, "dock")}
    # WebSocket goal events cover both
    evented = {f["body"]["goal_id"]: f["body"]["action"] for f in frames if f["type"] == "goal"}
    assert evented == {nav["goal_id"]: NAV_SERVER, dock["goal_id"]: DOCK_SERVER}
    # each tracker's end is audited, with its own server
    finished = await eventually(lambda: live.finished() if len(live.finished()) == 2 else None,
                                what="two GOAL_FINISHED entries")
    assert finished == {nav["goal_id"]: ("succeeded", NAV_SERVER),
                        dock["goal_id"]: ("succeeded", DOCK_SERVER)}


async def test_stop_cancels_goals_on_every_goal_server(live: Live) -> None:
    # A goal on the navigation server from another client (the bridge cancels every goal on
    # the server, whoever sent it) and the bridge's own docking goal.
    assert live.robot.node is not None
    other = ActionClient(live.robot.node, NAV_SERVER, NAV)
    try:
        elsewhere = await other.send_goal({"pose": {"pose": {"position": {"x": 3.0}}}},
                                          timeout=15)
        assert elsewhere.accepted
        dock = await live.command({"action": "dock", "params": {"dock_id": "far"}})
        await _goal(live, dock["goal_id"], "executing")
        # One goal cancelled by id is found on its own server; the other server's goal runs on.
        assert live.bridge.dispatcher is not None
        assert await live.bridge.dispatcher.cancel_goal(dock["goal_id"])
        await _goal(live, dock["goal_id"], "canceled")
        assert not elsewhere.state.terminal
        # stop: every goal on every goal server
        dock = await live.command({"action": "dock", "params": {"dock_id": "far"}})
        await _goal(live, dock["goal_id"], "executing")
        await live.command({"action": "stop"})
        await _goal(live, dock["goal_id"], "canceled")
        assert (await elsewhere.result(timeout=15)).state is GoalState.CANCELED
        assert live.finished()[dock["goal_id"]] == ("canceled", DOCK_SERVER)
        assert live.robot.navigated == [3.0] and live.robot.docked == ["far", "far"]
    finally:
        other.close()


MANY_GOALS = 60


async def test_the_bridge_s_per_goal_state_stays_bounded(live: Live) -> None:
    """The bridge keeps one action client per goal server for its whole life: what it holds
    per goal must not grow with the goals sent. Every goal here reached its end and its
    feedback stream ended: the client lets go of each, the tracker keeps its view (the
    newest `keep`) and nothing else."""
    sent = []
    for _ in range(MANY_GOALS):
        nav = await live.command({"action": "navigate", "params": {"x": 0.5, "y": 0, "yaw": 0}})
        await _goal(live, nav["goal_id"], "succeeded")
        sent.append(nav["goal_id"])
    assert live.bridge.goals is not None
    tracker = live.bridge.goals.tracker("nav_action")
    assert tracker is not None
    sent_goals = tracker._sent
    assert sent_goals is not None
    await eventually(lambda: not sent_goals._watchers, what="every goal's feedback stream ended")
    assert tracker.client.goals_tracked == 0
    assert not sent_goals._handles and set(sent_goals._message_ids) == set(sent)
    assert len(live.robot.navigated) == MANY_GOALS


def _cancel_pairs(live: Live, key: str) -> dict[Any, Any]:
    assert live.bridge.goals is not None
    tracker = live.bridge.goals.tracker(key)
    assert tracker is not None
    return tracker.client._cancel_srv._pairs


async def test_a_stop_s_cancel_client_is_ready_before_the_first_stop(live: Live) -> None:
    """A stop cancels every goal on a server, whoever sent it. The bridge here has sent no
    goal: the cancel client's endpoints were made (and matched) as the servers appeared,
    not by the stop — whose cancel would otherwise wait for discovery while another
    client's goal drives on."""
    assert live.robot.node is not None and live.bridge.goals is not None
    for key in ("nav_action", "dock_action"):
        await eventually(lambda key=key: bool(_cancel_pairs(live, key)), timeout=15,
                         what=f"{key}'s cancel client made before any stop")
    nav = live.bridge.goals.tracker("nav_action")
    assert nav is not None
    await eventually(lambda: nav.cancel_ready, timeout=15, what="nav's cancel client ready")
    made = dict(_cancel_pairs(live, "nav_action"))
    other = ActionClient(live.robot.node, NAV_SERVER, NAV)
    try:
        elsewhere = await other.send_goal({"pose": {"pose": {"position": {"x": 3.0}}}},
                                          timeout=15)
        assert elsewhere.accepted
        await live.command({"action": "stop"})
        assert (await elsewhere.result(timeout=15)).state is GoalState.CANCELED
        assert _cancel_pairs(live, "nav_action") == made  # the stop made no endpoints
        assert live.bridge.goals.goals() == []  # the bridge sent none
        # Nor did the stop make the goal-sending side, or parse the actions (issue 27: both
        # wait for the first goal).
        assert all(t.client._sending is None for t in live.bridge.goals.trackers)
        assert live.bridge.node is not None
        parsed = [n for n in live.bridge.node.store._types if n.startswith((NAV, DOCK))]
        assert not parsed, parsed
    finally:
        other.close()


async def test_a_server_that_comes_back_gets_its_cancel_client_ready_again(
        domain_id: int) -> None:
    from rcan_rtps.bridge.navigation import GoalTracker

    async def never_ends(goal: ServerGoal) -> dict[str, Any]:
        await goal.cancel_requested.wait()
        goal.canceled()
        return {}

    with RosNode("bridge", "/", domain_id=domain_id) as ours, \
            RosNode("robot", "/robot1", domain_id=domain_id) as robot:
        tracker = GoalTracker(ours, NAV_SERVER, NAV)
        tracker.keep_cancel_ready(period=0.1)
        try:
            first = ActionServer(robot, "navigate_to_pose", NAV, never_ends)
            await eventually(lambda: tracker.cancel_ready, timeout=15, what="first server")
            await first.close()
            await eventually(lambda: not tracker.client.server_present(), timeout=15,
                             what="the first server gone")
            second = ActionServer(robot, "navigate_to_pose", NAV, never_ends)
            await eventually(lambda: tracker.client.status_matches() == 2, timeout=15,
                             what="the second server matched")
            await eventually(lambda: tracker.cancel_ready, timeout=15, what="second server")
            other = ActionClient(robot, NAV_SERVER, NAV)
            goal = await other.send_goal({}, timeout=15)
            assert await tracker.cancel_all() == 1
            assert (await goal.result(timeout=15)).state is GoalState.CANCELED
            other.close()
            await second.close()
        finally:
            await tracker.close()
