"""Issue 23, item 2: SIGTERM and SIGINT stop the robot whatever the API was asked before.

One `rcan-rtps run --sim` per signal (a real process, mDNS on, in the test's network
namespace) is asked every route of the API — each GET and POST the OpenAPI document lists,
the audit verification and a WebSocket included — while a USER's `move` streams and its
`navigate` goal drives; then it gets the signal. An rclpy Jazzy node records what reached
the robot. An orderly stop is: exit status 0, the signal taken by the bridge's own handler
(its bounded graceful stop), zero velocity as the last Twist on /robot1/cmd_vel, the goal
canceled on the action's status topic, the stream ended `bridge_stopped` and BRIDGE_STOPPED
the last audit entry. After each route the test also reads every thread's signal mask from
/proc: none may take SIGINT or SIGTERM but the one waiting for them.

Before the fix, the verification's process pool (multiprocessing's resource tracker)
unblocked both signals in the event loop's thread: SIGTERM then killed the bridge at once
(exit 143, nothing stopped, no BRIDGE_STOPPED), SIGINT bypassed the bounded stop.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import platform
import re
import signal
import time
import uuid
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from oracle.client import RclpyOracle
from waiting import eventually

from .run_process import RunProcess, child_env, state_args

# mDNS on, under the demo's name: like every test that advertises, in the serial phase
# (tests/bridge/test_mdns.py).
pytestmark = pytest.mark.serial
EXIT_TIMEOUT = 60.0  # s; generous: the bounded stop gives up after 10 s
CMD_VEL = "/robot1/cmd_vel"
GOAL_STATUS = "/robot1/navigate_to_pose/_action/status"
CANCELING, CANCELED = 3, 5  # action_msgs/msg/GoalStatus
SPEED = 0.3
_RT_SIGTIMEDWAIT = {"x86_64": 128, "aarch64": 137}  # syscall numbers


RESAMPLES = 3  # looks again at a thread that seemed to take the stop signals (`Client._after`)


def _takes_stop_signals(pid: int) -> list[str]:
    """Threads of `pid` in which SIGINT or SIGTERM is not blocked, except those waiting for
    them in sigwait (the kernel unblocks what a thread waits for while it waits)."""
    bits = (1 << (signal.SIGINT - 1)) | (1 << (signal.SIGTERM - 1))
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            status = (task / "status").read_text()
            waiting = (task / "wchan").read_text()
            syscall = (task / "syscall").read_text().split()[0]
        except (FileNotFoundError, ProcessLookupError, IndexError):
            continue  # the thread has just ended
        blocked = int(re.search(r"^SigBlk:\s*([0-9a-f]+)", status, re.M).group(1), 16)
        in_sigwait = ("sigtimedwait" in waiting
                      or syscall == str(_RT_SIGTIMEDWAIT.get(platform.machine())))
        if blocked & bits != bits and not in_sigwait:
            found.append(f"{task.name} ({(task / 'comm').read_text().strip()})")
    return found


class Client:
    """The API of one run, as its demo principals; records each (method, route) visited and
    the threads that took stop signals after it."""

    def __init__(self, proc: RunProcess, http: aiohttp.ClientSession) -> None:
        self.proc, self.http = proc, http
        self.visited: set[tuple[str, str]] = set()
        self.unblocked: dict[str, list[str]] = {}
        self.sockets: list[aiohttp.ClientWebSocketResponse] = []  # open until the end
        self.last_headers: Any = {}

    def _after(self, method: str, route: str) -> None:
        self.visited.add((method, route))
        threads = set(_takes_stop_signals(self.proc.proc.pid))
        # A thread seen so must be seen so again: the sigwait thread, woken for a moment (a
        # SIGCHLD may pick it), shows the mask sigwait lowered while it is no longer in the
        # call (CI once: after `get /api/safety/manifest`). A thread that really unblocked
        # them stays so; one in that moment is back in sigwait a few ms later.
        for _ in range(RESAMPLES):
            if not threads:
                return
            time.sleep(0.02)
            threads &= set(_takes_stop_signals(self.proc.proc.pid))
        if threads:
            self.unblocked[f"{method} {route}"] = sorted(threads)

    async def call(self, method: str, path: str, token: str, body: Any = None, *,
                   route: str | None = None, headers: dict[str, str] | None = None
                   ) -> tuple[int, Any]:
        sent = {"Authorization": f"Bearer {token}", **(headers or {})}
        async with self.http.request(method, self.proc.url + path, json=body,
                                     headers=sent) as resp:
            data = await resp.read()
            status, ctype = resp.status, resp.content_type
            self.last_headers = resp.headers
        self._after(method.lower(), route or path.split("?")[0])
        if ctype == "application/json":
            return status, json.loads(data) if data else None
        return status, data if ctype.startswith("image/") else data.decode()

    async def command(self, token: str, body: dict[str, Any]) -> dict[str, Any]:
        status, reply = await self.call("POST", "/api/command", token, body)
        assert status in (200, 202), (status, reply)
        return dict(reply)

    async def websocket(self, token: str) -> aiohttp.ClientWebSocketResponse:
        ws = await self.http.ws_connect(self.proc.url + "/api/ws",
                                        headers={"Authorization": f"Bearer {token}"})
        frame = json.loads((await ws.receive(timeout=30)).data)
        assert frame["type"] == "status", frame
        self._after("get", "/api/ws")
        self.sockets.append(ws)
        return ws


@contextlib.asynccontextmanager
async def heartbeats(client: Client, token: str) -> AsyncIterator[None]:
    """The operator's control session held (5 s timeout in the demo) until the signal: the
    stop that follows must be the shutdown's, not a session loss."""
    async def beat() -> None:
        while True:
            status, _ = await client.call("POST", "/api/heartbeat", token)
            assert status == 200
            await asyncio.sleep(1.0)

    task = asyncio.create_task(beat())
    try:
        yield
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


async def visit_every_route(client: Client, proc: RunProcess) -> str:
    """Every route, with a goal running at the end; its goal_id."""
    user, owner = proc.user, proc.owner
    # The sim's arm heard first: the stop below, right after the arm's trajectory, holds it
    # where its joint_states say (unheard, the stop would fail: the arm not held).
    await eventually(lambda: _arm_heard(client), timeout=30, what="the sim's joint_states")
    for path in ("/api/status", "/api/openapi.json", "/api/metrics", "/api/goals",
                 "/api/safety/manifest", "/.well-known/rcan-node.json"):
        status, _ = await client.call("GET", path, user)
        assert status == 200, path
    # A cancelled motion command's withdrawal (`rcan-rtps mcp` sends it), before anything of
    # the user's moves: nothing to stop.
    status, cancel = await client.call("POST", "/api/command/cancel", user)
    assert (status, cancel["stopped"]) == (200, False), cancel
    await client.websocket(owner)  # left open: the shutdown closes it
    # HiTL: one arm command denied, one withdrawn by its issuer, one approved.
    arm = {"action": "arm_joint", "params": {"joints": ["elbow"], "positions": [0.2],
                                             "duration_s": 0.5}}
    held = [(await client.command(user, arm))["pending_id"] for _ in range(3)]
    status, pending = await client.call("GET", "/api/hitl/pending", owner)
    assert sorted(p["pending_id"] for p in pending["pending"]) == sorted(held)
    status, _ = await client.call("POST", "/api/hitl/deny", owner, {"pending_id": held[0]})
    assert status == 200
    status, denied = await client.call("GET", f"/api/hitl/pending/{held[0]}", user,
                                       route="/api/hitl/pending/{pending_id}")  # its issuer
    assert (status, denied["decision"]["outcome"]) == (200, "denied"), denied
    status, _ = await client.call("POST", "/api/hitl/withdraw", user, {"pending_id": held[2]})
    assert status == 200
    status, done = await client.call("POST", "/api/hitl/authorize", owner,
                                     {"pending_id": held[1]})
    assert (status, done["outcome"]) == (200, "executed"), done
    status, skills = await client.call("GET", "/api/skills", user)
    assert status == 200 and "hold_still" in skills["caps"]["invoke"]["params"]["skills"]
    # An AI's stop, and the thought it came from (§16.5).
    thought = {"action": "stop", "ai_provider": "p", "ai_model": "m", "thought_id": "t-1"}
    assert (await client.command(user, thought))["outcome"] == "executed"
    status, _ = await client.call("GET", "/api/thoughts/t-1", user,
                                  route="/api/thoughts/{thought_id}")
    assert status == 200
    # A goal far away (still driving at the signal, unless a move replaces it).
    goal = await client.command(user, {"action": "navigate",
                                       "params": {"x": 15.0, "y": 0.0, "yaw": 0.0}})
    assert goal["outcome"] == "executed", goal
    goal_id = goal["goal_id"]
    status, _ = await client.call("GET", f"/api/goals/{goal_id}", user,
                                  route="/api/goals/{goal_id}")
    assert status == 200
    status, page = await client.call("GET", "/api/audit?since=0", owner)
    assert status == 200 and page["entries"]
    status, report = await client.call("GET", "/api/audit/verify", owner)
    assert status == 200 and report["ok"], report
    status, export = await client.call("GET", "/api/v1/audit?format=jsonl", owner)
    assert status == 200 and '"type":"audit_export"' in export
    status, metrics = await client.call("GET", "/api/metrics", owner)  # after a command too
    assert status == 200 and "rcan" in metrics
    await visit_the_newer_routes(client, user)
    return goal_id


async def visit_the_newer_routes(client: Client, user: str) -> None:
    """The console's pages and tickets, the caller's own audit, the cameras and MCP."""
    for path, route in (("/", "/"), ("/console", "/console"), ("/console/", "/console/"),
                        ("/console/app.js", "/console/{name}"), ("/api/whoami", None),
                        ("/api/audit/mine?last=5", None), ("/api/images", None)):
        status, _ = await client.call("GET", path, user, route=route)
        assert status == 200, path
    status, _ = await client.call("POST", "/api/ws-ticket", user)
    assert status == 200
    status, _ = await client.call("GET", "/api/images/overhead", user,
                                  route="/api/images/{name}")
    assert status in (200, 503)  # a frame, or none yet
    mcp = {"Accept": "application/json, text/event-stream", "RCAN-AI-Model": "m"}
    status, opened = await client.call("POST", "/mcp", user, {
        "jsonrpc": "2.0", "id": 1, "method": "initialize", "params": {
            "protocolVersion": "2025-06-18", "capabilities": {},
            "clientInfo": {"name": "routes", "version": "1"}}}, headers=mcp)
    assert status == 200 and "result" in opened, opened
    session = {**mcp, "Mcp-Session-Id": client.last_headers["Mcp-Session-Id"],
               "Mcp-Protocol-Version": "2025-06-18"}
    status, _ = await client.call("GET", "/mcp", user, headers=mcp)  # no session: refused
    assert status == 400
    status, _ = await client.call("DELETE", "/mcp", user, headers=session)
    assert status == 200


def _served_routes(document: dict[str, Any]) -> set[tuple[str, str]]:
    return {(method, path) for path, ops in document["paths"].items() for method in ops}


# What drives the base at the signal: the goal, or a held move that replaced it (one arbiter:
# the move's stream cancels its sender's goal, so both never drive at once).
@pytest.mark.parametrize("driving", ["goal", "move"])
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
async def test_a_signal_after_every_route_stops_the_robot(
        tmp_path: Path, domain_id: int, jazzy_python: Path, sig: signal.Signals,
        driving: str) -> None:
    env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}  # the demo keeps to loopback
    with RclpyOracle(jazzy_python, "recorder", domain_id=domain_id, env=env) as robot:
        await robot.acall("subscribe", topic=CMD_VEL, type="geometry_msgs/msg/Twist")
        await robot.acall("subscribe", topic=GOAL_STATUS,
                          type="action_msgs/msg/GoalStatusArray")
        proc = RunProcess(["run", "--sim", "--port", "0", *state_args(tmp_path, "state")],
                          child_env(domain_id), demo=True)
        try:
            assert await robot.acall("wait_matched", topic=CMD_VEL, timeout=30.0) >= 1
            async with aiohttp.ClientSession() as http:
                client = Client(proc, http)
                _, document = await client.call("GET", "/api/openapi.json", proc.user)
                async with heartbeats(client, proc.user):
                    goal_id = await visit_every_route(client, proc)
                    assert client.visited == _served_routes(document), (
                        "routes not visited: "
                        f"{_served_routes(document) - client.visited}")
                    await eventually(lambda: _driving(client, goal_id), timeout=30,
                                     what="the goal executing")
                    move_id = None
                    if driving == "move":
                        move = await client.command(proc.user, {
                            "action": "move", "params": {"linear_x": SPEED}})
                        assert move["outcome"] == "executed", move
                        move_id = move["message_id"]
                        await eventually(lambda: _moving(robot), timeout=30,
                                         what=f"linear.x {SPEED} on {CMD_VEL}")
                    unblocked = dict(client.unblocked)
                    proc.signal(sig)
                rc = proc.wait(EXIT_TIMEOUT)
            assert rc == 0, f"rc={rc}\n{proc.output()}"
            # The bridge's own handler took it: the bounded graceful stop, not a default.
            proc.wait_for(rf"{sig.name}: shutting down", 5, stderr=True)
            assert not unblocked, f"threads taking SIGINT/SIGTERM after a route: {unblocked}"
            _assert_stopped_in_order(tmp_path / "state" / "audit.jsonl", move_id)
            # What reached the robot's reader before the bridge left (it waited for the
            # acknowledgement), handed to its callback maybe later: the rclpy executor's turn.
            twists: list[Any] = []

            async def last_is_zero() -> bool:
                twists.extend(await robot.acall("take", topic=CMD_VEL))
                return bool(twists) and twists[-1] == _ZERO_TWIST

            await eventually(last_is_zero, timeout=10,
                             what=lambda: f"zero velocity as the last Twist: {twists[-5:]}")
            # The server accepted the cancel (CANCELING); the sim, stopped right after the
            # bridge, may or may not have published CANCELED by then.
            states = _goal_states(await robot.acall("take", topic=GOAL_STATUS), goal_id)
            assert states[-1:] in ([CANCELING], [CANCELED]), states
        finally:
            proc.kill()


async def _arm_heard(client: Client) -> bool:
    status, body = await client.call("GET", "/api/status", client.proc.user)
    joints = body["telemetry"]["joints"] if status == 200 else None
    return bool(joints) and "elbow" in joints["names"]


async def _driving(client: Client, goal_id: str) -> bool:
    status, goal = await client.call("GET", f"/api/goals/{goal_id}", client.proc.user,
                                     route="/api/goals/{goal_id}")
    return status == 200 and goal["state"] == "executing"


async def _moving(robot: RclpyOracle) -> bool:
    return any(m["linear"]["x"] == SPEED for m in await robot.acall("take", topic=CMD_VEL))


_ZERO_TWIST = {"linear": {"x": 0.0, "y": 0.0, "z": 0.0},
               "angular": {"x": 0.0, "y": 0.0, "z": 0.0}}


def _goal_states(arrays: list[dict[str, Any]], goal_id: str) -> list[int]:
    """The statuses of `goal_id` in the order the action server published them."""
    wanted = list(uuid.UUID(goal_id).bytes)
    return [s["status"] for array in arrays for s in array["status_list"]
            if list(s["goal_info"]["goal_id"]["uuid"]) == wanted]


def _assert_stopped_in_order(audit: Path, move_id: str | None) -> None:
    entries = [json.loads(line) for line in audit.read_text().splitlines()]
    assert entries[-1]["event"] == "BRIDGE_STOPPED", entries[-3:]
    if move_id is None:
        return
    ended = [e for e in entries if e["event"] == "STREAM_ENDED"
             and e["message_id"] == move_id]
    assert [e["params"]["reason"] for e in ended] == ["bridge_stopped"], ended
