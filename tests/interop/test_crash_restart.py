"""A bridge killed mid-flight (SIGKILL) left its motion running with nobody governing it: an
arm's JointTrajectory runs on in its controller (the topic has no cancel, no timeout), a
navigation goal in its server. Restarted on the same state directory (`rcan-rtps run`, a
real process both times), the bridge takes that motion back before its ready line: each arm
held where joint_states says it is, each goal cancelled by its id, a zero velocity — and
records it (NETWORK_LOSS_SAFE_STOP, `applied.scope: crash`) right after its BRIDGE_STARTED.

The robot: an rclpy node (both RMWs) subscribed to the arm's trajectory topic and cmd_vel,
publishing joint_states; for the goal, a NavigateToPose server of our own on a participant
of its own (the rclpy oracle serves only Fibonacci) that records every cancel request."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
import uuid
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from oracle.client import OracleEnv, RclpyOracle, both_rmws
from waiting import eventually, take

from rcan_rtps.governance.audit import AuditEvent, AuditLog, AuditRecord
from rcan_rtps.governance.clock import ManualClock, system_boot
from rcan_rtps.ros.action_server import ActionServer, ServerGoal
from rcan_rtps.ros.participant import RosNode

from .run_process import RunProcess

TOKEN = "c" * 32
TRAJ = "trajectory_msgs/msg/JointTrajectory"
LEFT = "/robot1/left_arm/joint_trajectory"
JOINT_STATES, JOINT_STATE = "/robot1/joint_states", "sensor_msgs/msg/JointState"
CMD_VEL, TWIST = "/robot1/cmd_vel", "geometry_msgs/msg/Twist"
NAV = "nav2_msgs/action/NavigateToPose"
LONG = {"group": "left", "joints": ["l_shoulder", "l_elbow"], "positions": [1.0, 2.0],
        "duration_s": 600.0}
AT = [0.25, -0.5]  # where joint_states says the arm is


def _config(state: Path, domain_id: int, match_timeout_s: float = 10.0) -> str:
    return textwrap.dedent(f"""\
        robot:
          ruri: rcan://registry.local/acme/rover/unit-0001
          name: Crash Rover
        bridge:
          ros2:
            namespace: /robot1
            node_name: rcan_bridge
            domain_id: {domain_id}
            match_timeout_s: {match_timeout_s}
            arms:
              left: {{topic: left_arm/joint_trajectory, joints: [l_shoulder, l_elbow]}}
          api:
            auth_token_env: RCAN_BRIDGE_TOKEN
          safety:
            max_linear_vel: 1.5
            max_angular_vel: 1.0
            session_timeout_s: 3600
            workspace: [[-10, -10], [10, -10], [10, 10], [-10, 10]]
          audit:
            path: {state / "audit.jsonl"}
            key_path: {state / "audit.key"}
        """)


class Bridge:
    """`rcan-rtps run` on one config and state directory, started again after a SIGKILL."""

    def __init__(self, config: Path, state: Path) -> None:
        self.config, self.audit = config, state / "audit.jsonl"
        self.run: RunProcess | None = None

    async def start(self) -> RunProcess:
        """Started, once its ready line is out (waited for off the loop: the test's own
        peers answer on it meanwhile)."""
        env = {**os.environ, "RCAN_BRIDGE_TOKEN": TOKEN}
        args = ["run", "--config", str(self.config), "--port", "0", "--no-mdns"]
        self.run = await asyncio.to_thread(RunProcess, args, env, demo=False)
        return self.run

    def kill(self) -> None:
        assert self.run is not None
        self.run.kill()  # SIGKILL: no BRIDGE_STOPPED, no halt on the way out

    def close(self) -> None:
        if self.run is not None:
            self.run.stop()

    async def command(self, body: dict[str, Any]) -> dict[str, Any]:
        assert self.run is not None
        headers = {"Authorization": f"Bearer {TOKEN}"}
        async with aiohttp.ClientSession(headers=headers) as http, \
                http.post(self.run.url + "/api/command", json=body) as resp:
            answer: dict[str, Any] = await resp.json()
            assert resp.status == 200, answer
            return answer

    def entries(self) -> list[dict[str, Any]]:
        return [json.loads(line) for line in self.audit.read_text().splitlines()]



def took_back_in(entries: list[dict[str, Any]], scope: str = "crash") -> dict[str, Any]:
    """The entry of the last start's halt of a crashed run's motion (`scope` `stopped`:
    of the goals a clean stop left), checked to follow that start's BRIDGE_STARTED (nothing
    between them)."""
    starts = [i for i, e in enumerate(entries) if e["event"] == "BRIDGE_STARTED"]
    assert len(entries) > starts[-1] + 1, "nothing recorded after the last BRIDGE_STARTED"
    after = entries[starts[-1] + 1]
    assert (after["event"], after["applied"]["scope"]) == ("NETWORK_LOSS_SAFE_STOP",
                                                            scope), after
    return after


@pytest.fixture
def bridge(tmp_path: Path, domain_id: int) -> Iterator[Bridge]:
    yield from _bridge(tmp_path, _config(tmp_path / "state", domain_id))


@pytest.fixture
def default_bridge(tmp_path: Path, domain_id: int) -> Iterator[Bridge]:
    """With the default match_timeout_s (1 s) and crash_halt_wait_s."""
    config = "".join(line for line in _config(tmp_path / "state", domain_id).splitlines(True)
                     if "match_timeout_s" not in line)
    yield from _bridge(tmp_path, config)


def _bridge(tmp_path: Path, text: str) -> Iterator[Bridge]:
    state = tmp_path / "state"
    config = tmp_path / "robot.rcan.yaml"
    config.write_text(text)
    made = Bridge(config, state)
    try:
        yield made
    finally:
        made.close()


@pytest.fixture
async def robot(jazzy_oracle: OracleEnv, domain_id: int) -> AsyncIterator[RclpyOracle]:
    """The rclpy side: the left arm's trajectory topic and cmd_vel read, joint_states at
    50 Hz (the arm at rest at AT)."""
    with RclpyOracle(jazzy_oracle, "robot", "/robot1", domain_id=domain_id) as oracle:
        for topic, type_name in ((LEFT, TRAJ), (CMD_VEL, TWIST)):
            await oracle.acall("subscribe", topic=topic, type=type_name)
        await oracle.acall("publisher", topic=JOINT_STATES, type=JOINT_STATE)
        await oracle.acall("publish_periodic", topic=JOINT_STATES, type=JOINT_STATE, rate=50.0,
                           value={"name": ["l_shoulder", "l_elbow"], "position": AT,
                                  "velocity": [0.0, 0.0]})
        yield oracle


@both_rmws
async def test_a_restart_after_a_kill_holds_the_arm_it_left_moving(
        bridge: Bridge, robot: RclpyOracle) -> None:
    await bridge.start()
    moving = await bridge.command({"action": "arm_joint", "params": LONG})
    (sent,) = await take(robot, LEFT)
    assert sent["points"][0]["positions"] == [1.0, 2.0]
    bridge.kill()
    await robot.acall("take", topic=CMD_VEL)  # what the first run sent is not the point
    await bridge.start()
    written = bridge.entries()  # as the ready line came
    (hold,) = await take(robot, LEFT)
    assert hold["joint_names"] == ["l_shoulder", "l_elbow"]
    (point,) = hold["points"]
    assert point["positions"] == AT and point["velocities"] == [0.0, 0.0]
    assert point["time_from_start"] == {"sec": 0, "nanosec": 0}
    zeros = await take(robot, CMD_VEL)  # and a zero velocity, the first word
    assert zeros[0]["linear"] == {"x": 0.0, "y": 0.0, "z": 0.0}, zeros
    # The start awaited the hold before its ready line: its entry was written by then.
    took_back = took_back_in(written)
    assert took_back["outcome"] == "executed", took_back
    assert took_back["applied"]["arms_held"] == [LEFT]
    assert [a["message_id"] for a in took_back["applied"]["left"]["arms"]] == [
        moving["message_id"]]


async def test_a_restart_after_a_kill_with_the_arm_unheard_says_so(
        bridge: Bridge, robot: RclpyOracle) -> None:
    """joint_states stops with the bridge's death: the arm is not held at a guess; the entry
    fails, naming it."""
    await bridge.start()
    await bridge.command({"action": "arm_joint", "params": LONG})
    await take(robot, LEFT)
    bridge.kill()
    await robot.acall("stop_periodic", topic=JOINT_STATES)
    await bridge.start()
    took_back = took_back_in(bridge.entries())
    assert took_back["outcome"] == "failed", took_back
    [why] = took_back["applied"]["arms_not_held"]
    assert why.startswith(f"the arm on {LEFT} was not held: no joint_states heard"), why
    assert await robot.acall("take", topic=LEFT) == []  # nothing sent at a guess
    # Heard again, the next stop of this run holds it, as it would one of its own.
    await _heard_then_held_by_a_stop(bridge, robot)


class CancelRecordingServer(ActionServer):
    """Our NavigateToPose server, recording the goal id of every cancel request."""

    cancels: list[bytes]

    async def _on_cancel(self, request: Any) -> dict[str, Any]:
        self.cancels.append(bytes(request.goal_info.goal_id.uuid))
        return await super()._on_cancel(request)


async def _until_cancelled(goal: ServerGoal) -> dict[str, Any]:
    await goal.cancel_requested.wait()
    goal.canceled()
    return {}


@both_rmws
async def test_a_restart_after_a_kill_cancels_the_goal_it_left_by_its_id(
        bridge: Bridge, robot: RclpyOracle, domain_id: int) -> None:
    with RosNode("nav_robot", "/robot1", domain_id=domain_id) as node:
        server = CancelRecordingServer(node, "navigate_to_pose", NAV, _until_cancelled)
        server.cancels = []
        try:
            await bridge.start()
            sent = await bridge.command({"action": "navigate",
                                         "params": {"x": 3.0, "y": 0.0, "yaw": 0.0}})
            goal_id = uuid.UUID(sent["goal_id"]).bytes
            bridge.kill()
            await asyncio.sleep(0.5)  # a cancel would be on its way by now: none is
            assert server.cancels == []
            await bridge.start()
            # Awaited before the ready line: the server has answered it already.
            assert server.cancels == [goal_id]
            took_back = took_back_in(bridge.entries())
            assert took_back["applied"]["goals_cancelled"] == [sent["goal_id"]], took_back
            [dispatched] = [e for e in bridge.entries() if e.get("action_type") == "navigate"]
            assert dispatched["goal_id"] == sent["goal_id"]  # written ahead
            zeros = await take(robot, CMD_VEL)
            assert zeros[-1]["linear"]["x"] == 0.0
        finally:
            await server.close()


async def test_a_restart_waits_past_match_timeout_for_the_arm_s_joint_states(
        default_bridge: Bridge, robot: RclpyOracle) -> None:
    """On a busy board joint_states can take over a second to be heard after the restart
    joins the domain. Here they come only once the restart's take-back has waited longer
    than match_timeout_s (1 s): the take-back waits up to crash_halt_wait_s (5 s) and holds
    the arm. Before, it gave up at match_timeout_s: the arm not held at start."""
    bridge = default_bridge
    await bridge.start()
    # Its first command waits only match_timeout_s for the arm's topic and joints: on a busy
    # host, sent again until one is answered 200 (a 503 sent nothing).
    moving = await eventually(lambda: bridge.command({"action": "arm_joint", "params": LONG}),
                              what="the trajectory sent")
    await take(robot, LEFT)
    bridge.kill()
    await robot.acall("stop_periodic", topic=JOINT_STATES)
    restarting = asyncio.create_task(bridge.start())

    def started_again() -> bool:  # read as text: a line may be half written
        return bridge.audit.read_text().count('"event":"BRIDGE_STARTED"') == 2

    await eventually(started_again, timeout=60, what="the second BRIDGE_STARTED")
    # The take-back began before that entry; joint_states come past match_timeout_s.
    await asyncio.sleep(1.5)
    await robot.acall("publish_periodic", topic=JOINT_STATES, type=JOINT_STATE, rate=50.0,
                      value={"name": ["l_shoulder", "l_elbow"], "position": AT,
                             "velocity": [0.0, 0.0]})
    await restarting
    took_back = took_back_in(bridge.entries())
    assert took_back["outcome"] == "executed", took_back
    assert took_back["applied"]["arms_held"] == [LEFT]
    assert [a["message_id"] for a in took_back["applied"]["left"]["arms"]] == [
        moving["message_id"]]
    (hold,) = await take(robot, LEFT)
    assert hold["points"][0]["positions"] == AT, hold


async def _killed_while_taking_back(bridge: Bridge) -> None:
    """A start killed during its halt of what the crashed run left: its BRIDGE_STARTED is
    written (the halt began before it), the halt still waits for joint_states (unheard:
    up to match_timeout_s), no ready line yet."""
    env = {**os.environ, "RCAN_BRIDGE_TOKEN": TOKEN}
    args = [sys.executable, "-m", "rcan_rtps", "run", "--config", str(bridge.config),
            "--port", "0", "--no-mdns"]
    proc = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        def started_again() -> bool:  # read as text: a line may be half written
            return bridge.audit.read_text().count('"event":"BRIDGE_STARTED"') == 2

        await eventually(started_again, timeout=60, what="the second BRIDGE_STARTED")
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


async def test_a_start_killed_during_its_halt_leaves_it_to_the_next_start(
        bridge: Bridge, robot: RclpyOracle) -> None:
    """Killed right after its trajectory went out; restarted with the arm unheard (the halt
    waits for it) and killed again mid-halt; restarted with the arm heard: the third start
    holds it (from the second's BRIDGE_STARTED, `params.left_running`)."""
    await bridge.start()
    moving = await bridge.command({"action": "arm_joint", "params": LONG})
    await take(robot, LEFT)
    bridge.kill()
    await robot.acall("stop_periodic", topic=JOINT_STATES)
    await _killed_while_taking_back(bridge)
    entries = bridge.entries()
    assert entries[-1]["event"] == "BRIDGE_STARTED", entries[-1]  # nothing of the halt
    assert await robot.acall("take", topic=LEFT) == []  # nothing sent at a guess
    await robot.acall("publish_periodic", topic=JOINT_STATES, type=JOINT_STATE, rate=50.0,
                      value={"name": ["l_shoulder", "l_elbow"], "position": AT,
                             "velocity": [0.0, 0.0]})
    await bridge.start()
    (hold,) = await take(robot, LEFT)
    assert hold["points"][0]["positions"] == AT, hold
    took_back = took_back_in(bridge.entries())
    assert took_back["outcome"] == "executed", took_back
    assert [a["message_id"] for a in took_back["applied"]["left"]["arms"]] == [
        moving["message_id"]]


async def test_an_arm_left_stamped_ahead_of_the_clock_is_kept_no_longer_than_it_runs(
        bridge: Bridge, robot: RclpyOracle) -> None:
    """A board without a clock of its own comes up after a power cut with the time it last
    saved (fake-hwclock: up to an hour behind the entries the crashed run wrote). A left
    trajectory of 1 s, stamped an hour ahead of that clock, is due for the scan (fail closed);
    unheard at start, it is kept for the next stop to hold — but no longer than it can run:
    1 s, not the hour the clock is behind. Before, every stop failed (503, the arm not held)
    for that hour while joint_states stayed silent."""
    await robot.acall("stop_periodic", topic=JOINT_STATES)
    ahead = ManualClock(time.time() + 3600)
    log = await AuditLog.open(bridge.audit, bridge.audit.parent / "audit.key",
                              ruri="rcan://registry.local/acme/rover/unit-0001", clock=ahead)
    await log.append(AuditRecord(event=AuditEvent.BRIDGE_STARTED,
                                 params={"estop_latched": False, "locks": {}}))
    short = {**LONG, "duration_s": 1.0}
    await log.append(AuditRecord(
        event=AuditEvent.COMMAND_DISPATCHED, principal="operator", role="USER",
        message_id=str(uuid.uuid4()), action_type="arm_joint", params=short, applied=short,
        outcome="executed", ros2_topic=LEFT))
    await log.close()  # no BRIDGE_STOPPED: a crash
    await bridge.start()
    took_back = took_back_in(bridge.entries())
    assert took_back["outcome"] == "failed", took_back  # unheard: not held at a guess
    await asyncio.sleep(1.0 + 1.0)  # its time (and settling) is over by now, whatever the clock
    stopped = await bridge.command({"action": "stop"})
    assert stopped["outcome"] == "executed", stopped


async def _crashed_an_hour_ago_by_the_wall_clock(bridge: Bridge) -> str:
    """The log of a run killed just now, in this boot, with a trajectory of 600 s running,
    written as if the wall clock had been set forward an hour since (NTP's first sync,
    `date -s`): by its wall time it ended long ago; its boot stamp (this boot's, read now)
    says it was sent just now."""
    boot = system_boot()
    assert boot is not None  # Linux: CLOCK_BOOTTIME and a boot id
    behind = ManualClock(time.time() - 3600)
    log = await AuditLog.open(bridge.audit, bridge.audit.parent / "audit.key",
                              ruri="rcan://registry.local/acme/rover/unit-0001", clock=behind)
    await log.append(AuditRecord(event=AuditEvent.BRIDGE_STARTED,
                                 params={"estop_latched": False, "locks": {}}))
    message_id = str(uuid.uuid4())
    await log.append(AuditRecord(
        event=AuditEvent.COMMAND_DISPATCHED, principal="operator", role="USER",
        message_id=message_id, action_type="arm_joint", params=LONG, applied=LONG,
        outcome="executed", ros2_topic=LEFT, boot={"boot_id": boot.boot_id, "ms": boot.ms}))
    await log.close()  # no BRIDGE_STOPPED: a crash
    return message_id


async def test_a_wall_clock_set_forward_across_the_restart_drops_no_arm(
        bridge: Bridge, robot: RclpyOracle) -> None:
    """The real boot clock (the bridge's process reads CLOCK_BOOTTIME and the boot id):
    the trajectory still has ten minutes to run, so it is held, whatever the wall clock
    says. Before, it was judged ended and left to run."""
    message_id = await _crashed_an_hour_ago_by_the_wall_clock(bridge)
    await bridge.start()
    took_back = took_back_in(bridge.entries())
    assert took_back["outcome"] == "executed", took_back
    assert took_back["applied"]["arms_held"] == [LEFT]
    assert [a["message_id"] for a in took_back["applied"]["left"]["arms"]] == [message_id]
    (hold,) = await take(robot, LEFT)
    assert hold["points"][0]["positions"] == AT, hold


async def _heard_then_held_by_a_stop(bridge: Bridge, robot: RclpyOracle) -> None:
    """The left arm's joint_states heard again: a stop holds it where they say. Until the
    bridge has heard them, a stop answers 503 naming the arm: sent again until one is 200."""
    await robot.acall("publish_periodic", topic=JOINT_STATES, type=JOINT_STATE, rate=50.0,
                      value={"name": ["l_shoulder", "l_elbow"], "position": AT,
                             "velocity": [0.0, 0.0]})
    stopped = await eventually(lambda: bridge.command({"action": "stop"}),
                               what="a stop answered 200 once joint_states are heard")
    assert stopped["outcome"] == "executed", stopped
    (hold,) = await take(robot, LEFT)
    assert hold["points"][0]["positions"] == AT, hold


async def test_an_arm_unheard_after_a_wall_clock_step_is_kept_for_the_next_stop(
        bridge: Bridge, robot: RclpyOracle) -> None:
    """Unheard at start, that arm is kept for the next stop to hold for what is left of its
    time by the boot clock (before: by the wall clock, nothing, so no stop held it)."""
    await robot.acall("stop_periodic", topic=JOINT_STATES)
    await _crashed_an_hour_ago_by_the_wall_clock(bridge)
    await bridge.start()
    took_back = took_back_in(bridge.entries())
    assert took_back["outcome"] == "failed", took_back  # unheard: not held at a guess
    await asyncio.sleep(2.0)  # past the settling second any arm of ours is kept for
    await _heard_then_held_by_a_stop(bridge, robot)


class HeldAcceptServer(CancelRecordingServer):
    """Accepts each goal only once `release` is set (a busy server: the bridge's send gives
    up first); its goals run until cancelled (`running`: their ids, until then)."""

    def __init__(self, node: RosNode) -> None:
        self.release = asyncio.Event()
        self.cancels = []
        self.running: set[bytes] = set()
        self.ended: dict[bytes, str] = {}  # how each goal that ran ended
        super().__init__(node, "navigate_to_pose", NAV, self._until_cancelled,
                         accept=self._accept_late)

    async def _accept_late(self, goal: Any) -> bool:
        await self.release.wait()
        return True

    async def _until_cancelled(self, goal: ServerGoal) -> dict[str, Any]:
        self.running.add(goal.goal_id)
        try:
            result = await _until_cancelled(goal)
            self.ended[goal.goal_id] = "canceled"
            return result
        finally:
            self.running.discard(goal.goal_id)


async def _navigate(run: Any) -> dict[str, Any]:
    """The answer to a navigate sent to `run`."""
    headers = {"Authorization": f"Bearer {TOKEN}"}
    async with aiohttp.ClientSession(headers=headers) as http, \
            http.post(run.url + "/api/command", json={
                "action": "navigate", "params": {"x": 3.0, "y": 0.0, "yaw": 0.0},
            }) as resp:
        answer: dict[str, Any] = await resp.json()
    return answer


async def _given_up_navigate(bridge: Bridge, run: Any) -> tuple[dict[str, Any], bytes]:
    """A navigate whose send gives up (the server holds it past match_timeout_s): its
    COMMAND_FAILED entry, and its goal's id."""
    answer = await _navigate(run)
    assert answer["outcome"] == "failed", answer
    [failed] = [e for e in bridge.entries() if e["event"] == "COMMAND_FAILED"]
    assert "goal_id" in failed, failed  # it may run
    return failed, uuid.UUID(failed["goal_id"]).bytes


async def test_a_clean_stop_during_a_late_goal_s_watch_leaves_it_to_the_next_start(
        bridge: Bridge, robot: RclpyOracle, domain_id: int) -> None:
    """Stopped (SIGTERM) while a goal whose send gave up is watched, its server not having
    accepted it yet: the stop's server-wide cancel cannot reach it, and the watch ends with
    the process. BRIDGE_STOPPED names it (`params.left_running`), and the next start cancels
    it by id before it serves. Before, the stop was clean and left it running."""
    with RosNode("nav_robot", "/robot1", domain_id=domain_id) as node:
        server = HeldAcceptServer(node)
        try:
            run = await bridge.start()
            failed, goal = await _given_up_navigate(bridge, run)
            assert run.stop() == 0
            stopped = bridge.entries()[-1]
            assert stopped["event"] == "BRIDGE_STOPPED", stopped
            [left] = stopped["params"]["left_running"]["goals"]
            assert (left["goal_id"], left["message_id"]) == (failed["goal_id"],
                                                             failed["message_id"]), left
            server.release.set()
            await eventually(lambda: goal in server.running, what="the late goal running")
            await bridge.start()
            took_back = took_back_in(bridge.entries(), scope="stopped")
            assert took_back["applied"]["goals_cancelled"] == [failed["goal_id"]], took_back
            await eventually(lambda: goal not in server.running,
                             what="the late goal cancelled")
        finally:
            await server.close()


async def test_a_clean_stop_after_a_goal_s_server_vanished_leaves_the_goal_to_the_next_start(
        bridge: Bridge, robot: RclpyOracle, domain_id: int) -> None:
    """A goal was running when its server's participant vanished (a partition, a crashed
    nav stack: no end of it said): the bridge finds it `lost`, and a clean stop's
    server-wide cancel finds no server. A server that comes back with it runs it with
    nobody to cancel it: BRIDGE_STOPPED names it (`params.left_running`), and the next
    start tries to cancel it by id. Before, the stop named nothing and the start tried
    nothing (red team 17)."""
    node = RosNode("nav_robot", "/robot1", domain_id=domain_id)
    server = HeldAcceptServer(node)
    server.release.set()  # accepted at once, running until cancelled
    try:
        run = await bridge.start()
        answer = await _navigate(run)
        assert answer["outcome"] == "executed", answer
        [dispatched] = [e for e in bridge.entries() if e.get("action_type") == "navigate"]
        goal_id = dispatched["goal_id"]
        await eventually(lambda: uuid.UUID(goal_id).bytes in server.running,
                         what="the goal running")
        node.close()  # its participant gone, the goal's end never said
        await eventually(lambda: [e for e in bridge.entries() if e["event"] == "GOAL_FINISHED"
                                  and e["params"]["goal_id"] == goal_id],
                         timeout=30, what="the goal lost")
        assert run.stop() == 0
        stopped = bridge.entries()[-1]
        assert stopped["event"] == "BRIDGE_STOPPED", stopped
        [left] = stopped["params"]["left_running"]["goals"]
        assert (left["goal_id"], left["message_id"]) == (goal_id, answer["message_id"]), left
        await bridge.start()
        took_back = took_back_in(bridge.entries(), scope="stopped")
        assert goal_id in json.dumps(took_back["applied"]), took_back
    finally:
        with contextlib.suppress(Exception):  # (its node is gone: closing says so)
            await server.close()
        node.close()


async def test_a_restart_after_a_kill_during_a_late_goal_s_watch_cancels_it(
        bridge: Bridge, robot: RclpyOracle, domain_id: int) -> None:
    """The goal's send gave up (no answer within match_timeout_s: its command failed) and
    the bridge was killed while it watched for the server accepting it late. The server then
    accepts it: it runs with nobody governing it. Before, the restart took the command's
    COMMAND_FAILED for the goal's end and left it running; now the COMMAND_FAILED names the
    goal (it may run) and the restart cancels it by id."""
    with RosNode("nav_robot", "/robot1", domain_id=domain_id) as node:
        server = HeldAcceptServer(node)
        try:
            failed, goal = await _given_up_navigate(bridge, await bridge.start())
            [dispatched] = [e for e in bridge.entries() if e.get("action_type") == "navigate"
                            and e["event"] == "COMMAND_DISPATCHED"]
            assert failed["goal_id"] == dispatched["goal_id"], failed  # it may run
            bridge.kill()  # mid-watch: its late cancel dies with it
            server.release.set()
            await eventually(lambda: goal in server.running, what="the late goal running")
            await bridge.start()
            # Awaited before the ready line: the server is canceling it by then.
            took_back = took_back_in(bridge.entries())
            assert took_back["applied"]["goals_cancelled"] == [failed["goal_id"]], took_back
            await eventually(lambda: goal not in server.running,
                             what="the late goal cancelled")
        finally:
            await server.close()


async def test_a_restart_watches_a_goal_left_that_its_server_accepts_after_the_restart(
        bridge: Bridge, robot: RclpyOracle, domain_id: int) -> None:
    """Killed during a late-goal watch, and the server still holds the request when the
    restart takes back what the run left: its cancel by id finds nothing. The restart
    watches for the goal as its own send that gave up: accepted after the ready line, it
    is cancelled and audited (GOAL_FINISHED, with the failed command). Before, it ran on."""
    with RosNode("nav_robot", "/robot1", domain_id=domain_id) as node:
        server = HeldAcceptServer(node)
        try:
            failed, goal = await _given_up_navigate(bridge, await bridge.start())
            bridge.kill()
            await bridge.start()
            took_back = took_back_in(bridge.entries())
            [why] = took_back["applied"]["goals_not_cancelled"]
            assert why.startswith(failed["goal_id"]), why
            server.release.set()
            await eventually(lambda: server.ended.get(goal) == "canceled", timeout=20,
                             what="the late goal cancelled")

            def finished() -> dict[str, Any] | None:
                return next((e for e in bridge.entries() if e["event"] == "GOAL_FINISHED"
                             and e["params"]["goal_id"] == failed["goal_id"]), None)

            entry = await eventually(finished, what="its GOAL_FINISHED")
            assert (entry["outcome"], entry["message_id"]) == (
                "canceled", failed["message_id"]), entry
        finally:
            await server.close()
