"""A stop withdraws the held motion it is a stop for (after red team 25).

Red team 25 had motion held for a human refused `stopped` when approved after a stop of the
robot (a `stop`, an e-stop, a session loss's halt) — but left it in the held-command list:
approvers were shown commands they could only be refused. And a stop of one principal's
motion alone (its connection closing, its control session lapsing while another principal
drives) left that principal's held motion approvable: an approval later started motion for
a client that was gone.

Each such stop now withdraws that held motion in its own step (`Governor._withdraw_held`):
HITL_WITHDRAWN by its issuer, the reason naming the stop; `hitl_withdrawn` in its issuer's
pending record; out of the list, and the governance channel (the approvals frames) told.
Held commands that are not motion stay, and so does other principals' held motion when the
stop was one principal's own."""

from __future__ import annotations

import asyncio
import threading
from typing import Any

import pytest
from govhelpers import ADMIN, OPS, PLANNER, Harness, command, principal

from rcan_rtps.governance import estop
from rcan_rtps.governance.governor import (
    BRIDGE_STOPPING,
    CONNECTION_CLOSED,
    ROBOT_STOPPED,
    SESSION_LOST,
    Governor,
)
from rcan_rtps.governance.rbac import Principal
from rcan_rtps.rcan import Outcome, Role

ARM = {"joints": ["shoulder", "elbow"], "positions": [0.1, -0.2], "duration_s": 2.0}
GATES = ("[{action: arm_joint, require_auth: true, authorized_roles: [OWNER]}, "
         "{action: lock, require_auth: true, authorized_roles: [OWNER]}]")
TWO_OWNERS = ("[{action: arm_joint, require_auth: true, approvals: 2, "
              "authorized_roles: [OWNER]}]")
OTHER = principal("other", Role.USER)
OPS2 = principal("ops2", Role.OWNER)
ENDS = {"HITL_AUTHORIZED", "HITL_DENIED", "HITL_WITHDRAWN", "HITL_EXPIRED"}


async def _held(gov: Governor, who: Principal, action: str = "arm_joint") -> str:
    params = ARM if action == "arm_joint" else {"name": "teleop"}
    held = await gov.decide(command(action, params), who)
    assert held.outcome is Outcome.PENDING_AUTH and held.pending_id, held
    return held.pending_id


def _withdrawals(harness: Harness) -> dict[str, tuple[str, list[str | None]]]:
    """pending id → (who withdrew it, the reasons its HITL_WITHDRAWN entry names)."""
    return {e["pending_id"]: (e["principal"], [r.get("reason") for r in e["approvals"]])
            for e in harness.entries if e["event"] == "HITL_WITHDRAWN"}


class Scene:
    """PLANNER's held arm_joint and lock, OTHER's held arm_joint; what the list was each time
    the governance channel (the approvals frames, STATUS) was told of a change."""

    def __init__(self, gov: Governor, harness: Harness) -> None:
        self.gov, self.harness = gov, harness
        self.told: list[set[str]] = []
        gov.events.governance.subscribe(
            lambda: self.told.append({p.pending_id for p in gov.pending()}))

    async def hold(self) -> Scene:
        self.arm = await _held(self.gov, PLANNER)
        self.lock = await _held(self.gov, PLANNER, "lock")
        self.theirs = await _held(self.gov, OTHER)
        return self

    async def settled(self) -> None:
        await asyncio.gather(*self.gov._tasks)

    def withdrawn(self, expected: dict[str, tuple[str, str]]) -> None:
        """Exactly `expected` (pending id → (issuer, reason)) withdrawn, each by its issuer,
        resolved `hitl_withdrawn` for it to read; the list is the rest, and was told so."""
        assert _withdrawals(self.harness) == {
            pending_id: (who, [reason]) for pending_id, (who, reason) in expected.items()}
        for pending_id in expected:
            record = self.gov.pending_record(pending_id)
            assert record is not None and record.state == "resolved"
            assert record.decision is not None and record.decision.reason == "hitl_withdrawn"
        refused = [e for e in self.harness.entries if e["event"] == "COMMAND_REJECTED"]
        assert refused == []  # each withdrawn once: none found taken by an earlier one
        left = {self.arm, self.lock, self.theirs} - set(expected)
        assert {p.pending_id for p in self.gov.pending()} == left
        assert self.told[-1] == left  # the last change told is the list as it is now

    async def unapprovable(self, *pending_ids: str) -> None:
        for pending_id in pending_ids:
            late = await self.gov.authorize(pending_id, OPS)
            assert (late.http_status, late.reason) == (404, "pending_not_found"), late
        assert "arm_joint" not in [a for a, _ in self.harness.dispatcher.calls]


@pytest.fixture
async def scene(harness: Harness) -> Scene:
    gov = await harness.governor(gates=GATES)
    return await Scene(gov, harness).hold()


async def test_an_estop_withdraws_all_held_motion(scene: Scene) -> None:
    await scene.gov.decide(command("estop"), OTHER)  # anyone's e-stop stops all
    await scene.settled()
    why = ROBOT_STOPPED.format("an e-stop")
    scene.withdrawn({scene.arm: ("planner", why), scene.theirs: ("other", why)})
    cleared = await scene.gov.decide(command("clear_estop"), ADMIN)
    assert cleared.outcome is Outcome.EXECUTED
    await scene.unapprovable(scene.arm, scene.theirs)


async def test_a_stop_withdraws_all_held_motion(scene: Scene) -> None:
    stopped = await scene.gov.decide(command("stop"), OPS2)
    assert stopped.outcome is Outcome.EXECUTED
    await scene.settled()
    why = ROBOT_STOPPED.format("a stop by 'ops2'")
    scene.withdrawn({scene.arm: ("planner", why), scene.theirs: ("other", why)})
    await scene.unapprovable(scene.arm, scene.theirs)
    # The stop's entry comes first: the withdrawals are what it did to held motion.
    events = [e["event"] for e in scene.harness.entries]
    assert events.index("HITL_WITHDRAWN") > events.index("COMMAND_DISPATCHED")


async def test_a_session_loss_halt_withdraws_all_held_motion(scene: Scene) -> None:
    """PLANNER's move opened a control session; nobody else drives when it lapses: a halt
    of the robot, a stop of all motion, held motion too."""
    gov, harness = scene.gov, scene.harness
    assert (await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)).outcome is \
        Outcome.EXECUTED
    harness.clock.advance(3)  # past `session_timeout_s` (2 s)
    await gov.sweep()
    await scene.settled()
    assert harness.dispatcher.calls[-1] == ("stop", {})  # the halt
    why = ROBOT_STOPPED.format("a halt for the lost control session of 'planner'")
    scene.withdrawn({scene.arm: ("planner", why), scene.theirs: ("other", why)})
    await scene.unapprovable(scene.arm, scene.theirs)


async def test_a_session_lost_while_another_drives_withdraws_only_its_held_motion(
        scene: Scene) -> None:
    """PLANNER's move opened a session; OTHER's move replaced it and OTHER stays: PLANNER's
    lapse stops PLANNER's motion alone (scope own), its held motion included — OTHER's held
    arm_joint still waits, and runs once approved."""
    gov, harness = scene.gov, scene.harness
    for who in (PLANNER, OTHER):
        moved = await gov.decide(command("move", {"linear_x": 0.2}), who)
        assert moved.outcome is Outcome.EXECUTED, moved
    for _ in range(6):  # 3 s: OTHER heartbeats, PLANNER is silent
        harness.clock.advance(0.5)
        gov.heartbeat(OTHER)
        await gov.sweep()
    await scene.settled()
    [lost] = [e for e in harness.entries if e["event"] == "NETWORK_LOSS_SAFE_STOP"]
    assert (lost["principal"], lost["applied"]["scope"]) == ("planner", "own")
    why = SESSION_LOST.format("no command or heartbeat for 2 s")
    scene.withdrawn({scene.arm: ("planner", why)})
    await scene.unapprovable(scene.arm)
    ran = await gov.authorize(scene.theirs, OPS)
    assert ran.outcome is Outcome.EXECUTED, ran
    gov.end_streams()


async def test_a_closed_connection_withdraws_only_its_principals_held_motion(
        scene: Scene) -> None:
    """PLANNER's connection closes with no control session (nothing of its moved): no stop
    is recorded, nothing is sent, and its held motion is withdrawn — only its own. (As the
    WebSocket does: `connection_closed` first, then `end_session`, which calls it again.)"""
    gov, harness = scene.gov, scene.harness
    assert gov.connection_closed(PLANNER) is False  # nothing of its on its way
    assert await gov.end_session(PLANNER) is None
    await scene.settled()
    scene.withdrawn({scene.arm: ("planner", CONNECTION_CLOSED)})
    await scene.unapprovable(scene.arm)
    assert "NETWORK_LOSS_SAFE_STOP" not in [e["event"] for e in harness.entries]
    ran = await gov.authorize(scene.theirs, OPS)
    assert ran.outcome is Outcome.EXECUTED, ran


async def test_an_approval_counted_while_a_stop_comes_counts_and_then_it_is_withdrawn(
        harness: Harness) -> None:
    """Of two approvals needed, the first is being written (HITL_APPROVAL, under the held
    command's lock) when a stop comes: it counts, and the withdrawal — waiting for that lock
    — ends the command next. The second approval is refused; nothing runs."""
    gov = await harness.governor(gates=TWO_OWNERS)
    pending_id = await _held(gov, PLANNER)
    first = asyncio.ensure_future(gov.authorize(pending_id, OPS))
    held = gov._desk._pending.get(pending_id)
    assert held is not None
    for _ in range(1000):  # until its review holds the command's lock, its entry being written
        if held.lock.locked() or first.done():
            break
        await asyncio.sleep(0)
    assert held.lock.locked() and not first.done()
    await gov.decide(command("stop"), OPS2)
    assert (await first).http_status == 202
    await asyncio.gather(*gov._tasks)
    assert _withdrawals(harness) == {  # with the approval it had (no reason given)
        pending_id: ("planner", [None, ROBOT_STOPPED.format("a stop by 'ops2'")])}
    late = await gov.authorize(pending_id, ADMIN)
    assert (late.http_status, late.reason) == (404, "pending_not_found"), late
    assert [a for a, _ in harness.dispatcher.calls] == ["stop"]


def _ends(harness: Harness, pending_id: str) -> list[dict[str, Any]]:
    return [e for e in harness.entries if e["event"] in ENDS and e.get("pending_id") == pending_id]


@pytest.mark.parametrize("stop", ["stop", "estop"])
@pytest.mark.parametrize("first", ["approval", "stop"])
async def test_an_approval_and_a_stop_in_the_same_loop_turn(harness: Harness, stop: str,
                                                            first: str) -> None:
    """Both arrive in one turn of the loop, in either order. Whatever the governor takes
    first, the held arm_joint never reaches the robot after the stop, ends once, and is out
    of the list.

    A stop taken first withdraws it, and the approval finds nothing. An e-stop latches as it
    arrives, before the approval's review (its own task) runs: the same. An approval taken
    before a `stop` (decided in a task of its own) runs it as motion decided before the
    stop: sent before the stop's halt when its entry was written inline, in the approval's
    first step (the stop then stops it as any motion), else refused `stopped` once the stop
    came (`_carry_out`); either way it was taken before the stop, so nothing is withdrawn."""
    gov = await harness.governor()
    pending_id = await _held(gov, PLANNER)
    approving = lambda: gov.authorize(pending_id, OPS)  # noqa: E731
    stopping = lambda: gov.decide(command(stop), OPS2)  # noqa: E731
    calls = [approving, stopping] if first == "approval" else [stopping, approving]
    answers = await asyncio.gather(*(asyncio.ensure_future(call()) for call in calls))
    approved = answers[calls.index(approving)]
    await asyncio.gather(*gov._tasks)
    actions = [a for a, _ in harness.dispatcher.calls]
    # Motion cannot be sent after the halt (checked with no await before the publish), and
    # is recorded before the stop's own send if it was sent before the halt.
    assert "arm_joint" not in actions[actions.index(stop):], actions
    assert gov.pending() == []
    [end] = _ends(harness, pending_id)
    if first == "approval" and stop == "stop":  # the approval took it before the stop
        assert _withdrawals(harness) == {}
        if "arm_joint" in actions:
            assert approved.outcome is Outcome.EXECUTED, approved
        else:
            assert (approved.http_status, approved.reason) == (409, "stopped"), approved
    else:
        assert (approved.http_status, approved.reason) == (404, "pending_not_found"), approved
        assert "arm_joint" not in actions
        cause = "an e-stop" if stop == "estop" else "a stop by 'ops2'"
        assert (end["event"], end["approvals"][-1]["reason"]) == (
            "HITL_WITHDRAWN", ROBOT_STOPPED.format(cause))


async def test_the_bridge_stopping_withdraws_every_held_command_before_bridge_stopped(
        scene: Scene) -> None:
    """Held commands live in memory alone: a bridge that stopped with them held left each a
    PENDING_AUTH with no end in its log, and told no issuer. Its stop withdraws them all —
    motion or not, anyone's — each by its issuer, before BRIDGE_STOPPED."""
    gov, harness = scene.gov, scene.harness
    await gov.start()
    await gov.stop()
    scene.withdrawn({pending_id: (who, BRIDGE_STOPPING) for pending_id, who in (
        (scene.arm, "planner"), (scene.lock, "planner"), (scene.theirs, "other"))})
    events = [e["event"] for e in harness.entries]
    assert events[-1] == "BRIDGE_STOPPED"
    assert events.count("HITL_WITHDRAWN") == 3
    assert harness.dispatcher.calls == []  # nothing of them ran


async def test_a_held_command_past_its_ttl_when_the_bridge_stops_is_expired_first(
        harness: Harness) -> None:
    """`withdrawing` leaves a command past its TTL to the sweeper, which the bridge's stop
    ends: one no sweep had come for yet was left a PENDING_AUTH with no end in the log, and
    what awaited its end (a held INVOKE's answer) waited for good."""
    gov = await harness.governor(gates=GATES, hitl_timeout=60)
    held = await _held(gov, PLANNER)
    ended = gov.held_ended(held)
    assert ended is not None
    harness.clock.advance(61)  # past its TTL
    await gov.stop()  # (never started: no sweeper comes for it)
    events = [e["event"] for e in harness.entries]
    assert events[-2:] == ["HITL_EXPIRED", "BRIDGE_STOPPED"], events
    assert ended.done() and ended.result().decision.reason == "pending_expired"


async def test_an_expiry_cut_off_ends_what_awaits_each_held_command_it_took(
        harness: Harness) -> None:
    """The sweeper cancelled as the bridge stops, in the middle of an expiry: the held
    commands it had taken out of the store after the one being written were never ended, and
    a held INVOKE's answer waited on each for good."""
    gov = await harness.governor(gates=GATES, hitl_timeout=60)
    ids = [await _held(gov, PLANNER), await _held(gov, OTHER), await _held(gov, PLANNER)]
    ends = [gov.held_ended(pending_id) for pending_id in ids]
    harness.clock.advance(61)
    expiring = asyncio.ensure_future(gov.expire_pending())
    while not any(e["event"] == "HITL_EXPIRED" for e in harness.entries):
        await asyncio.sleep(0)  # it took them all, and writes one after another
    expiring.cancel()
    await asyncio.gather(expiring, return_exceptions=True)
    assert gov.pending() == []
    assert all(end is not None and end.done() for end in ends), ends


async def test_no_motion_reaches_the_robot_once_the_bridge_began_stopping(
        scene: Scene) -> None:
    """The run's stop ends the streams, then halts the robot (`end_streams`, then the
    dispatcher's halt): motion decided after that — an approval or a command already past
    the API, in a task of its own — must never be sent after the halt, which is the last
    thing the robot hears from this bridge. Before, only motion decided before the streams
    ended was refused (its stop mark); one decided after went to the robot."""
    gov, harness = scene.gov, scene.harness
    await gov.start()
    gov.end_streams()
    approved = await gov.authorize(scene.arm, OPS)
    moved = await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    assert (approved.reason, moved.reason) == ("stopped", "stopped"), (approved, moved)
    assert [a for a, _ in harness.dispatcher.calls if a != "stop"] == []
    stopped = await gov.decide(command("stop"), PLANNER)  # a stop still stops
    assert stopped.outcome is Outcome.EXECUTED


async def test_no_estop_clear_reaches_the_robot_once_the_bridge_began_stopping(
        harness: Harness) -> None:
    """Red team 28: a clear_estop tells the robot its e-stop is released (`{"data": false}` on
    the latched e-stop topic) and persists the latch file unlatched. One decided after the
    streams ended — or waiting for the robot when they did (in a task of its own past the
    API, which the run's stop awaits only after the robot's halt) — went out after the halt:
    the last thing the robot heard from the bridge was its e-stop released, and the next
    start began unlatched. Now it is refused `stopped` as motion is; the latch holds."""
    gov = await harness.governor()
    await gov.start()
    await gov.decide(command("estop"), OPS)
    gov.end_streams()
    late = await gov.decide(command("clear_estop"), ADMIN)
    assert (late.outcome, late.reason) == (Outcome.DENIED, "stopped"), late
    assert [a for a, _ in harness.dispatcher.calls if a == "clear_estop"] == []
    assert gov.latch.latched


async def test_an_estop_clear_waiting_for_the_robot_as_the_bridge_stops_is_refused(
        harness: Harness) -> None:
    """(as above) The clear waited for the robot (`ready`) when the streams ended."""
    gov = await harness.governor()
    await gov.start()
    await gov.decide(command("estop"), OPS)
    robot = harness.dispatcher
    wait, entered, ready = asyncio.Event(), asyncio.Event(), robot.ready

    async def slow_ready(cmd: Any) -> str | None:
        entered.set()
        await wait.wait()
        return await ready(cmd)

    robot.ready = slow_ready  # type: ignore[method-assign]
    clearing = asyncio.ensure_future(gov.decide(command("clear_estop"), ADMIN))
    await entered.wait()
    gov.end_streams()  # the run's stop: streams ended, then the robot halted
    wait.set()
    waited = await clearing
    assert waited.outcome is not Outcome.EXECUTED and waited.reason == "stopped", waited
    assert [a for a, _ in robot.calls if a == "clear_estop"] == []
    assert gov.latch.latched
    assert gov.latch.file.load(first_start=False)[0]  # the next start is latched too


async def test_an_estop_clear_whose_latch_file_write_spans_the_bridges_stop_is_undone(
        harness: Harness) -> None:
    """(as above) The streams ended while the clear's `false` was being written to the
    latch file (past the clear's last look before the write): it is not unlatched nor
    published, and the file is latched again — the next start is latched too."""
    gov = await harness.governor()
    await gov.start()
    await gov.decide(command("estop"), OPS)
    file, robot = gov.latch.file, harness.dispatcher
    wait, entered, write = asyncio.Event(), asyncio.Event(), file.write

    async def slow_write(latched: bool, by: str, at_ms: int) -> None:
        if not latched:
            entered.set()
            await wait.wait()
        await write(latched, by, at_ms)

    file.write = slow_write  # type: ignore[method-assign]
    clearing = asyncio.ensure_future(gov.decide(command("clear_estop"), ADMIN))
    await entered.wait()
    gov.end_streams()
    wait.set()
    waited = await clearing
    assert waited.outcome is not Outcome.EXECUTED and waited.reason == "stopped", waited
    assert [a for a, _ in robot.calls if a == "clear_estop"] == []
    assert gov.latch.latched
    assert file.load(first_start=False)[0]


async def test_an_estop_in_the_window_of_a_clear_undone_by_the_stop_keeps_its_own_latch(
        harness: Harness, monkeypatch: pytest.MonkeyPatch) -> None:
    """(red team 29) An e-stop came while the clear's `false` was being written, and the
    streams ended before the clear looked again: the e-stop's own `true` (queued after the
    `false`) latches the file, naming who e-stopped; the clear undone must not write it over
    with the bridge's name, nor take the latch back to the e-stop before the clear (a repeat
    is answered with the entry that latched it: the later e-stop's)."""
    gov = await harness.governor()
    await gov.start()
    await gov.decide(command("estop"), ADMIN)
    writing, go = threading.Event(), threading.Event()
    write = estop.atomic_write

    def slow_write(path: Any, data: bytes) -> None:  # the disk, slow for the clear's `false`
        if b'"latched":false' in data:
            writing.set()
            go.wait(10)
        write(path, data)

    monkeypatch.setattr(estop, "atomic_write", slow_write)
    clearing = asyncio.ensure_future(gov.decide(command("clear_estop"), ADMIN))
    while not writing.is_set():
        await asyncio.sleep(0.01)
    stopped = asyncio.ensure_future(gov.decide(command("estop"), OPS))
    await asyncio.sleep(0)  # its first step: its `true` is queued after the `false`
    gov.end_streams()
    go.set()
    waited, later = await clearing, await stopped
    assert waited.reason == "stopped" and later.outcome is Outcome.EXECUTED, (waited, later)
    assert gov.latch.file.path.read_bytes().count(b'"by":"ops"') == 1  # who e-stopped
    again = await gov.decide(command("estop"), OPS)
    assert again.reason == "already_latched" and again.audit_id == later.audit_id, again
