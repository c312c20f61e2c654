"""Red team 21: the wall clock stepped under a running bridge (NTP after a boot at 1970, an
operator's `date -s`, NTP stepping back a few seconds). A step may refuse or expire things;
it never re-admits a replay, keeps a stale approval alive, or runs a command twice.

`ManualClock.step` moves the wall clock alone; `advance` moves both clocks (time passing).
"""

from __future__ import annotations

from pathlib import Path

from govhelpers import OPS, PLANNER, Harness, command, principal

from rcan_rtps.governance import outcomes
from rcan_rtps.governance.audit import AuditEvent, AuditLog, AuditRecord
from rcan_rtps.governance.clock import LatestWall, ManualClock
from rcan_rtps.governance.governor import Governor
from rcan_rtps.governance.rbac import RateLimiter
from rcan_rtps.governance.replay import ReplayWindow
from rcan_rtps.rcan import Outcome, Role
from tests.governance.test_redteam20_audit import _logged

T = 1_800_000_000.0
HOUR = 3600.0


def test_latest_wall_never_goes_back_and_follows_a_step_forward() -> None:
    clock = ManualClock(T)
    latest = LatestWall(clock)
    clock.step(-HOUR)
    assert latest.time() == T
    clock.step(2 * HOUR)
    assert latest.time() == T + HOUR


# -- the replay window (§8.3) ------------------------------------------------------------------


def _taken_then_forgotten(clock: ManualClock, window: ReplayWindow) -> float:
    """A message taken, then its id forgotten once it went stale (another check forgets)."""
    sent = clock.time()
    assert window.check("m", sent) is None
    clock.advance(31)
    assert window.check("later", clock.time()) is None
    assert len(window) == 1  # "m" is forgotten
    return sent


def test_a_step_back_does_not_make_a_forgotten_message_fresh_again() -> None:
    """NTP steps back 2 s: a message stale and forgotten 1 s ago would be fresh by the clock
    now — it is refused as stale, not taken a second time."""
    clock = ManualClock(T)
    window = ReplayWindow(clock, window_s=30)
    sent = _taken_then_forgotten(clock, window)
    clock.step(-2)
    assert clock.time() - sent < 30  # fresh by the clock now
    replay = window.check("m", sent)
    assert replay is not None and replay.error_code.value == "MESSAGE_STALE"
    assert replay.reason == "older_than_30_s_before_the_clock_went_back"


def test_a_step_forward_then_back_does_not_re_admit_a_replay() -> None:
    """`date -s` an hour ahead (every id is forgotten as stale), then set right again."""
    clock = ManualClock(T)
    window = ReplayWindow(clock, window_s=30)
    sent = clock.time()
    assert window.check("m", sent) is None
    clock.step(HOUR)
    assert window.check("m", sent) is not None  # stale now
    assert window.check("ahead", clock.time()) is None
    assert len(window) == 1  # "m" was forgotten
    clock.step(-HOUR)
    replay = window.check("m", sent)
    assert replay is not None and replay.error_code.value == "MESSAGE_STALE"


def test_after_a_step_back_fresh_messages_pass_within_the_window_and_later_again() -> None:
    """A step back shorter than the window refuses nothing new; a longer one refuses what
    the clock stepped back from until the clock has passed it again."""
    clock = ManualClock(T)
    window = ReplayWindow(clock, window_s=30)
    assert window.check("a", clock.time()) is None
    clock.step(-5)
    assert window.check("b", clock.time()) is None
    clock.step(-HOUR)
    refused = window.check("c", clock.time())
    assert refused is not None and refused.reason.endswith("_before_the_clock_went_back")
    clock.advance(HOUR - 20)
    assert window.check("d", clock.time()) is None


async def test_a_start_behind_the_log_remembers_its_last_ids_until_the_clock_passes_them(
        tmp_path: Path) -> None:
    """The bridge restarts with the clock an hour behind its log (stepped back, or a start
    before NTP set it); NTP then steps it forward: a message the last run took seconds before
    it ended is fresh again — and a replay."""
    path = await _logged(tmp_path, T + HOUR, ["m-1"])
    clock = ManualClock(T)
    window = ReplayWindow(clock)
    window.remember_logged(path)
    clock.step(HOUR + 5)
    assert window.check("m-1", T + HOUR) == outcomes.REPLAY_DETECTED


async def test_a_start_reads_back_only_the_last_entries_of_a_log_ahead_of_it(
        tmp_path: Path) -> None:
    """Entries far older than the log's last are stale whatever the clock says now."""
    log = await AuditLog.open(tmp_path / "r.jsonl", tmp_path / "k.key",
                              clock=(at := ManualClock(T + HOUR)))
    await log.append(AuditRecord(event=AuditEvent.COMMAND_DISPATCHED, principal="p",
                                 message_id="old"))
    at.advance(600)
    await log.append(AuditRecord(event=AuditEvent.COMMAND_DISPATCHED, principal="p",
                                 message_id="new"))
    await log.close()
    assert ReplayWindow(ManualClock(T)).remember_logged(tmp_path / "r.jsonl") == 1


# -- HiTL approvals (§9) -------------------------------------------------------------------

ARM = {"joints": ["shoulder", "elbow"], "positions": [0.1, -0.2], "duration_s": 2.0}


async def _held(gov: Governor) -> str:
    d = await gov.decide(command("arm_joint", ARM), PLANNER)
    assert d.outcome is Outcome.PENDING_AUTH and d.pending_id
    return d.pending_id


async def test_a_step_back_keeps_no_held_command_past_its_ttl(harness: Harness,
                                                             gov: Governor) -> None:
    """The clock steps back an hour while a command waits (TTL 300 s): 301 s later it has
    expired, swept and audited; an approval then runs nothing."""
    pending_id = await _held(gov)
    harness.clock.step(-HOUR)
    harness.clock.advance(301)
    [expired] = await gov.expire_pending()
    assert (expired.reason, harness.entries[-1]["event"]) == ("pending_expired", "HITL_EXPIRED")
    late = await gov.authorize(pending_id, OPS)
    assert (late.http_status, late.reason) == (404, "pending_not_found")
    assert harness.dispatcher.calls == []


async def test_an_approval_after_a_step_back_past_the_ttl_is_refused_before_any_sweep(
        harness: Harness, gov: Governor) -> None:
    """Set back to 1970 (a board without an RTC reset by hand): the approval comes before the
    sweep ran, past the TTL as it is measured, and is refused as expired."""
    pending_id = await _held(gov)
    harness.clock.step(-harness.clock.time())
    harness.clock.advance(301)
    late = await gov.authorize(pending_id, OPS)
    assert (late.http_status, late.reason) == (404, "pending_expired")
    assert harness.dispatcher.calls == []


async def test_a_step_back_keeps_withdrawn_nothing_that_expired(harness: Harness,
                                                               gov: Governor) -> None:
    """A command past its TTL (the clock stepped back meanwhile) is left to expire, not
    withdrawn as if it still waited."""
    await _held(gov)
    harness.clock.step(-HOUR)
    harness.clock.advance(301)
    cancel = gov.motion_cancelled(PLANNER)
    await cancel.stopping
    assert cancel.withdrawn == ()
    [expired] = await gov.expire_pending()
    assert expired.reason == "pending_expired"


async def test_a_step_forward_past_its_expiry_expires_a_held_command(harness: Harness,
                                                                    gov: Governor) -> None:
    """NTP steps forward past `expires_at_ms`, which the issuer and approvers were shown:
    the command expires, as it said it would (a step may expire things, never prolong)."""
    pending_id = await _held(gov)
    harness.clock.step(HOUR)
    late = await gov.authorize(pending_id, OPS)
    assert (late.http_status, late.reason) == (404, "pending_expired")
    assert harness.dispatcher.calls == []


# -- e-stops ---------------------------------------------------------------------------------


async def test_a_step_back_does_not_delay_the_record_of_repeated_estops(
        harness: Harness, gov: Governor) -> None:
    """E-stops repeated while latched are recorded together every minute: a step back of an
    hour does not hold them unrecorded for an hour more."""
    await gov.start()
    await gov.decide(command("estop"), PLANNER)
    await gov.decide(command("estop"), PLANNER)
    harness.clock.step(-HOUR)
    harness.clock.advance(61)
    await gov.sweep()
    entry = harness.entries[-1]
    assert (entry["event"], entry["params"]["count"]) == ("ESTOP_REPEATED", 1)
    await gov.stop()


async def test_a_step_back_to_1970_leaves_the_estop_latched(harness: Harness,
                                                           gov: Governor) -> None:
    """The latch holds whatever the clock does; a stop still stops."""
    await gov.start()
    await gov.decide(command("estop"), PLANNER)
    harness.clock.step(-harness.clock.time())
    harness.clock.advance(3600)
    await gov.sweep()
    assert gov.latch.latched
    moved = await gov.decide(command("move", {"linear_x": 0.2, "duration_s": 1.0}), OPS)
    assert moved.outcome is not Outcome.EXECUTED
    stopped = await gov.decide(command("stop"), PLANNER)
    assert stopped.outcome is Outcome.EXECUTED
    await gov.stop()


# -- control sessions (§10.8): the dead-man -------------------------------------------------


async def test_a_step_back_does_not_keep_a_silent_session_driving(harness: Harness,
                                                                 gov: Governor) -> None:
    """The silence a session survives is measured on the monotonic clock: set back an hour
    (or to 1970), a silent driver is stopped when its 2 s are up, as ever."""
    await gov.start()
    await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    harness.clock.step(-harness.clock.time())
    harness.clock.advance(2.1)
    await gov.sweep()
    assert [e["event"] for e in harness.entries].count("NETWORK_LOSS_SAFE_STOP") == 1
    assert harness.dispatcher.calls[-1] == ("stop", {})
    await gov.stop()


async def test_a_step_forward_does_not_cut_a_session_short(harness: Harness,
                                                          gov: Governor) -> None:
    """Ten years forward (NTP after a boot with a stale date): a driver heard 1 s ago still
    drives."""
    await gov.start()
    await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    harness.clock.step(10 * 365 * 86400)
    harness.clock.advance(1.0)
    await gov.sweep()
    assert "NETWORK_LOSS_SAFE_STOP" not in [e["event"] for e in harness.entries]
    await gov.stop()


# -- the audit log --------------------------------------------------------------------------


async def test_a_log_written_across_steps_back_verifies_and_opens_again(
        harness: Harness, gov: Governor) -> None:
    """Entries are ordered by seq and hash chain, not by time: a log whose timestamps go back
    (a step to 1970 mid-run) verifies, and a start reads it back."""
    await gov.start()
    await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    harness.clock.step(-harness.clock.time())
    await gov.decide(command("stop"), PLANNER)
    await gov.stop()
    times = [e["timestamp_ms"] for e in harness.entries]
    assert times != sorted(times)
    await harness.restart()
    again = await harness.governor()
    await again.start()
    assert harness.entries[-1]["event"] == "BRIDGE_STARTED"
    await again.stop()


# -- rate limits ------------------------------------------------------------------------------


def test_a_step_forward_refills_no_rate_limit() -> None:
    """A principal out of requests stays out when the clock is set ten years forward."""
    clock = ManualClock(T)
    limiter = RateLimiter(clock)
    guest = principal("guest", Role.GUEST)  # 10 a minute
    assert all(limiter.allow(guest) for _ in range(10))
    assert not limiter.allow(guest)
    clock.step(10 * 365 * 86400)
    assert not limiter.allow(guest)
    clock.advance(6.1)  # a minute's tenth: one more
    assert limiter.allow(guest)
    assert not limiter.allow(guest)
