"""A goal whose send gave up must not run: red team 15 found that a navigation goal sent to a
busy server (no answer within the send's timeout: its command answered failed) could still be
accepted afterwards, and then ran with nothing governing it — no handle for a stop's own
cancel, not in the bridge's goals, ended by its COMMAND_FAILED in a restart's replay.

The robot side is a NavigateToPose server of our own (Cyclone mapping) whose accept waits
until the test lets it go: the goal is accepted only after the bridge gave up on it. Its
goals run until cancelled; it records the goal id of every cancel request. And an rclpy Jazzy
Fibonacci server (both RMWs) that answers each goal request only after the timeout."""

from __future__ import annotations

import asyncio
import contextlib
import json
import uuid
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from oracle.client import OracleEnv, RclpyOracle, both_rmws
from waiting import eventually

from rcan_rtps.bridge.navigation import GoalTracker
from rcan_rtps.bridge.sent_goals import GoalFinished
from rcan_rtps.governance.audit import AuditEvent, AuditLog, AuditRecord
from rcan_rtps.governance.left import LeftArm, LeftGoal, LeftRunning
from rcan_rtps.ros import action_goals
from rcan_rtps.ros.action_goals import MAX_GIVEN_UP
from rcan_rtps.ros.action_server import ActionServer, ServerGoal
from rcan_rtps.ros.errors import ActionError, WireError
from rcan_rtps.ros.participant import RosNode

from .bridge_rig import AGENT, NAV, Rig, bridge_config, close_rig, make_rig, nav_tracker


class SlowServer(ActionServer):
    """Accepts each goal only once `release` is set; records the goal ids it was sent, the
    cancels it got, and how each goal ended."""

    def __init__(self, node: RosNode) -> None:
        self.release = asyncio.Event()
        self.sent: list[bytes] = []
        self.cancels: list[bytes] = []
        self.ended: dict[bytes, str] = {}
        super().__init__(node, "navigate_to_pose", NAV, self._until_cancelled,
                         accept=self._accept_late)

    async def _accept_late(self, goal: Any) -> bool:
        await self.release.wait()
        return True

    async def _on_send_goal(self, request: Any) -> dict[str, Any]:
        self.sent.append(bytes(request.goal_id.uuid))
        return await super()._on_send_goal(request)

    async def _on_cancel(self, request: Any) -> dict[str, Any]:
        self.cancels.append(bytes(request.goal_info.goal_id.uuid))
        return await super()._on_cancel(request)

    async def _until_cancelled(self, goal: ServerGoal) -> dict[str, Any]:
        self.ended[goal.goal_id] = "running"
        await goal.cancel_requested.wait()
        goal.canceled()
        self.ended[goal.goal_id] = "canceled"
        return {}


@pytest.fixture
async def slow(tmp_path: Path, jazzy_python: Path,
               domain_id: int) -> AsyncIterator[tuple[Rig, SlowServer]]:
    # match_timeout_s: 3.0 is the goal send's timeout
    config = bridge_config(tmp_path, domain_id)
    with RosNode("nav_robot", "/robot1", domain_id=domain_id) as robot_node:
        server = SlowServer(robot_node)
        rig = await make_rig(config, jazzy_python, domain_id, navigation=True)
        heartbeat = asyncio.create_task(_hold_session(rig))
        try:
            await eventually(nav_tracker(rig).client.server_present,
                             what="the NavigateToPose server")
            yield rig, server
        finally:
            heartbeat.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await heartbeat
            server.release.set()
            await close_rig(rig)
            await server.close()


async def _hold_session(rig: Rig) -> None:
    while True:
        rig.governor.heartbeat(AGENT)
        await asyncio.sleep(0.2)


def _finished(rig: Rig, goal_id: str) -> dict[str, Any] | None:
    for entry in rig.entries():
        if entry["event"] == "GOAL_FINISHED" and entry["params"]["goal_id"] == goal_id:
            return entry
    return None


async def test_a_goal_accepted_after_its_send_timed_out_is_cancelled_and_audited(
        slow: tuple[Rig, SlowServer]) -> None:
    rig, server = slow
    decision = await rig.command(AGENT, {"action": "navigate",
                                         "params": {"x": 3.0, "y": 0.0, "yaw": 0.0}})
    assert decision.http_status != 200, decision  # no answer within the send's timeout
    [failed] = [e for e in rig.entries() if e["event"] == "COMMAND_FAILED"]
    assert failed["message_id"] == decision.message_id
    [goal] = server.sent
    goal_id = str(uuid.UUID(bytes=goal))
    # The bridge cancels it at once; the server, not having it yet, cancels nothing.
    await eventually(lambda: goal in server.cancels, what="a cancel of the goal given up")
    server.release.set()  # the busy server gets to it at last: accepted
    await eventually(lambda: server.ended.get(goal) == "canceled", timeout=20,
                     what=lambda: f"the late goal cancelled (now {server.ended.get(goal)})")
    assert server.cancels.count(goal) >= 2  # again, once the status topic listed it
    entry = await eventually(lambda: _finished(rig, goal_id), what="its GOAL_FINISHED")
    assert entry["outcome"] == "canceled", entry
    assert entry["message_id"] == decision.message_id  # the failed command that sent it
    assert "after its send had given up" in entry["deny_reason"], entry
    assert rig.goals is not None and rig.goals.active() == []
    view = rig.goals.goal(goal_id)
    assert view is not None and view.state == "canceled", view


async def test_a_goal_whose_send_was_cancelled_is_cancelled_once_accepted(
        slow: tuple[Rig, SlowServer]) -> None:
    """The send's caller went away (its task cancelled) while the server held the request."""
    rig, server = slow
    tracker = nav_tracker(rig)
    goal = {"pose": {"header": {"frame_id": "map"},
                     "pose": {"position": {"x": 3.0}, "orientation": {"w": 1.0}}}}
    sending = asyncio.create_task(tracker.send(goal, timeout=60.0, message_id="m-1",
                                               command="navigate"))
    [sent] = await eventually(lambda: server.sent, what="the goal request at the server")
    sending.cancel()
    with pytest.raises(asyncio.CancelledError):
        await sending
    server.release.set()
    await eventually(lambda: server.ended.get(sent) == "canceled", timeout=20,
                     what=lambda: f"the late goal cancelled (now {server.ended.get(sent)})")
    assert sent in server.cancels


FIB = "test_msgs/action/Fibonacci"


@both_rmws
async def test_a_goal_an_rclpy_server_accepts_after_the_send_timed_out_is_cancelled(
        jazzy_oracle: OracleEnv, domain_id: int, jazzy_share: Path) -> None:
    with RclpyOracle(jazzy_oracle, "fib_server", "/", domain_id=domain_id) as oracle, \
            RosNode("rcan_late", "/", domain_id=domain_id, distro="jazzy",
                    idl_paths=[jazzy_share]) as node:
        # answers each goal request 4 s late; its goals run 80 s unless cancelled
        await oracle.acall("action_server", name="/fib", mode="slow", accept_after=4.0)
        tracker = GoalTracker(node, "/fib", FIB)
        ended: list[GoalFinished] = []
        tracker.events.goal_finished.subscribe(ended.append)
        try:
            await tracker.client.wait_for_server(20.0)
            goal_id = str(uuid.uuid4())
            with pytest.raises(WireError, match="no reply within the timeout"):
                await tracker.send({"order": 400}, timeout=1.0, message_id="m-late",
                                   goal_id=goal_id)
            [end] = await eventually(lambda: ended, timeout=30, what="the late goal's end")
            assert (end.view.goal_id, end.view.state, end.message_id) == (
                goal_id, "canceled", "m-late"), end
            assert end.view.detail is not None and "cancelled by the bridge" in end.view.detail
        finally:
            await tracker.close()


GOAL = {"pose": {"header": {"frame_id": "map"},
                 "pose": {"position": {"x": 3.0}, "orientation": {"w": 1.0}}}}


@contextlib.asynccontextmanager
async def slow_server_and_tracker(domain_id: int) -> AsyncIterator[tuple[SlowServer,
                                                                        GoalTracker]]:
    """A SlowServer on its own node and a GoalTracker of it on another, the server found."""
    with RosNode("nav_robot", "/robot1", domain_id=domain_id) as robot_node, \
            RosNode("rcan_tracker", "/", domain_id=domain_id) as node:
        server = SlowServer(robot_node)
        tracker = GoalTracker(node, "/robot1/navigate_to_pose", NAV)
        try:
            await tracker.client.wait_for_server(20.0)
            yield server, tracker
        finally:
            server.release.set()
            await tracker.close()
            await server.close()


async def test_past_the_watch_s_bound_a_goal_is_not_sent_and_none_is_let_go_of(
        domain_id: int, caplog: pytest.LogCaptureFixture) -> None:
    """MAX_GIVEN_UP sends gave up on a server that holds every request: each is watched. The
    next goal is refused before its request goes out, saying why; before, it was sent, and
    the oldest watched goal was let go of — accepted late, it ran on with nobody to cancel
    it but a stop. Sent all at once, the ones past the bound are refused too (a send on its
    way holds a place: before, all went out and ~80 were watched). Released, the server
    accepts every one it got: each is cancelled."""
    async with slow_server_and_tracker(domain_id) as (server, tracker):
        over = 8
        outcomes = await asyncio.gather(*(
            tracker.send(GOAL, timeout=2.0, message_id=f"m-{n}")
            for n in range(MAX_GIVEN_UP + over)), return_exceptions=True)
        assert all(isinstance(e, WireError) for e in outcomes), outcomes
        refused = [e for e in outcomes if "sends are on their way" in str(e)]
        assert (len(outcomes) - len(refused), len(refused)) == (MAX_GIVEN_UP, over)
        assert len(server.sent) == MAX_GIVEN_UP
        with pytest.raises(ActionError, match=f"{MAX_GIVEN_UP} goals whose send gave up"):
            await tracker.send(GOAL, timeout=2.0, message_id="m-over")
        assert len(server.sent) == MAX_GIVEN_UP  # its request never went out
        assert "no longer watched" not in caplog.text
        server.release.set()
        await eventually(lambda: len(server.ended) == MAX_GIVEN_UP, timeout=30,
                         what=lambda: f"{len(server.ended)} accepted")
        await eventually(
            lambda: all(state == "canceled" for state in server.ended.values()),
            timeout=30, what=lambda: f"all cancelled: {sorted(server.ended.values())}")


async def test_a_goal_accepted_after_its_watch_ended_is_cancelled_when_listed(
        domain_id: int, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    """The server accepts a given-up goal only after its watch ended (here 1 s, the send's
    timeout; in a run at least LATE_WATCH_S): cancelled as soon as the status topic lists
    it running (before: it ran on until a stop), and the tracker told of it as a late goal
    (which a bridge audits: GOAL_FINISHED)."""
    monkeypatch.setattr(action_goals, "LATE_WATCH_S", 0.5)
    async with slow_server_and_tracker(domain_id) as (server, tracker):
        with pytest.raises(WireError):
            await tracker.send(GOAL, timeout=1.0, message_id="m-unseen")
        [goal] = server.sent
        await eventually(lambda: not tracker.client.watching_late(goal), timeout=20,
                         what="the watch's end")
        server.release.set()  # accepted now, after the watch
        await eventually(lambda: server.ended.get(goal) == "canceled", timeout=30,
                         what=lambda: f"the goal cancelled (now {server.ended.get(goal)})")
        told = f"goal {uuid.UUID(bytes=goal)} (command m-unseen): accepted by"
        await eventually(lambda: told in caplog.text, timeout=30, what="the late goal told")
        assert "cancelled by the bridge; ended canceled" in caplog.text


async def test_a_stop_during_a_watch_leaves_the_watched_goal_cancelled(
        slow: tuple[Rig, SlowServer], caplog: pytest.LogCaptureFixture) -> None:
    """A stop (a server-wide cancel: the server has nothing yet) while a goal whose send
    gave up is watched: the stop is answered, the watch goes on, and the goal, accepted
    after the stop, is cancelled and audited; nothing raises."""
    rig, server = slow
    decision = await rig.command(AGENT, {"action": "navigate",
                                         "params": {"x": 3.0, "y": 0.0, "yaw": 0.0}})
    assert decision.http_status != 200, decision
    [goal] = server.sent
    stopped = await rig.command(AGENT, {"action": "stop"})
    assert stopped.audit_id is not None, stopped  # answered and audited
    server.release.set()
    await eventually(lambda: server.ended.get(goal) == "canceled", timeout=20,
                     what=lambda: f"the late goal cancelled (now {server.ended.get(goal)})")
    entry = await eventually(lambda: _finished(rig, str(uuid.UUID(bytes=goal))),
                             what="its GOAL_FINISHED")
    assert entry["outcome"] == "canceled", entry
    errors = [r for r in caplog.records if r.levelname in ("ERROR", "CRITICAL")]
    assert errors == [], [r.getMessage() for r in errors]


async def _refuse(goal: Any) -> bool:
    return False


async def test_a_goal_its_server_refused_is_not_named_by_its_command_s_failure(
        tmp_path: Path, jazzy_python: Path, domain_id: int) -> None:
    """The counterpart: a goal the server refused cannot run. Its COMMAND_FAILED names no
    goal (a restart after a crash takes nothing back for it), as one whose send gave up
    does (test_crash_restart)."""
    config = bridge_config(tmp_path, domain_id)
    with RosNode("nav_robot", "/robot1", domain_id=domain_id) as robot_node:
        server = SlowServer(robot_node)
        server._accept = _refuse
        rig = await make_rig(config, jazzy_python, domain_id, navigation=True)
        try:
            await eventually(nav_tracker(rig).client.server_present,
                             what="the NavigateToPose server")
            rig.governor.heartbeat(AGENT)
            decision = await rig.command(AGENT, {"action": "navigate",
                                                 "params": {"x": 3.0, "y": 0.0, "yaw": 0.0}})
            assert decision.http_status != 200, decision
            [failed] = [e for e in rig.entries() if e["event"] == "COMMAND_FAILED"]
            assert "rejected" in failed["deny_reason"], failed
            assert failed.get("goal_id") is None, failed
        finally:
            await close_rig(rig)
            await server.close()


async def test_a_crashed_run_s_goal_id_that_is_no_uuid_fails_nothing_at_the_restart(
        tmp_path: Path, jazzy_python: Path, domain_id: int,
        caplog: pytest.LogCaptureFixture) -> None:
    """Red team 16: a goal id in the log that is no UUID (another version's entry, a damaged
    one) made the restart's take-back raise (ValueError turning it into bytes, in the watch
    for its late acceptance): the whole take-back was recorded not done — its arms, its
    zero — with a traceback, and again at every start. Now that goal cannot be named: every
    goal of its server is cancelled (here it had none), and nothing raises."""
    config = bridge_config(tmp_path, domain_id)
    audit = await AuditLog.open(config.bridge.audit.path, config.bridge.audit.key_path)
    await audit.append(AuditRecord(event=AuditEvent.BRIDGE_STARTED,
                                   params={"estop_latched": False, "locks": {}}))
    params = {"x": 3.0, "y": 0.0, "yaw": 0.0}
    await audit.append(AuditRecord(
        event=AuditEvent.COMMAND_DISPATCHED, principal=AGENT.name, role="USER",
        message_id="nav-1", action_type="navigate", params=params, applied=params,
        outcome="executed", ros2_topic="/robot1/navigate_to_pose", goal_id="not-a-uuid"))
    await audit.close()  # killed: no BRIDGE_STOPPED
    with RosNode("nav_robot", "/robot1", domain_id=domain_id) as robot_node:
        server = SlowServer(robot_node)
        server.release.set()
        rig = await make_rig(config, jazzy_python, domain_id, navigation=True)
        try:
            [took_back] = [e for e in rig.entries() if e["event"] == "NETWORK_LOSS_SAFE_STOP"]
            applied = took_back["applied"]
            assert applied["scope"] == "crash", took_back
            assert "ValueError" not in json.dumps(took_back), took_back
            assert applied["left"]["goals"][0]["goal_id"] is None, took_back
            # (No e-stop state file beside this log: the start is latched, logged as ERROR.)
            tracebacks = [r for r in caplog.records if r.exc_info]
            assert tracebacks == [], [r.getMessage() for r in tracebacks]
        finally:
            await close_rig(rig)
            await server.close()


async def test_a_take_back_whose_goal_part_raises_keeps_what_the_arm_part_found(
        slow: tuple[Rig, SlowServer]) -> None:
    """The take-back's parts (the zero, the goals, the arms) run side by side; one that
    raises is reported for its own motion alone. Before, a goal whose cancel raised (a goal
    id that is no UUID, handed on unchecked) made the whole take-back raise: the arms' own
    outcome was lost, recorded as the goal's exception."""
    rig, _ = slow
    left = LeftRunning(
        goals=[LeftGoal(message_id="nav-1", action="navigate", principal=None, server=None,
                        goal_id="not-a-uuid")],
        arms=[LeftArm(message_id="arm-1", action="arm_joint", principal=None,
                      topic="/robot1/gone_arm/joint_trajectory", params={},
                      joints=["elbow"], sent_at_ms=0, runs_for_s=600.0)])
    halted = await rig.dispatcher.halt_left(left)
    [why_goal] = halted.goals_not_cancelled
    assert "ValueError" in why_goal, halted
    [why_arm] = halted.arms.not_held
    assert "ValueError" not in why_arm and "gone_arm" in why_arm, halted
    assert set(halted.still_left) == {"nav-1", "arm-1"}, halted
