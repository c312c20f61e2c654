"""Start points: a start replays the last run from the replay's state saved at the last audit
checkpoint (`<log>.resume`) instead of from the run's first entry, so that its time does not
grow with the run. The result must be the replay's from the boundary, whatever the run held;
a point that is torn, altered, signed by another key or naming another log's entry is not
used (the replay goes back to the boundary: the same guarantees, only slower).

The logs are built with the audit writer itself (signed, chained), the points by the hook
`Governor.from_config` installs (`AuditLog.on_checkpoint`)."""

from __future__ import annotations

import asyncio
import base64
import functools
import json
import tempfile
from pathlib import Path
from typing import Any

import msgspec
import pytest
from govhelpers import PLANNER, RURI, Harness, command
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from rcan_rtps.governance.audit import (
    RESUME_POINT_TAG,
    AuditEvent,
    AuditLog,
    AuditRecord,
    Checkpoint,
    load_or_create_key,
)
from rcan_rtps.governance.clock import ManualClock
from rcan_rtps.governance.governor import _write_start_point
from rcan_rtps.governance.resume import point_path, resume, write_point
from rcan_rtps.rcan import Effect, Outcome
from rcan_rtps.rcan.actions import with_effect

ARMS = [("/robot1/left_arm/joint_trajectory", ["l_shoulder", "l_elbow"]),
        ("/robot1/left_arm/joint_trajectory", ["l_elbow"]),
        ("/robot1/right_arm/joint_trajectory", ["r_shoulder"])]
PRINCIPALS = ["planner", "ops", "other"]
LOCK, UNLOCK = with_effect(Effect.LOCK).name, with_effect(Effect.UNLOCK).name


class Run:
    """A log written entry by entry, with start points written at the checkpoints asked for."""

    def __init__(self, path: Path, clock: ManualClock, audit: AuditLog) -> None:
        self.path, self.clock, self.audit = path, clock, audit
        self.commands: list[dict[str, Any]] = []  # what a COMMAND_FAILED may name
        self.goals: list[str] = []
        self.n = 0
        self.saved_point: bytes | None = None  # the last point written while running

    @classmethod
    async def open(cls, tmp: Path, clock: ManualClock) -> Run:
        path = tmp / "audit.jsonl"
        audit = await AuditLog.open(path, tmp / "audit.key", ruri=RURI, clock=clock)
        audit.on_checkpoint(functools.partial(_write_start_point, path, audit.public_key,
                                              audit.sign_resume_point))
        return cls(path, clock, audit)

    def next_id(self, kind: str) -> str:
        self.n += 1
        return f"{kind}-{self.n}"

    async def add(self, event: AuditEvent, **fields: Any) -> None:
        await self.audit.append(AuditRecord(event=event, **fields))

    async def command(self, action: str, params: dict[str, Any], topic: str | None, *,
                      principal: str = "planner", applied: dict[str, Any] | None = None,
                      **more: Any) -> str:
        message_id = self.next_id(action)
        fields = dict(principal=principal, message_id=message_id, action_type=action,
                      params=params, applied=params if applied is None else applied,
                      outcome="executed", ros2_topic=topic, **more)
        self.commands.append(fields)
        await self.add(AuditEvent.COMMAND_DISPATCHED, role="USER", **fields)
        return message_id

    async def point(self) -> None:
        await self.audit.checkpoint()
        self.saved_point = point_path(self.path).read_bytes()

    async def crash(self) -> None:
        """Ends as a kill does: the closing checkpoint's point is not left behind."""
        await self.audit.close()
        if self.saved_point is None:
            point_path(self.path).unlink(missing_ok=True)
        else:
            point_path(self.path).write_bytes(self.saved_point)


# -- the equivalence ----------------------------------------------------------------------

Step = tuple[Any, ...]
steps = st.one_of(
    st.tuples(st.just("arm"), st.integers(0, len(ARMS) - 1), st.sampled_from(PRINCIPALS),
              st.sampled_from([0.5, 2.0, 60.0])),
    st.tuples(st.just("goal"), st.sampled_from(PRINCIPALS), st.booleans()),
    st.tuples(st.just("finish"), st.integers(0, 20)),
    st.tuples(st.just("move"), st.sampled_from(PRINCIPALS), st.booleans()),
    st.tuples(st.just("ended"), st.integers(0, 40)),
    st.tuples(st.just("failed"), st.integers(0, 3), st.booleans()),
    st.tuples(st.just("failed"), st.integers(0, 3), st.booleans()),
    st.tuples(st.just("stop")),
    st.tuples(st.just("own_stop"), st.sampled_from(PRINCIPALS), st.integers(0, len(ARMS) - 1)),
    st.tuples(st.just("estop")),
    st.tuples(st.just("clear")),
    st.tuples(st.just("lock"), st.sampled_from(["dock", "arm"]), st.booleans()),
    st.tuples(st.just("started"), st.booleans()),
    st.tuples(st.just("stopped"), st.booleans()),
    st.tuples(st.just("crash_halt"), st.booleans()),
    st.tuples(st.just("later"), st.sampled_from([0.1, 1.0, 30.0])),
    st.tuples(st.just("point")),
    st.tuples(st.just("point")),
)


async def _step(run: Run, step: Step) -> None:
    kind = step[0]
    if kind == "arm":
        topic, joints = ARMS[step[1]]
        params = {"group": "left" if "left" in topic else "right", "joints": joints,
                  "positions": [0.5] * len(joints), "duration_s": step[3]}
        await run.command("arm_joint", params, topic, principal=step[2])
    elif kind == "goal":
        goal_id = f"00000000-0000-4000-8000-{run.n:012d}" if step[2] else None
        await run.command("navigate", {"x": 1.0, "y": 2.0, "yaw": 0.0},
                          "/robot1/navigate_to_pose", principal=step[1], goal_id=goal_id)
        run.goals.append(goal_id or run.commands[-1]["message_id"])
    elif kind == "finish" and run.goals:
        goal = run.goals[step[1] % len(run.goals)]
        await run.add(AuditEvent.GOAL_FINISHED, message_id=goal, params={"goal_id": goal},
                      outcome="succeeded")
    elif kind == "move":
        await _move(run, step[1], replaces=step[2])
    elif kind == "ended" and run.commands:
        ended = run.commands[step[1] % len(run.commands)]
        await run.add(AuditEvent.STREAM_ENDED, message_id=ended["message_id"],
                      params={"reason": "ended"})
    elif kind == "failed" and run.commands:  # mostly of a recent command, as in a run
        await _failed(run, run.commands[-1 - step[1] % min(len(run.commands), 4)],
                      named=step[2])
    elif kind == "stop":
        await run.command("stop", {}, "/robot1/cmd_vel", principal="ops", sent_first=True)
    elif kind == "own_stop":
        await _own_stop(run, step[1], ARMS[step[2]][0])
    elif kind in ("estop", "clear"):
        await run.add(AuditEvent.ESTOP if kind == "estop" else AuditEvent.ESTOP_CLEARED,
                      principal="ops", message_id=run.next_id(kind))
    elif kind == "lock":
        await run.command(LOCK if step[2] else UNLOCK, {"name": step[1]}, None,
                          principal="ops")
    elif kind in ("started", "stopped"):
        await _boundary(run, kind, latched=step[1])
    elif kind == "crash_halt":
        await _crash_halt(run, still=step[1])
    elif kind == "later":
        run.clock.advance(step[1])
    elif kind == "point":
        await run.point()


async def _move(run: Run, principal: str, *, replaces: bool) -> None:
    """A move; `replaces`: its entry says it replaced the last move's stream, as the
    governor's does when that stream is running (`applied.replaces`)."""
    params = {"linear_x": 0.2, "angular_z": 0.0}
    moves = [c["message_id"] for c in run.commands if c["action_type"] == "move"]
    applied = dict(params)
    if replaces and moves:
        applied["replaces"] = {"message_id": moves[-1], "reason": "replaced"}
    await run.command("move", params, "/robot1/cmd_vel", principal=principal, applied=applied)


async def _failed(run: Run, failed: dict[str, Any], *, named: bool) -> None:
    goal_id = failed.get("goal_id") if named else None
    await run.add(AuditEvent.COMMAND_FAILED, principal=failed["principal"],
                  message_id=failed["message_id"], action_type=failed["action_type"],
                  outcome="failed", goal_id=goal_id)


async def _own_stop(run: Run, principal: str, topic: str) -> None:
    goals = [c.get("goal_id") for c in run.commands
             if c["principal"] == principal and c.get("goal_id")]
    await run.add(AuditEvent.NETWORK_LOSS_SAFE_STOP, principal=principal,
                  message_id=run.next_id("loss"), action_type="stop", outcome="executed",
                  applied={"scope": "own", "goals_cancelled": goals[:1], "arms_held": [topic]})


def _left_facts(run: Run) -> dict[str, Any]:
    """What an entry may name as left running: the last arm and goal commands, as a start
    lists them."""
    found = resume(run.path, now_ms=int(run.clock.time() * 1000))
    return found.left.facts()


async def _boundary(run: Run, kind: str, *, latched: bool) -> None:
    params: dict[str, Any] = {"estop_latched": latched, "locks": {"dock": "ops"}}
    facts = _left_facts(run)
    if facts["arms"] or facts["goals"]:
        params["left_running"] = facts
    event = AuditEvent.BRIDGE_STARTED if kind == "started" else AuditEvent.BRIDGE_STOPPED
    await run.add(event, params=params)


async def _crash_halt(run: Run, *, still: bool) -> None:
    facts = _left_facts(run)
    named = [a["message_id"] for a in facts["arms"]] + [g["message_id"] for g in facts["goals"]]
    applied = {"scope": "crash", "left": facts, "zero_reached": True, "goals_cancelled": []}
    if still:
        applied["still_left"] = named[:2]
    await run.add(AuditEvent.NETWORK_LOSS_SAFE_STOP, principal=None,
                  message_id=run.next_id("halt"), action_type="stop", outcome="executed",
                  applied=applied, sent_first=True)


async def _equivalence(tmp: Path, run_steps: list[Step], crashed: bool) -> None:
    run = await Run.open(tmp, ManualClock())
    await run.add(AuditEvent.BRIDGE_STARTED, params={"estop_latched": False, "locks": {}})
    for step in run_steps:
        await _step(run, step)
    if crashed:
        await run.crash()
    else:
        await run.add(AuditEvent.BRIDGE_STOPPED, params={"estop_latched": False, "locks": {}})
        await run.audit.close()
    pubkey = load_or_create_key(tmp / "audit.key").public_key()
    for later_s in (0.0, 1.5, 100.0):
        now_ms = int((run.clock.time() + later_s) * 1000)
        from_point = resume(run.path, now_ms=now_ms, pubkey=pubkey)
        from_boundary = resume(run.path, now_ms=now_ms)  # no key: no point is used
        assert from_point == from_boundary


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(steps, min_size=1, max_size=30), st.booleans())
# What a point must carry besides the running motion (rarely drawn at random): a stop whose
# own COMMAND_FAILED, after the point, gives back what it halted; a trajectory refused after
# the point, which gives back the one it replaced; an own stop, then a boundary after a point.
@example([("arm", 0, "planner", 60.0), ("stop",), ("point",), ("failed", 0, False)], True)
@example([("arm", 0, "planner", 60.0), ("arm", 0, "other", 60.0), ("point",),
          ("failed", 0, False)], True)
@example([("goal", "planner", True), ("arm", 2, "planner", 60.0), ("point",),
          ("own_stop", "planner", 2), ("estop",), ("point",), ("started", True),
          ("lock", "arm", True), ("failed", 1, True)], True)
# A goal a boundary lists by its id (keyed by it: red team 16), then a point: the point's
# key must come back as the key it was, not one no dict can hold.
@example([("goal", "planner", True), ("started", False), ("point",)], True)
# A move's stream replaced by another's after a point, the replacer refused: given back.
@example([("move", "planner", False), ("point",), ("move", "other", True),
          ("failed", 0, False)], True)
@example([("move", "planner", False), ("move", "other", True), ("point",),
          ("failed", 0, False), ("stop",), ("point",), ("failed", 0, False)], True)
def test_a_start_from_the_last_point_finds_what_a_start_from_the_boundary_finds(
        run_steps: list[Step], crashed: bool) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        asyncio.run(_equivalence(Path(tmp), run_steps, crashed))


# -- what a start does with a point --------------------------------------------------------

LONG_ARM = {"group": "left", "joints": ["l_shoulder", "l_elbow"], "positions": [1.0, 2.0],
            "duration_s": 60.0}


async def _crashed_with_an_arm(tmp: Path, clock: ManualClock) -> Run:
    """A run that sent a long arm trajectory, wrote a point, sent a goal and was killed."""
    run = await Run.open(tmp, clock)
    await run.add(AuditEvent.BRIDGE_STARTED, params={"estop_latched": False, "locks": {}})
    await run.command("arm_joint", LONG_ARM, ARMS[0][0])
    await run.point()
    await run.command("navigate", {"x": 1.0, "y": 2.0, "yaw": 0.0}, "/robot1/navigate_to_pose",
                      goal_id="00000000-0000-4000-8000-000000000001")
    await run.crash()
    return run


def _pubkey(tmp: Path) -> Any:
    return load_or_create_key(tmp / "audit.key").public_key()


def _left_ids(run: Run, *, pubkey: Any) -> tuple[bool, list[str], list[str]]:
    found = resume(run.path, now_ms=int(run.clock.time() * 1000), pubkey=pubkey)
    return (found.crashed, [a.message_id for a in found.left.arms],
            [g.message_id for g in found.left.goals])


async def test_a_start_replays_from_its_point_not_from_the_run_s_first_entry(
        tmp_path: Path, clock: ManualClock) -> None:
    """The lines before the point are not read: made unreadable, the start still finds what
    the run left (from the point's state and the entries after it); the replay from the
    boundary, which reads them, fails closed on them (latched)."""
    run = await _crashed_with_an_arm(tmp_path, clock)
    point = json.loads(point_path(run.path).read_bytes())["body"]
    data = bytearray(run.path.read_bytes())
    first_line_end = data.index(b"\n")
    data[:first_line_end] = b"x" * first_line_end  # BRIDGE_STARTED, garbled in place
    run.path.write_bytes(bytes(data))
    assert point["start"] > first_line_end
    assert _left_ids(run, pubkey=_pubkey(tmp_path)) == (True, ["arm_joint-1"], ["navigate-2"])
    from_boundary = resume(run.path)  # reads the garbled line: fails closed
    assert from_boundary.latched and "unreadable" in str(from_boundary.latched_by)


async def test_a_point_of_the_replay_s_earlier_meaning_is_not_used(
        tmp_path: Path, clock: ManualClock) -> None:
    """A point signed under the previous tag (v2: a replaced stream stayed listed until the
    run ended) holds a state the replay of today would not find: it is not used, and the
    replay goes back to the boundary (the run's moves read as they are read today)."""
    run = await Run.open(tmp_path, clock)
    await run.add(AuditEvent.BRIDGE_STARTED, params={"estop_latched": False, "locks": {}})
    await _move(run, "planner", replaces=False)
    await _move(run, "planner", replaces=True)
    await run.add(AuditEvent.STREAM_ENDED, message_id=run.commands[-1]["message_id"],
                  params={"reason": "completed"})
    await run.point()
    await run.crash()
    path = point_path(run.path)
    file = json.loads(path.read_bytes())
    file["body"]["motion"]["streams"] = [[["planner", "move-1", "move"], {
        "message_id": "move-1", "action": "move", "principal": "planner",
        "topic": "/robot1/cmd_vel"}]]  # as v2 left it
    body = json.dumps(file["body"]).encode()
    key = load_or_create_key(tmp_path / "audit.key")
    old_tag = b"rcan-rtps resume point v2\n"
    path.write_bytes(json.dumps({"body": file["body"], "sig": base64.b64encode(
        key.sign(old_tag + body)).decode()}).encode())
    found = resume(run.path, now_ms=int(clock.time() * 1000), pubkey=_pubkey(tmp_path))
    assert found.left.streams == [] and found.crashed


def _rewrite_point(run: Run, change: Any) -> None:
    """The point file with its body changed by `change`, its signature kept."""
    path = point_path(run.path)
    file = json.loads(path.read_bytes())
    change(file["body"])
    path.write_bytes(json.dumps(file).encode())


async def test_a_point_whose_state_was_altered_is_not_used(
        tmp_path: Path, clock: ManualClock, caplog: pytest.LogCaptureFixture) -> None:
    """An altered point (its arm taken out, the latch set off) fails its signature: the start
    replays from the boundary and still takes the arm back."""
    run = await _crashed_with_an_arm(tmp_path, clock)
    _rewrite_point(run, lambda body: body["motion"].update(arms=[]))
    assert _left_ids(run, pubkey=_pubkey(tmp_path)) == (True, ["arm_joint-1"], ["navigate-2"])
    assert "not signed by the audit log's key" in caplog.text


async def test_a_torn_point_is_not_used(tmp_path: Path, clock: ManualClock,
                                        caplog: pytest.LogCaptureFixture) -> None:
    run = await _crashed_with_an_arm(tmp_path, clock)
    path = point_path(run.path)
    path.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    assert _left_ids(run, pubkey=_pubkey(tmp_path)) == (True, ["arm_joint-1"], ["navigate-2"])
    assert "malformed" in caplog.text


async def test_a_point_another_key_signed_is_not_used(tmp_path: Path, clock: ManualClock) -> None:
    run = await _crashed_with_an_arm(tmp_path, clock)
    other = load_or_create_key(tmp_path / "other.key")
    file = json.loads(point_path(run.path).read_bytes())
    body = msgspec.json.encode(msgspec.json.decode(json.dumps(file["body"]).encode()))
    forged = {**file, "sig": base64.b64encode(other.sign(RESUME_POINT_TAG + body)).decode()}
    point_path(run.path).write_text(json.dumps(forged))
    assert _left_ids(run, pubkey=_pubkey(tmp_path)) == (True, ["arm_joint-1"], ["navigate-2"])


async def test_a_point_naming_an_entry_the_log_does_not_hold_is_not_used(
        tmp_path: Path, clock: ManualClock, caplog: pytest.LogCaptureFixture) -> None:
    """A point of another log under the same key (or of this one before it was replaced): the
    line at its span is not its entry. Here: a run that sent nothing, with the point of a run
    whose arm had stopped (none listed), copied in — the arm of this log is still found."""
    quiet = await Run.open(tmp_path / "quiet", clock)
    await quiet.add(AuditEvent.BRIDGE_STARTED, params={"estop_latched": False, "locks": {}})
    await quiet.add(AuditEvent.COMMAND_REJECTED, principal="planner", message_id="x",
                    action_type="move", deny_reason="rate limited")
    await quiet.point()
    await quiet.crash()
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "audit.key").write_bytes((tmp_path / "quiet" / "audit.key").read_bytes())
    (busy / "audit.key").chmod(0o600)
    run = await Run.open(busy, clock)
    await run.add(AuditEvent.BRIDGE_STARTED, params={"estop_latched": False, "locks": {}})
    await run.command("arm_joint", LONG_ARM, ARMS[0][0])
    await run.command("navigate", {"x": 1.0, "y": 2.0, "yaw": 0.0}, "/robot1/navigate_to_pose",
                      goal_id="00000000-0000-4000-8000-000000000001")
    await run.crash()
    point_path(run.path).write_bytes(point_path(quiet.path).read_bytes())
    assert _left_ids(run, pubkey=_pubkey(busy)) == (True, ["arm_joint-1"], ["navigate-2"])
    assert "not used" in caplog.text


async def test_the_governor_writes_points_at_each_checkpoint(harness: Harness) -> None:
    """`Governor.from_config` has the log write a point at its checkpoints (every
    CHECKPOINT_EVERY entries, and at close): a clean stop leaves one naming BRIDGE_STOPPED."""
    gov = await harness.governor()
    await gov.start()
    decision = await gov.decide(command("move", {"linear_x": 0.1, "angular_z": 0.0}), PLANNER)
    assert decision.outcome == Outcome.EXECUTED
    await gov.stop()
    await harness.restart()
    point = json.loads(point_path(harness.tmp / "audit.jsonl").read_bytes())["body"]
    last = harness.entries[-1]
    assert (point["seq"], point["audit_id"], point["last_event"]) == (
        last["seq"], last["audit_id"], "BRIDGE_STOPPED")


async def test_a_checkpoint_past_the_log_s_end_writes_no_point(tmp_path: Path,
                                                              clock: ManualClock) -> None:
    """The log cut below its checkpoint (by someone else, while it ran): no point, an error
    the log's hook logs; before, the replay read past the end forever and hung the log's
    close (tests/api/test_hitl_audit.py's cut-back log)."""
    run = await Run.open(tmp_path, clock)
    await run.add(AuditEvent.BRIDGE_STARTED, params={"estop_latched": False, "locks": {}})
    await run.audit.close()
    size = run.path.stat().st_size
    past = Checkpoint(seq=9, audit_id="sha256:" + "0" * 64, start=size, end=size + 100)
    with pytest.raises(ValueError, match=r"is not where the log's writer put it \(its entry's "
                       r"span .* is not in the log\)"):
        write_point(run.path, past, _pubkey(tmp_path), lambda body: b"")


async def test_a_point_that_is_no_regular_file_is_not_read(
        tmp_path: Path, clock: ManualClock, caplog: pytest.LogCaptureFixture) -> None:
    """A FIFO in the point's place (or a link to a device): the start does not wait on it
    for a writer that never comes (before: `read_bytes` blocked the start, and with it the
    e-stop, for good) — it replays from the boundary, and says why."""
    import os
    import threading

    run = await _crashed_with_an_arm(tmp_path, clock)
    point_path(run.path).unlink()
    os.mkfifo(point_path(run.path))
    found: list[tuple[bool, list[str], list[str]]] = []
    replay = threading.Thread(target=lambda: found.append(
        _left_ids(run, pubkey=_pubkey(tmp_path))), daemon=True)
    replay.start()
    replay.join(30)
    blocked = replay.is_alive()  # on the FIFO's open, for a writer
    if blocked:  # (let the blocked open go, so the thread ends)
        os.close(os.open(point_path(run.path), os.O_WRONLY | os.O_NONBLOCK))
        replay.join(30)
    assert not blocked
    assert found == [(True, ["arm_joint-1"], ["navigate-2"])]
    assert "not a regular file" in caplog.text


async def test_a_huge_point_is_not_read(tmp_path: Path, clock: ManualClock,
                                        caplog: pytest.LogCaptureFixture) -> None:
    """A point far larger than any the replay's state makes is not read into memory (a
    start reading gigabytes before its e-stop answers): refused by its size, unread."""
    from rcan_rtps.governance.resume import MAX_POINT_BYTES

    run = await _crashed_with_an_arm(tmp_path, clock)
    with point_path(run.path).open("r+b") as file:  # sparse: no disk, no memory here
        file.truncate(MAX_POINT_BYTES + 1)
    assert _left_ids(run, pubkey=_pubkey(tmp_path)) == (True, ["arm_joint-1"], ["navigate-2"])
    assert f"larger than {MAX_POINT_BYTES}" in caplog.text


async def test_goals_past_the_list_s_bound_are_still_taken_back(tmp_path: Path,
                                                              clock: ManualClock) -> None:
    """A crashed run left more goals running than the list names by id (MAX_LEFT): the
    oldest are not dropped (before: the 6 oldest of 70 were in no list, and ran on after the
    start's take-back with nobody to cancel them) — their server's every goal is cancelled
    (one listed with no goal id), as for a goal whose id was never recorded. With or without
    the start point."""
    from rcan_rtps.governance.resume import MAX_LEFT

    run = await Run.open(tmp_path, clock)
    await run.add(AuditEvent.BRIDGE_STARTED, params={"estop_latched": False, "locks": {}})
    ids = [f"00000000-0000-4000-8000-{n:012d}" for n in range(MAX_LEFT + 6)]
    for n, goal_id in enumerate(ids):
        await run.command("navigate", {"x": 1.0, "y": 2.0, "yaw": 0.0},
                          "/robot1/navigate_to_pose", goal_id=goal_id)
        if n == MAX_LEFT:
            await run.point()
    await run.crash()
    for pubkey in (None, _pubkey(tmp_path)):
        goals = resume(run.path, now_ms=int(clock.time() * 1000), pubkey=pubkey).left.goals
        named = {g.goal_id for g in goals}
        everything = [g for g in goals if g.goal_id is None]
        assert named - {None} == set(ids[-len(named - {None}):])
        assert [g.server for g in everything] == ["/robot1/navigate_to_pose"]
        assert len(goals) <= MAX_LEFT


def test_goals_of_too_many_servers_past_the_bound_cancel_every_goal() -> None:
    """Past the bound, goals of more servers than half the list holds: one listed for every
    goal of every server (no server, no id), then the newest by id; still at most MAX_LEFT."""
    from rcan_rtps.governance.left import LeftGoal
    from rcan_rtps.governance.resume import MAX_LEFT, _goals_left

    goals = [LeftGoal(message_id=f"m{n}", action="navigate", principal="planner",
                      server=f"/server{n}", goal_id=f"00000000-0000-4000-8000-{n:012d}")
             for n in range(2 * MAX_LEFT)]
    left = _goals_left(goals)
    assert len(left) == MAX_LEFT
    assert (left[0].server, left[0].goal_id) == (None, None)
    assert left[1:] == goals[-(MAX_LEFT - 1):]
    assert _goals_left(goals[:MAX_LEFT]) == goals[:MAX_LEFT]


@pytest.mark.parametrize(("outcome", "listed"), [
    ("unknown", True), ("lost", True), ("succeeded", False), ("canceled", False),
    ("aborted", False)])
async def test_a_goal_finished_with_no_end_seen_is_still_taken_back(
        tmp_path: Path, clock: ManualClock, outcome: str, listed: bool) -> None:
    """A GOAL_FINISHED that saw no end: a goal its server accepted after its send gave up,
    whose cancel went unanswered and whose end was not seen within its watch (`unknown`:
    `SentGoals._late_goal`), or whose server was lost from sight (`lost`). It may run still:
    a crash after it leaves it to the start (before: ended, it was in no list, and ran on
    with nobody to cancel it). An end its server listed ends it."""
    goal_id = "00000000-0000-4000-8000-0000000000aa"
    run = await Run.open(tmp_path, clock)
    await run.add(AuditEvent.BRIDGE_STARTED, params={"estop_latched": False, "locks": {}})
    sent = await run.command("navigate", {"x": 1.0, "y": 2.0, "yaw": 0.0},
                             "/robot1/navigate_to_pose", goal_id=goal_id)
    await run.add(AuditEvent.COMMAND_FAILED, principal="planner", message_id=sent,
                  action_type="navigate", outcome="failed", goal_id=goal_id)
    await run.point()
    await run.add(AuditEvent.GOAL_FINISHED, message_id=sent, params={"goal_id": goal_id},
                  outcome=outcome, deny_reason="accepted after its send had given up",
                  ros2_topic="/robot1/navigate_to_pose")
    await run.crash()
    for pubkey in (None, _pubkey(tmp_path)):
        found = resume(run.path, now_ms=int(clock.time() * 1000), pubkey=pubkey)
        assert [g.goal_id for g in found.left.goals] == ([goal_id] if listed else [])


async def test_a_point_that_cannot_be_written_is_said_in_one_line(
        tmp_path: Path, clock: ManualClock, caplog: pytest.LogCaptureFixture) -> None:
    """The log cut below its checkpoint while it ran (by someone else): the point is not
    written, and the log says why in one line at each checkpoint — never a traceback (before:
    `audit checkpoint hook failed` with the ValueError's traceback, every 1000 entries)."""
    run = await Run.open(tmp_path, clock)
    await run.add(AuditEvent.BRIDGE_STARTED, params={"estop_latched": False, "locks": {}})
    cut = run.path.stat().st_size
    await run.command("move", {"linear_x": 0.2, "angular_z": 0.0}, "/robot1/cmd_vel")
    with run.path.open("r+b") as file:
        file.truncate(cut)
    await run.audit.checkpoint()
    await run.audit.close()
    assert "audit start point not written (checkpoint 2 is not where the log's writer put it" \
        in caplog.text and "is not in the log" in caplog.text
    assert not [r for r in caplog.records if r.exc_info]


@pytest.mark.parametrize(("planted", "said"), [
    (b"garbage", "an audit line not JSON"),
    (b"[3, 1]", "an audit line that is no entry"),
    (b"[" * 50_000 + b"]" * 50_000, "an audit line nested too deeply"),
])
async def test_a_line_planted_in_a_running_log_is_named_not_taken(
        tmp_path: Path, clock: ManualClock, caplog: pytest.LogCaptureFixture,
        planted: bytes, said: str) -> None:
    """A line written into the log by someone else while it ran shifts the entries after it:
    no start point is written naming the writer's offsets (before: one was written for a
    deep line, to be refused at the next start), said in one line; the next start's replay
    latches, naming what the line is (before: json's bare "Expecting value")."""
    run = await Run.open(tmp_path, clock)
    await run.add(AuditEvent.BRIDGE_STARTED, params={"estop_latched": False, "locks": {}})
    with run.path.open("ab") as file:
        file.write(planted + b"\n")
    await run.command("move", {"linear_x": 0.2, "angular_z": 0.0}, "/robot1/cmd_vel")
    await run.audit.checkpoint()
    await run.audit.close()
    assert "audit start point not written (checkpoint 2 is not where the log's writer put " \
        "it" in caplog.text
    assert not point_path(run.path).exists()
    assert not [r for r in caplog.records if r.exc_info]
    found = resume(run.path, now_ms=int(clock.time() * 1000), pubkey=_pubkey(tmp_path))
    assert found.latched and said in (found.latched_by or "")


async def test_goals_listed_with_no_id_on_two_servers_are_both_kept(
        tmp_path: Path, clock: ManualClock) -> None:
    """A list of motion left that names, with no goal id, every goal of two servers under one
    command (a clean stop's goals whose command was forgotten are named `""`, and past the
    list's bound each server's are folded into one such): both servers' are kept (before:
    keyed by principal, command and action alone, the second replaced the first, whose
    server's goals the start then did not cancel)."""
    every = [{"message_id": "", "action": "", "principal": None, "server": server,
              "goal_id": None} for server in ("/robot1/navigate_to_pose", "/robot1/dock")]
    run = await Run.open(tmp_path, clock)
    await run.add(AuditEvent.BRIDGE_STOPPED, params={
        "estop_latched": False, "locks": {}, "left_running": {"goals": every}})
    await run.crash()
    for pubkey in (None, _pubkey(tmp_path)):
        goals = resume(run.path, now_ms=int(clock.time() * 1000), pubkey=pubkey).left.goals
        assert sorted(str(g.server) for g in goals) == ["/robot1/dock",
                                                        "/robot1/navigate_to_pose"]
