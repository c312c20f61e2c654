"""The wall clock set forward between a crash and the restart (NTP's first sync, `date -s`)
must not make an arm trajectory the crashed run left running look ended: the restart would
not take it back. An arm trajectory's entry records the boot clock (`boot`: the boot's id
and ms on CLOCK_BOOTTIME, never stepped); a restart in the same boot dates it by that.
Another boot, an entry without the stamp (written before it) or a platform without a boot
clock: the wall clock dates it, as before.

`ManualClock.step` moves the wall clock alone; `ManualClock.reboot` starts another boot."""

from __future__ import annotations

from pathlib import Path

from govhelpers import OPS, PLANNER, Harness, command
from test_crash_left_running import LONG, Log

from rcan_rtps.governance.audit import AuditEvent, load_or_create_key
from rcan_rtps.governance.clock import BootInstant, ManualClock
from rcan_rtps.governance.resume import point_path, resume
from rcan_rtps.rcan import Outcome

RUNS_S = 600.0  # the crashed run's arm trajectory
PAST_ITS_END_S = 3600.0  # a wall-clock step forward, well past its end


async def _crashed_with_an_arm(harness: Harness) -> str:
    """A run that sent an arm a trajectory of RUNS_S and was killed; restarted 10 s later
    (the clock moved after the kill: moved before it, the run's own sweep would stop the
    arm, its planner silent past the session timeout)."""
    gov = await harness.governor(gates="[]")
    await gov.start()
    arm = await gov.decide(command("arm_joint", {"joints": ["elbow"], "positions": [0.8],
                                                 "duration_s": RUNS_S}), PLANNER)
    assert arm.outcome is Outcome.EXECUTED and arm.message_id is not None, arm
    await harness.restart()  # no BRIDGE_STOPPED: a crash
    harness.clock.advance(10)
    return arm.message_id


async def _taken_back(harness: Harness) -> list[str]:
    """Restarted: the message ids of the arm trajectories its start took back."""
    harness.dispatcher.left.clear()
    gov = await harness.governor(gates="[]")
    await gov.start()
    arms = [a.message_id for left in harness.dispatcher.left for a in left.arms]
    await gov.stop()
    return arms


async def test_an_arm_trajectory_s_entry_records_the_boot_clock(harness: Harness) -> None:
    """On the arm trajectory's entry only: a goal's and a stop's have none (nothing new on
    the path of a stop)."""
    harness.clock.advance(5)
    gov = await harness.governor(gates="[]")
    await gov.start()
    for action, params in (
            ("arm_joint", {"joints": ["elbow"], "positions": [0.8], "duration_s": 1.0}),
            ("navigate", {"x": 1.0, "y": 0.0, "yaw": 0.0}), ("stop", {})):
        decided = await gov.decide(command(action, params), PLANNER)
        assert decided.outcome is Outcome.EXECUTED, decided
    await gov.stop()
    stamps = {e["action_type"]: e.get("boot") for e in harness.entries
              if e["event"] == "COMMAND_DISPATCHED"}
    assert stamps == {"arm_joint": {"boot_id": "manual-boot-1", "ms": 5000},
                      "navigate": None, "stop": None}


async def test_a_wall_clock_set_forward_across_the_restart_in_the_same_boot_drops_no_arm(
        harness: Harness) -> None:
    """Set forward an hour past its end while it still has 590 s to run: still taken back
    (before, it was judged ended by the wall clock and left to run)."""
    arm_id = await _crashed_with_an_arm(harness)
    harness.clock.step(PAST_ITS_END_S)
    assert await _taken_back(harness) == [arm_id]


async def test_the_start_point_keeps_the_stamp(harness: Harness) -> None:
    """The replay from the start point written at the log's last checkpoint and the replay
    from the boundary date the arm alike."""
    arm_id = await _crashed_with_an_arm(harness)
    harness.clock.step(PAST_ITS_END_S)
    path = harness.tmp / "audit.jsonl"
    assert b"sent_boot_id" in point_path(path).read_bytes()
    pubkey = load_or_create_key(harness.tmp / "audit.key").public_key()
    now_ms, boot = int(harness.clock.time() * 1000), harness.clock.boot()
    from_point = resume(path, now_ms=now_ms, boot=boot, pubkey=pubkey)
    from_boundary = resume(path, now_ms=now_ms, boot=boot)
    assert from_point == from_boundary
    assert [a.message_id for a in from_point.left.arms] == [arm_id]


async def test_an_approved_arm_trajectory_is_dated_by_the_boot_clock_too(
        harness: Harness) -> None:
    """Held for approval, then approved: its HITL_AUTHORIZED entry is the one it was sent
    after, and records the boot clock of that moment."""
    gov = await harness.governor()  # (arm_joint needs an OWNER's approval)
    await gov.start()
    held = await gov.decide(command("arm_joint", {"joints": ["elbow"], "positions": [0.8],
                                                  "duration_s": RUNS_S}), PLANNER)
    assert held.outcome is Outcome.PENDING_AUTH and held.pending_id, held
    harness.clock.advance(1.5)  # (within the planner's session timeout: no safe stop)
    approved = await gov.authorize(held.pending_id, OPS)
    assert approved.outcome is Outcome.EXECUTED, approved
    [authorized] = [e for e in harness.entries if e["event"] == "HITL_AUTHORIZED"]
    assert authorized["boot"] == {"boot_id": "manual-boot-1", "ms": 1500}
    await harness.restart()  # killed
    harness.clock.step(PAST_ITS_END_S)
    assert await _taken_back(harness) == [held.message_id]


async def test_a_wall_clock_set_back_in_the_same_boot_keeps_no_ended_arm(
        harness: Harness) -> None:
    """The boot clock says it ended (its time and settling are over): not taken back, though
    the wall clock, set back an hour, would have it still running."""
    await _crashed_with_an_arm(harness)
    harness.clock.advance(RUNS_S)
    harness.clock.step(-PAST_ITS_END_S)
    assert await _taken_back(harness) == []


async def test_the_boot_clock_dates_it_to_the_millisecond(harness: Harness) -> None:
    """Due until its time and settling (1 s) are over by the boot clock, whatever the wall
    clock did."""
    arm_id = await _crashed_with_an_arm(harness)  # 10 s after its send
    harness.clock.step(PAST_ITS_END_S)
    harness.clock.advance(RUNS_S + 1.0 - 10 - 0.001)
    assert await _taken_back(harness) == [arm_id]
    await harness.restart()
    harness.clock.advance(0.001)
    assert await _taken_back(harness) == []


async def test_another_boot_dates_it_by_the_wall_clock(harness: Harness) -> None:
    """The machine booted again: its boot clock tells nothing of the last boot's, and the
    wall clock dates the arm as before — still due by it: taken back; a step forward past
    its end: not (not covered: docs/governance.md)."""
    arm_id = await _crashed_with_an_arm(harness)
    harness.clock.reboot("manual-boot-2")
    assert await _taken_back(harness) == [arm_id]

    await harness.restart()
    harness.clock.reboot("manual-boot-3")
    harness.clock.step(PAST_ITS_END_S)
    assert await _taken_back(harness) == []


async def test_another_boot_with_the_wall_clock_behind_takes_it_back(
        harness: Harness) -> None:
    """Fail closed: a wall clock set back (a board without an RTC up at a stale time)
    makes the arm look due: held (harmless: it is held where it is)."""
    arm_id = await _crashed_with_an_arm(harness)
    harness.clock.advance(RUNS_S)  # ended
    harness.clock.reboot("manual-boot-2")
    harness.clock.step(-PAST_ITS_END_S)
    assert await _taken_back(harness) == [arm_id]


async def test_a_crash_during_the_halt_keeps_the_stamp_for_the_next_start(
        harness: Harness) -> None:
    """A crash loop: the arm a start could not hold is listed in its entries with its stamp,
    and the next start, in the same boot, still dates it by the boot clock."""
    arm_id = await _crashed_with_an_arm(harness)
    harness.dispatcher.unheard_arms = True
    gov = await harness.governor(gates="[]")
    await gov.start()  # the arm not held: left to the next start
    [started] = [e for e in harness.entries if e["event"] == "BRIDGE_STARTED"][-1:]
    [listed] = started["params"]["left_running"]["arms"]
    assert (listed["message_id"], listed["sent_boot_id"]) == (arm_id, "manual-boot-1")
    await harness.restart()  # killed again
    harness.dispatcher.unheard_arms = False
    harness.clock.step(PAST_ITS_END_S)
    assert await _taken_back(harness) == [arm_id]


async def test_a_platform_without_a_boot_clock_dates_it_by_the_wall_clock(
        tmp_path: Path) -> None:
    """No boot clock (macOS): no stamp is written, and the wall clock dates the arm."""
    harness = Harness(tmp_path, ManualClock(boot_id=None))
    try:
        arm_id = await _crashed_with_an_arm(harness)
        assert all("boot" not in e for e in harness.entries)
        assert await _taken_back(harness) == [arm_id]
        await harness.restart()
        harness.clock.step(PAST_ITS_END_S)
        assert await _taken_back(harness) == []
    finally:
        await harness.restart()


async def test_an_entry_written_before_the_stamp_is_dated_by_the_wall_clock(
        tmp_path: Path, clock: ManualClock) -> None:
    """An older log's arm entry, without `boot`: exactly as before, whatever the boot clock
    says — listed while due by the wall clock, not once that is past its end."""
    log = await Log.open(tmp_path, clock)
    await log.started()
    await log.arm("arm-1")  # (written as before: no boot stamp)
    await log.audit.close()
    assert "boot" not in log.path.read_text()
    due = log.now_ms() + round((LONG["duration_s"] + 1.0) * 1000)
    same_boot = BootInstant("manual-boot-1", 0)
    assert [a.message_id for a in resume(log.path, now_ms=due - 1, boot=same_boot).left.arms
            ] == ["arm-1"]
    assert resume(log.path, now_ms=due, boot=same_boot).left.arms == []


async def test_a_stamp_this_version_does_not_read_is_dated_by_the_wall_clock(
        tmp_path: Path, clock: ManualClock) -> None:
    """A misshapen stamp (another version's) neither fails the start nor dates the arm."""
    log = await Log.open(tmp_path, clock)
    await log.started()
    await log.add(AuditEvent.COMMAND_DISPATCHED, principal="planner", role="USER",
                  message_id="arm-1", action_type="arm_joint", params=LONG, applied=LONG,
                  outcome="executed", ros2_topic="/robot1/left_arm/joint_trajectory",
                  boot={"boot_id": "manual-boot-1", "ms": "soon"})
    await log.audit.close()
    due = log.now_ms() + round((LONG["duration_s"] + 1.0) * 1000)
    found = resume(log.path, now_ms=due, boot=BootInstant("manual-boot-1", 0))
    assert found.crashed and not found.latched and found.left.arms == []
