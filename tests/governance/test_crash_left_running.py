"""A run that did not end with BRIDGE_STOPPED (SIGKILL, out of memory, power) left the motion
it started running with nobody governing it: an arm's trajectory runs on in its controller (up
to an hour), a goal in its server. `resume` lists it from the signed log, less what a later
entry shows ended; a start takes it back (`Dispatcher.halt_left`) and records that in one
NETWORK_LOSS_SAFE_STOP of scope `crash`, after its BRIDGE_STARTED. A clean stop leaves nothing.

The logs are built with the audit writer itself (signed, chained), entry by entry."""

from __future__ import annotations

import asyncio
import json
import tracemalloc
import uuid
from pathlib import Path
from typing import Any

import msgspec
from govhelpers import PLANNER, RURI, Harness, command
from waiting import eventually

from rcan_rtps.governance.audit import AuditEvent, AuditLog, AuditRecord
from rcan_rtps.governance.clock import ManualClock
from rcan_rtps.governance.left import SETTLING_S, LeftGoal
from rcan_rtps.governance.resume import point_path, resume
from rcan_rtps.rcan import Outcome

ARM_TOPIC = "/robot1/left_arm/joint_trajectory"
NAV = "/robot1/navigate_to_pose"
LONG = {"group": "left", "joints": ["l_shoulder", "l_elbow"], "positions": [1.0, 2.0],
        "duration_s": 60.0}


class Log:
    """A signed log written entry by entry, on a manual clock."""

    def __init__(self, path: Path, clock: ManualClock, audit: AuditLog) -> None:
        self.path, self.clock, self.audit = path, clock, audit

    @classmethod
    async def open(cls, tmp: Path, clock: ManualClock) -> Log:
        path = tmp / "audit.jsonl"
        return cls(path, clock, await AuditLog.open(path, tmp / "audit.key", ruri=RURI,
                                                    clock=clock))

    async def add(self, event: AuditEvent, **fields: Any) -> None:
        await self.audit.append(AuditRecord(event=event, **fields))

    async def started(self) -> None:
        await self.add(AuditEvent.BRIDGE_STARTED, params={"estop_latched": False, "locks": {}})

    async def arm(self, message_id: str, params: dict[str, Any] = LONG) -> None:
        await self.add(AuditEvent.COMMAND_DISPATCHED, principal="planner", role="USER",
                       message_id=message_id, action_type="arm_joint", params=params,
                       applied=params, outcome="executed", ros2_topic=ARM_TOPIC)

    async def goal(self, message_id: str, goal_id: str | None) -> None:
        params = {"x": 1.0, "y": 2.0, "yaw": 0.0}
        await self.add(AuditEvent.COMMAND_DISPATCHED, principal="planner", role="USER",
                       message_id=message_id, action_type="navigate", params=params,
                       applied=params, outcome="executed", ros2_topic=NAV, goal_id=goal_id)

    async def move(self, message_id: str, replaces: str | None = None) -> None:
        """A held velocity stream; `replaces`: the stream its entry says it ended."""
        applied: dict[str, Any] = {"linear_x": 0.2, "angular_z": 0.0}
        if replaces is not None:
            applied["replaces"] = {"message_id": replaces, "reason": "replaced"}
        await self.add(AuditEvent.COMMAND_DISPATCHED, principal="planner", role="USER",
                       message_id=message_id, action_type="move",
                       params={"linear_x": 0.2}, applied=applied, outcome="executed",
                       ros2_topic="/robot1/cmd_vel")

    async def stream_ended(self, message_id: str) -> None:
        await self.add(AuditEvent.STREAM_ENDED, principal="planner", action_type="move",
                       message_id=message_id, params={"reason": "completed"})

    async def stop(self, message_id: str) -> None:
        await self.add(AuditEvent.COMMAND_DISPATCHED, principal="ops", role="OWNER",
                       message_id=message_id, action_type="stop", params={}, applied={},
                       outcome="executed", ros2_topic="/robot1/cmd_vel", sent_first=True)

    def now_ms(self) -> int:
        return int(self.clock.time() * 1000)


async def test_an_arm_trajectory_still_due_after_a_crash_is_listed(
        tmp_path: Path, clock: ManualClock) -> None:
    log = await Log.open(tmp_path, clock)
    await log.started()
    sent_at = log.now_ms()
    await log.arm("arm-1")
    clock.advance(10)
    await log.audit.close()  # killed: no BRIDGE_STOPPED
    found = resume(log.path, now_ms=log.now_ms())
    assert found.crashed
    [arm] = found.left.arms
    assert (arm.message_id, arm.topic, arm.joints) == ("arm-1", ARM_TOPIC,
                                                       ["l_shoulder", "l_elbow"])
    assert (arm.sent_at_ms, arm.runs_for_s, arm.params["group"]) == (sent_at, 60.0, "left")
    assert (found.left.goals, found.left.streams) == ([], [])


async def test_a_trajectory_that_ended_by_its_time_is_not_listed(
        tmp_path: Path, clock: ManualClock) -> None:
    log = await Log.open(tmp_path, clock)
    await log.started()
    points = {"group": "left", "joints": ["l_elbow"], "points": [
        {"positions": [0.1], "time_from_start_s": 1.0},
        {"positions": [0.2], "time_from_start_s": 5.0}]}
    await log.arm("arm-1", points)
    await log.audit.close()
    due = log.now_ms() + round((5.0 + SETTLING_S) * 1000)  # its last point, settled
    assert [a.message_id for a in resume(log.path, now_ms=due - 1).left.arms] == ["arm-1"]
    assert resume(log.path, now_ms=due).left.arms == []
    assert resume(log.path, now_ms=due).crashed


async def test_motion_a_later_stop_took_back_is_not_listed(
        tmp_path: Path, clock: ManualClock) -> None:
    log = await Log.open(tmp_path, clock)
    await log.started()
    await log.arm("arm-1")
    await log.goal("nav-1", str(uuid.uuid4()))
    await log.stop("stop-1")
    await log.audit.close()
    found = resume(log.path, now_ms=log.now_ms())
    assert found.crashed and not found.left


async def test_a_stop_that_failed_took_back_nothing(tmp_path: Path, clock: ManualClock) -> None:
    """Its own COMMAND_FAILED follows (say, an arm it could not hold): what ran, runs."""
    log = await Log.open(tmp_path, clock)
    await log.started()
    await log.arm("arm-1")
    await log.stop("stop-1")
    await log.add(AuditEvent.COMMAND_FAILED, principal="ops", message_id="stop-1",
                  action_type="stop", outcome="failed",
                  deny_reason="robot_unavailable:the arm was not held")
    await log.audit.close()
    assert [a.message_id for a in resume(log.path, now_ms=log.now_ms()).left.arms] == ["arm-1"]


async def test_a_stop_of_one_principal_ends_what_it_says_it_held(
        tmp_path: Path, clock: ManualClock) -> None:
    log = await Log.open(tmp_path, clock)
    await log.started()
    await log.arm("arm-1")
    goal_id = str(uuid.uuid4())
    await log.goal("nav-1", goal_id)
    await log.add(AuditEvent.NETWORK_LOSS_SAFE_STOP, principal="planner", message_id="own-1",
                  action_type="stop", outcome="executed", applied={
                      "scope": "own", "goals_cancelled": [goal_id], "arms_held": [ARM_TOPIC]})
    await log.audit.close()
    assert not resume(log.path, now_ms=log.now_ms()).left


async def test_a_clean_stop_leaves_nothing(tmp_path: Path, clock: ManualClock) -> None:
    log = await Log.open(tmp_path, clock)
    await log.started()
    await log.arm("arm-1")
    await log.goal("nav-1", str(uuid.uuid4()))
    await log.add(AuditEvent.BRIDGE_STOPPED, params={"estop_latched": False, "locks": {}})
    await log.audit.close()
    found = resume(log.path, now_ms=log.now_ms())
    assert not found.crashed and not found.left


async def test_goals_are_listed_by_id_or_as_having_none(
        tmp_path: Path, clock: ManualClock) -> None:
    """A goal's id is written ahead in its entry; an entry of a bridge before that has none
    (its goal is listed all the same: its server's goals are cancelled). GOAL_FINISHED ends
    one, by its id (or, having none, by its command's message id)."""
    log = await Log.open(tmp_path, clock)
    await log.started()
    ids = [str(uuid.uuid4()) for _ in range(2)]
    await log.goal("nav-1", ids[0])
    await log.goal("nav-2", None)
    await log.goal("nav-3", ids[1])
    await log.goal("nav-4", None)
    for message_id, goal_id in (("nav-3", ids[1]), ("nav-4", str(uuid.uuid4()))):
        await log.add(AuditEvent.GOAL_FINISHED, message_id=message_id,
                      params={"goal_id": goal_id}, outcome="succeeded", ros2_topic=NAV)
    await log.audit.close()
    goals = resume(log.path, now_ms=log.now_ms()).left.goals
    assert [(g.message_id, g.goal_id, g.server) for g in goals] == [
        ("nav-1", ids[0], NAV), ("nav-2", None, NAV)]


async def test_a_goal_whose_send_gave_up_is_listed_until_its_end(
        tmp_path: Path, clock: ManualClock) -> None:
    """A COMMAND_FAILED naming the goal (its send gave up after the request went out: the
    server may accept it late) does not end it; its GOAL_FINISHED does. One naming none (the
    server refused it) does."""
    log = await Log.open(tmp_path, clock)
    await log.started()
    ids = [str(uuid.uuid4()) for _ in range(3)]
    for n, goal_id in enumerate(ids, 1):
        await log.goal(f"nav-{n}", goal_id)
    for n, goal_id in ((1, ids[0]), (2, None), (3, ids[2])):
        await log.add(AuditEvent.COMMAND_FAILED, principal="planner", message_id=f"nav-{n}",
                      action_type="navigate", outcome="failed", goal_id=goal_id,
                      deny_reason="robot_unavailable:no reply within the timeout")
    await log.add(AuditEvent.GOAL_FINISHED, message_id="nav-3", params={"goal_id": ids[2]},
                  outcome="canceled", ros2_topic=NAV)
    await log.audit.close()
    goals = resume(log.path, now_ms=log.now_ms()).left.goals
    assert [(g.message_id, g.goal_id, g.server) for g in goals] == [("nav-1", ids[0], NAV)]


async def test_a_torn_last_line_does_not_hide_what_came_before(
        tmp_path: Path, clock: ManualClock) -> None:
    """Killed mid-append: the last line is cut short. The scan reads past it (the log cuts
    it when it opens); the motion before it is listed, and the latch is not taken for it."""
    log = await Log.open(tmp_path, clock)
    await log.started()
    await log.arm("arm-1")
    await log.audit.close()
    with log.path.open("ab") as f:
        f.write(b'{"event":"COMMAND_DISPATCHED","seq":4,"mess')
    found = resume(log.path, now_ms=log.now_ms())
    assert found.latched is False and found.crashed
    assert [a.message_id for a in found.left.arms] == ["arm-1"]


# -- a start takes it back ------------------------------------------------------------------

async def _crashed_with_an_arm_and_a_goal(harness: Harness) -> tuple[str, str]:
    gov = await harness.governor(gates="[]")
    await gov.start()
    arm = await gov.decide(command("arm_joint", {"joints": ["elbow"], "positions": [0.8],
                                                 "duration_s": 600.0}), PLANNER)
    goal = await gov.decide(command("navigate", {"x": 1.0, "y": 0.0, "yaw": 0.0}), PLANNER)
    assert arm.outcome is goal.outcome is Outcome.EXECUTED, (arm, goal)
    assert arm.message_id is not None and goal.message_id is not None
    await harness.restart()  # the log closed, no BRIDGE_STOPPED: a crash
    return arm.message_id, goal.message_id


async def test_a_goal_s_id_is_written_ahead(harness: Harness) -> None:
    await _crashed_with_an_arm_and_a_goal(harness)
    [sent] = [e for e in harness.entries if e.get("action_type") == "navigate"]
    assert uuid.UUID(sent["goal_id"]).version == 4, sent


async def test_a_start_after_a_crash_takes_back_what_it_left(harness: Harness) -> None:
    arm_id, goal_message_id = await _crashed_with_an_arm_and_a_goal(harness)
    [goal_id] = [e["goal_id"] for e in harness.entries if e.get("action_type") == "navigate"]
    gov = await harness.governor(gates="[]")
    await gov.start()
    [left] = harness.dispatcher.left
    assert [a.message_id for a in left.arms] == [arm_id]
    assert [(g.message_id, g.goal_id) for g in left.goals] == [(goal_message_id, goal_id)]
    started, took_back = harness.entries[-2:]
    assert started["event"] == "BRIDGE_STARTED"
    assert (took_back["event"], took_back["outcome"]) == ("NETWORK_LOSS_SAFE_STOP", "executed")
    applied = took_back["applied"]
    assert applied["scope"] == "crash" and applied["goals_cancelled"] == [goal_id]
    assert applied["arms_held"] == [left.arms[0].topic]
    assert [a["message_id"] for a in applied["left"]["arms"]] == [arm_id]
    await gov.stop()
    # Taken back: the next start after another crash finds nothing more to take back.
    await harness.restart()
    harness.dispatcher.left.clear()
    gov = await harness.governor(gates="[]")
    await gov.start()
    assert harness.dispatcher.left == []
    await gov.stop()


async def test_a_start_after_a_crash_cancels_a_goal_whose_send_gave_up(
        harness: Harness) -> None:
    """Killed while a goal whose send gave up was watched for (its server may accept it
    late): its COMMAND_FAILED names it, and the restart cancels it by id. A goal its server
    refused is not named, nor taken back."""
    gov = await harness.governor(gates="[]")
    await gov.start()
    failed = {}
    for send in ("gave up", "rejected"):
        harness.dispatcher.goal_send = send
        decided = await gov.decide(command("navigate", {"x": 1.0, "y": 0.0, "yaw": 0.0}),
                                   PLANNER)
        assert decided.outcome is not Outcome.EXECUTED, decided
        failed[send] = decided.message_id
    [written] = [e["goal_id"] for e in harness.entries
                 if e["event"] == "COMMAND_DISPATCHED" and e["message_id"] == failed["gave up"]]
    [named] = [e["goal_id"] for e in harness.entries if e["event"] == "COMMAND_FAILED"
               and e["message_id"] == failed["gave up"]]
    assert named == written
    await harness.restart()  # no BRIDGE_STOPPED: a crash
    gov = await harness.governor(gates="[]")
    await gov.start()
    [left] = harness.dispatcher.left
    assert [(g.message_id, g.goal_id) for g in left.goals] == [(failed["gave up"], written)]
    assert harness.entries[-1]["applied"]["goals_cancelled"] == [written]
    await gov.stop()


async def test_an_arm_that_could_not_be_held_fails_the_entry_loudly(harness: Harness) -> None:
    await _crashed_with_an_arm_and_a_goal(harness)
    harness.dispatcher.unheard_arms = True
    gov = await harness.governor(gates="[]")
    await gov.start()
    took_back = harness.entries[-1]
    assert (took_back["event"], took_back["outcome"]) == ("NETWORK_LOSS_SAFE_STOP", "failed")
    assert "no joint_states heard" in took_back["deny_reason"]
    assert took_back["applied"]["arms_not_held"], took_back
    await gov.stop()


async def test_an_arm_not_held_is_tried_again_after_the_next_crash(harness: Harness) -> None:
    """A crash loop (out of memory at every start, say): the arm a start could not hold is
    in its entry (`still_left`), and the next start after another crash tries it again."""
    arm_id, _ = await _crashed_with_an_arm_and_a_goal(harness)
    harness.dispatcher.unheard_arms = True
    gov = await harness.governor(gates="[]")
    await gov.start()
    assert harness.entries[-1]["applied"]["still_left"] == [arm_id]
    await harness.restart()  # killed again: no BRIDGE_STOPPED
    harness.dispatcher.unheard_arms = False
    gov = await harness.governor(gates="[]")
    await gov.start()
    [_, again] = harness.dispatcher.left
    assert [a.message_id for a in again.arms] == [arm_id] and again.goals == []
    assert harness.entries[-1]["applied"]["arms_held"] == [again.arms[0].topic]
    await harness.restart()  # and again: held this time, nothing is left
    gov = await harness.governor(gates="[]")
    await gov.start()
    assert len(harness.dispatcher.left) == 2
    await gov.stop()


async def test_a_crash_during_the_halt_leaves_it_to_the_next_start(harness: Harness) -> None:
    """Killed again while taking back what the first crash left (before that halt's entry):
    its BRIDGE_STARTED lists what it set out to take back, and the next start does."""
    arm_id, goal_message_id = await _crashed_with_an_arm_and_a_goal(harness)
    harness.dispatcher.halt_hold = asyncio.Event()  # the halt never finishes
    gov = await harness.governor(gates="[]")
    starting = asyncio.ensure_future(gov.start())
    await eventually(lambda: harness.dispatcher.left and
                     harness.entries[-1]["event"] == "BRIDGE_STARTED", what="halting")
    starting.cancel()
    await harness.restart()  # killed mid-halt: no entry of it, no BRIDGE_STOPPED
    harness.dispatcher.halt_hold = None
    gov = await harness.governor(gates="[]")
    await gov.start()
    [_, again] = harness.dispatcher.left
    assert [a.message_id for a in again.arms] == [arm_id]
    assert [g.message_id for g in again.goals] == [goal_message_id]
    assert harness.entries[-1]["applied"]["scope"] == "crash"
    await gov.stop()


async def test_a_start_after_a_clean_stop_takes_nothing_back(harness: Harness) -> None:
    gov = await harness.governor(gates="[]")
    await gov.start()
    await gov.decide(command("arm_joint", {"joints": ["elbow"], "positions": [0.8],
                                           "duration_s": 600.0}), PLANNER)
    await gov.stop()
    await harness.restart()
    gov = await harness.governor(gates="[]")
    await gov.start()
    assert harness.dispatcher.left == []
    assert harness.entries[-1]["event"] == "BRIDGE_STARTED"
    await gov.stop()


async def test_a_clean_stop_leaves_the_goals_still_watched_to_the_next_start(
        harness: Harness) -> None:
    """Stopped while a goal whose send gave up is watched for and its server has not
    accepted it (the stop's server-wide cancel cannot reach it; the watch ends with the
    bridge): BRIDGE_STOPPED names it, and the next start cancels it by id (scope
    `stopped`). A start after that takes nothing more back."""
    gov = await harness.governor(gates="[]")
    await gov.start()
    goal_id = str(uuid.uuid4())
    watched = LeftGoal(message_id="nav-1", action="navigate", principal=None, server=NAV,
                       goal_id=goal_id)
    harness.dispatcher.watched = [watched]
    await gov.stop()
    stopped = harness.entries[-1]
    assert stopped["event"] == "BRIDGE_STOPPED"
    assert stopped["params"]["left_running"]["goals"] == [msgspec.to_builtins(watched)]
    harness.dispatcher.watched = []
    await harness.restart()
    gov = await harness.governor(gates="[]")
    await gov.start()
    [left] = harness.dispatcher.left
    assert left.goals == [watched] and left.arms == left.streams == []
    took_back = harness.entries[-1]
    assert (took_back["event"], took_back["applied"]["scope"]) == (
        "NETWORK_LOSS_SAFE_STOP", "stopped"), took_back
    assert took_back["applied"]["goals_cancelled"] == [goal_id]
    await gov.stop()
    assert "left_running" not in harness.entries[-1]["params"]
    await harness.restart()
    gov = await harness.governor(gates="[]")
    await gov.start()
    assert len(harness.dispatcher.left) == 1
    await gov.stop()


async def test_a_trajectory_whose_replacement_failed_is_still_listed(
        tmp_path: Path, clock: ManualClock) -> None:
    """A later trajectory of the same joints replaces the one running only if it was sent:
    written ahead, then refused (its COMMAND_FAILED: the robot went silent, its client left),
    it replaced nothing, and the first runs on."""
    log = await Log.open(tmp_path, clock)
    await log.started()
    await log.arm("arm-1")
    await log.arm("arm-2", {**LONG, "duration_s": 0.5})
    await log.add(AuditEvent.COMMAND_FAILED, principal="planner", message_id="arm-2",
                  action_type="arm_joint", outcome="failed",
                  deny_reason="robot_unavailable:robot silent")
    clock.advance(10)
    await log.audit.close()
    assert [a.message_id for a in resume(log.path, now_ms=log.now_ms()).left.arms] == ["arm-1"]


async def test_a_start_holds_an_arm_whose_replacement_was_refused_after_its_entry(
        harness: Harness) -> None:
    """The governor's own log of it: an arm's long trajectory, then one of the same joints
    that the robot refused once written ahead (gone silent meanwhile); killed. The first
    still runs: the restart takes it back."""
    gov = await harness.governor(gates="[]")
    await gov.start()
    elbow = {"joints": ["elbow"], "positions": [0.8]}
    first = await gov.decide(command("arm_joint", {**elbow, "duration_s": 600.0}), PLANNER)
    assert first.outcome is Outcome.EXECUTED, first
    harness.dispatcher.hold = asyncio.Event()
    replacing = asyncio.ensure_future(
        gov.decide(command("arm_joint", {**elbow, "duration_s": 0.5}), PLANNER))
    await asyncio.wait_for(harness.dispatcher.entered.wait(), timeout=10)
    harness.dispatcher.available = False  # silent while its entry was written
    harness.dispatcher.hold.set()
    refused = await replacing
    assert refused.outcome is Outcome.FAILED, refused
    harness.dispatcher.hold, harness.dispatcher.available = None, True
    await harness.restart()  # killed: no BRIDGE_STOPPED
    # Restarted 10 s later. (Moved on before the kill, the clock let the run's session
    # watchdog safe-stop the robot while its log closed, on a busy machine: nothing left.)
    harness.clock.advance(10)
    gov = await harness.governor(gates="[]")
    await gov.start()
    [left] = harness.dispatcher.left
    assert [a.message_id for a in left.arms] == [first.message_id]
    await gov.stop()


def test_the_scan_of_a_long_run_holds_no_more_than_its_motion(tmp_path: Path) -> None:
    """A run may write any number of entries (weeks up, a command a second): the scan back
    to its start reads them one at a time and keeps what they left running, never the run.
    Before, every entry of the run was held at once (100 000: 54 MB of log, 326 MB of
    memory at start, more with each day up: a board's start ends out of memory, again at
    each restart). The lines are written as the log writes them (compact, sorted keys); the
    scan reads what opening the log verified."""
    path = tmp_path / "audit.jsonl"
    runs = 20_000
    with path.open("wb") as log:
        log.write(_line(event="BRIDGE_STARTED", params={"estop_latched": False, "locks": {}}))
        for n in range(runs):
            goal_id = str(uuid.UUID(int=n))
            log.write(_line(event="COMMAND_DISPATCHED", principal="planner", role="USER",
                            message_id=f"nav-{n}", action_type="navigate",
                            params={"x": 1.0, "y": 2.0, "yaw": 0.0}, outcome="executed",
                            applied={"x": 1.0, "y": 2.0, "yaw": 0.0}, ros2_topic=NAV,
                            goal_id=goal_id, timestamp_ms=n))
            log.write(_line(event="GOAL_FINISHED", message_id=f"nav-{n}", outcome="succeeded",
                            params={"goal_id": goal_id}, ros2_topic=NAV, timestamp_ms=n))
    size = path.stat().st_size
    tracemalloc.start()
    try:
        found = resume(path, now_ms=runs)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert found.crashed and found.left.goals == [] and found.latched is False
    assert peak < size / 4, (peak, size)


def _line(**entry: Any) -> bytes:
    return json.dumps(entry, sort_keys=True, separators=(",", ":")).encode() + b"\n"


async def test_another_principal_s_command_of_the_same_id_ends_nothing_of_this_one(
        tmp_path: Path, clock: ManualClock) -> None:
    """Message ids are unique per principal only: another's command of the same id that
    failed, or that started a goal too, leaves this one's motion listed."""
    log = await Log.open(tmp_path, clock)
    await log.started()
    await log.arm("m-1")  # the planner's
    await log.goal("g-1", str(uuid.uuid4()))
    params = {"x": 1.0, "y": 2.0, "yaw": 0.0}
    for message_id in ("m-1", "g-1"):
        await log.add(AuditEvent.COMMAND_DISPATCHED, principal="ops", role="OWNER",
                      message_id=message_id, action_type="navigate", params=params,
                      applied=params, outcome="executed", ros2_topic=NAV,
                      goal_id=str(uuid.uuid4()))
    await log.add(AuditEvent.COMMAND_FAILED, principal="ops", message_id="m-1",
                  action_type="navigate", outcome="failed", deny_reason="robot_unavailable")
    await log.audit.close()
    left = resume(log.path, now_ms=log.now_ms()).left
    assert [(a.principal, a.message_id) for a in left.arms] == [("planner", "m-1")]
    assert [(g.principal, g.message_id) for g in left.goals] == [("planner", "g-1"),
                                                                  ("ops", "g-1")]


async def test_a_failed_hold_of_an_arm_named_by_its_command_s_id_ends_nothing(
        harness: Harness) -> None:
    """An INVOKE's timeout, or its client gone, holds its arm and cancels its goal under the
    id of the command that sent them; when that hold or cancel fails, its COMMAND_FAILED
    bears that id — and the motion runs on. A restart after a crash takes it back."""
    gov = await harness.governor(gates="[]")
    await gov.start()
    arm = await gov.decide(command("arm_joint", {"joints": ["elbow"], "positions": [0.8],
                                                 "duration_s": 600.0}), PLANNER)
    assert arm.outcome is Outcome.EXECUTED and arm.message_id is not None, arm
    harness.dispatcher.unheard_arms = True  # the hold cannot be made
    held = await gov.hold_trajectory(arm.message_id, PLANNER, message_id=arm.message_id,
                                     why="INVOKE's client left")
    assert held.outcome is Outcome.FAILED, held
    assert harness.entries[-1]["event"] == "COMMAND_FAILED"
    await harness.restart()  # killed: no BRIDGE_STOPPED
    harness.dispatcher.unheard_arms = False
    gov = await harness.governor(gates="[]")
    await gov.start()
    [left] = harness.dispatcher.left
    assert [a.message_id for a in left.arms] == [arm.message_id]
    await gov.stop()


async def test_a_failed_cancel_of_a_goal_named_by_its_command_s_id_ends_nothing(
        tmp_path: Path, clock: ManualClock) -> None:
    log = await Log.open(tmp_path, clock)
    await log.started()
    goal_id = str(uuid.uuid4())
    await log.goal("nav-1", goal_id)
    await log.add(AuditEvent.COMMAND_DISPATCHED, principal="planner", message_id="nav-1",
                  action_type="cancel_goal", outcome="executed",
                  params={"goal_id": goal_id, "why": "INVOKE timeout"})
    await log.add(AuditEvent.COMMAND_FAILED, principal="planner", message_id="nav-1",
                  action_type="cancel_goal", params={"goal_id": goal_id}, outcome="failed",
                  deny_reason="robot_unavailable:goal_not_cancelled")
    await log.audit.close()
    goals = resume(log.path, now_ms=log.now_ms()).left.goals
    assert [(g.message_id, g.goal_id) for g in goals] == [("nav-1", goal_id)]


async def test_an_entry_of_an_unexpected_shape_latches_the_start_not_crashes_it(
        tmp_path: Path, clock: ManualClock) -> None:
    """Signed, so written by a bridge — but perhaps another version of it: a field of
    another type is no reason for the start to end in a traceback. It fails closed, as an
    unreadable tail does: latched, saying why."""
    log = await Log.open(tmp_path, clock)
    await log.started()
    await log.arm("arm-1")
    await log.add(AuditEvent.NETWORK_LOSS_SAFE_STOP, principal="planner", message_id="own-1",
                  action_type="stop", outcome="executed",
                  applied={"scope": "own", "goals_cancelled": 5, "arms_held": 7})
    await log.audit.close()
    found = resume(log.path, now_ms=log.now_ms())
    assert found.latched is True and "unreadable" in str(found.latched_by), found


async def test_a_trajectory_replaced_just_before_the_crash_is_still_listed(
        tmp_path: Path, clock: ManualClock) -> None:
    """Killed between a trajectory's write-ahead entry and its publish: the log cannot tell
    whether it went out, and if it did not, the one it would have replaced runs on (here
    600 s, where the later one was over in a second). Fail closed: both are listed while
    due — a hold of an arm that the later one stopped holds it where it already is."""
    log = await Log.open(tmp_path, clock)
    await log.started()
    await log.arm("arm-1")
    await log.arm("arm-2", {**LONG, "duration_s": 0.5})
    clock.advance(10)
    await log.audit.close()
    assert [a.message_id for a in resume(log.path, now_ms=log.now_ms()).left.arms] == ["arm-1"]


async def test_a_goal_id_that_is_no_uuid_is_listed_unnamed_not_as_given(
        tmp_path: Path, clock: ManualClock) -> None:
    """Red team 16: a goal id an entry gives that is no UUID (another version's log, a
    damaged one) made the start's take-back raise turning it into bytes — the whole
    take-back failed, arms included, with a traceback, at every start. Now it is listed
    with no id (every goal of its server is cancelled: fail closed), wherever it was read:
    a dispatched goal's entry, a COMMAND_FAILED naming it, a clean stop's list. Ids of
    other spellings of a UUID are listed as the take-back writes them."""
    log = await Log.open(tmp_path, clock)
    braced = uuid.uuid4()
    named = {"message_id": "nav-0", "action": "navigate", "principal": None,
             "server": NAV, "goal_id": "{" + braced.hex.upper() + "}"}
    await log.add(AuditEvent.BRIDGE_STARTED, params={"estop_latched": False, "locks": {},
                                                     "left_running": {"goals": [named]}})
    await log.goal("nav-1", "not-a-uuid")
    await log.goal("nav-2", str(uuid.uuid4()))
    await log.add(AuditEvent.COMMAND_FAILED, principal="planner", message_id="nav-2",
                  action_type="navigate", outcome="failed", goal_id="../../etc\n{}",
                  deny_reason="robot_unavailable:no reply within the timeout")
    await log.audit.close()
    found = resume(log.path, now_ms=log.now_ms())
    assert found.latched is False and found.crashed, found
    assert [(g.message_id, g.goal_id) for g in found.left.goals] == [
        ("nav-0", str(braced)), ("nav-1", None), ("nav-2", None)]


async def test_motion_left_that_a_boundary_lists_unreadably_latches_the_start(
        tmp_path: Path, clock: ManualClock) -> None:
    """A clean stop's (or a start's) list of the motion left running that does not read as
    one (a goal id of another type, say): before, the whole list was dropped in silence and
    the goals it named ran on with nobody to cancel them. Now the start fails closed:
    latched, saying why (as for any entry of an unexpected shape)."""
    log = await Log.open(tmp_path, clock)
    await log.started()
    good = {"message_id": "nav-1", "action": "navigate", "principal": None, "server": NAV,
            "goal_id": str(uuid.uuid4())}
    await log.add(AuditEvent.BRIDGE_STOPPED, params={
        "estop_latched": False, "locks": {},
        "left_running": {"goals": [good, {**good, "message_id": "nav-2", "goal_id": 7}]}})
    await log.audit.close()
    found = resume(log.path, now_ms=log.now_ms())
    assert found.latched is True and "unreadable" in str(found.latched_by), found


async def test_every_goal_a_clean_stop_names_is_listed_even_of_one_message_id(
        tmp_path: Path, clock: ManualClock) -> None:
    """Red team 16: a clean stop names the goals still watched by id, with no principal
    (`Dispatcher.goals_watched`); message ids are unique per principal only, so two
    principals' goals of one message id — or two of a command not known — were listed as
    one (the last), and the next start left the other to run. Each is listed."""
    log = await Log.open(tmp_path, clock)
    await log.started()
    named = [{"message_id": message_id, "action": action, "principal": None,
              "server": NAV, "goal_id": str(uuid.uuid4())}
             for message_id, action in (("m-1", "navigate"), ("m-1", "navigate"),
                                        ("", ""), ("", ""))]
    await log.add(AuditEvent.BRIDGE_STOPPED, params={"estop_latched": False, "locks": {},
                                                     "left_running": {"goals": named}})
    await log.audit.close()
    found = resume(log.path, now_ms=log.now_ms())
    assert not found.crashed
    assert [g.goal_id for g in found.left.goals] == [g["goal_id"] for g in named]


async def test_an_arm_left_running_for_ever_latches_the_start_not_crashes_it(
        tmp_path: Path, clock: ManualClock) -> None:
    """Red team 16: an arm a boundary lists as left running whose run time is out of any
    range (another version's entry, a damaged one: 1e308 s) made resume raise OverflowError
    working out when it is due — the start ended in a traceback. It fails closed as any
    entry of an unexpected shape: latched, saying why."""
    log = await Log.open(tmp_path, clock)
    arm = {"message_id": "arm-1", "action": "arm_joint", "principal": "planner",
           "topic": ARM_TOPIC, "params": {}, "joints": ["elbow"], "sent_at_ms": 1,
           "runs_for_s": 1e308}
    await log.add(AuditEvent.BRIDGE_STARTED, params={"estop_latched": False, "locks": {},
                                                     "left_running": {"arms": [arm]}})
    await log.audit.close()
    found = resume(log.path, now_ms=log.now_ms())
    assert found.latched is True and "unreadable" in str(found.latched_by), found


async def test_more_arm_trajectories_left_than_listed_are_held_all_the_same(
        tmp_path: Path, clock: ManualClock) -> None:
    """A crashed run left more arm trajectories still due than the list names one by one
    (MAX_LEFT: here 70, each moving a joint of its own, so none replaced another): those of
    one route are listed as one, every joint they move, until the last is due. Before, the
    list kept the newest 64: 6 joints ran on with nobody to hold them (red team 17)."""
    from rcan_rtps.governance.resume import MAX_LEFT

    log = await Log.open(tmp_path, clock)
    await log.started()
    joints = [f"j{n}" for n in range(MAX_LEFT + 6)]
    for n, joint in enumerate(joints):
        await log.arm(f"arm-{n}", {"group": "left", "joints": [joint], "positions": [0.5],
                                   "duration_s": 60.0 + n})
    await log.arm("short", {"group": "left", "joints": ["wrist"], "positions": [0.5],
                            "duration_s": 1.0})
    clock.advance(10)
    await log.audit.close()  # killed: no BRIDGE_STOPPED
    [arm] = resume(log.path, now_ms=log.now_ms()).left.arms
    assert sorted(arm.joints) == sorted(joints)  # the short one is over: not held
    assert (arm.topic, arm.runs_for_s) == (ARM_TOPIC, 60.0 + MAX_LEFT + 5)


async def test_a_stream_a_later_move_replaced_ends_with_that_move(
        tmp_path: Path, clock: ManualClock) -> None:
    """A move that replaces the stream running says so in its own entry (`applied.replaces`);
    no STREAM_ENDED of the replaced one follows. Before, each replaced stream stayed in the
    replay's state for the rest of the run (and in every start point: ~1.1 kB per move made
    over REST), and a crash listed them all as left running."""
    log = await Log.open(tmp_path, clock)
    await log.started()
    await log.move("move-1")
    await log.move("move-2", replaces="move-1")
    await log.move("move-3", replaces="move-2")
    await log.stream_ended("move-3")
    await log.audit.close()  # killed: no BRIDGE_STOPPED
    assert resume(log.path, now_ms=log.now_ms()).left.streams == []


async def test_the_stream_a_move_replaced_is_listed_while_the_move_is(
        tmp_path: Path, clock: ManualClock) -> None:
    """The crash may have come between the move's entry and its first sample: the stream it
    replaced may be the one still on the wire. Both are listed (fail closed), as for a
    replaced trajectory; the replaced one alone once the move's own COMMAND_FAILED says it
    was refused after its entry."""
    log = await Log.open(tmp_path, clock)
    await log.started()
    await log.move("move-1")
    await log.move("move-2", replaces="move-1")
    await log.audit.close()
    left = resume(log.path, now_ms=log.now_ms()).left.streams
    assert [s.message_id for s in left] == ["move-1", "move-2"]

    log = await Log.open(tmp_path / "refused", clock)
    await log.started()
    await log.move("move-1")
    await log.move("move-2", replaces="move-1")
    await log.add(AuditEvent.COMMAND_FAILED, principal="planner", message_id="move-2",
                  action_type="move", outcome="failed",
                  deny_reason="robot_unavailable:robot silent")
    await log.audit.close()
    left = resume(log.path, now_ms=log.now_ms()).left.streams
    assert [s.message_id for s in left] == ["move-1"]


async def test_a_stream_given_back_by_its_replacer_s_failure_ends_by_its_own_entry(
        tmp_path: Path, clock: ManualClock) -> None:
    """Given back, the replaced stream runs on until its own end (the replacer never took
    the wire, so the live bridge records that end in a STREAM_ENDED of its own)."""
    log = await Log.open(tmp_path, clock)
    await log.started()
    await log.move("move-1")
    await log.move("move-2", replaces="move-1")
    await log.add(AuditEvent.COMMAND_FAILED, principal="planner", message_id="move-2",
                  action_type="move", outcome="failed", deny_reason="estop_active")
    await log.stream_ended("move-1")
    await log.audit.close()
    assert resume(log.path, now_ms=log.now_ms()).left.streams == []


async def test_a_run_of_replaced_moves_leaves_the_replay_no_bigger(harness: Harness) -> None:
    """The governor's own log of it: moves made one after another over REST (each replacing
    the stream before it), then a kill. The replay and the start point it writes hold the
    last move and the one it replaced, not every move of the run."""
    gov = await harness.governor(gates="[]")
    await gov.start()
    moves = [await gov.decide(command("move", {"linear_x": 0.1 + n / 1000}), PLANNER)
             for n in range(40)]
    assert all(m.outcome is Outcome.EXECUTED for m in moves)
    replacing = [e for e in harness.entries if e.get("message_id") == moves[-1].message_id]
    assert replacing[0]["applied"]["replaces"]["message_id"] == moves[-2].message_id
    await harness.logs[0].checkpoint()  # a start point, as the running bridge writes them
    point = json.loads(point_path(harness.tmp / "audit.jsonl").read_bytes())
    assert len(point["body"]["motion"]["streams"]) == 1, point["body"]["motion"]
    await harness.restart()  # killed: no BRIDGE_STOPPED
    left = resume(harness.tmp / "audit.jsonl").left.streams
    assert [s.message_id for s in left] == [moves[-2].message_id, moves[-1].message_id]
