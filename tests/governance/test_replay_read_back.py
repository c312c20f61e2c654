"""What a start reads back into the replay window (§8.3): a running bridge's bound, and never
a replay let through for it.

A start kept every id the log named in the window (35 s), up to 200 000 lines: a dense log
(a flood's refusals are logged with their ids) made that 65 MB at start, although a run
holds at most `max_entries` of a sender's ids. It now keeps the newest of them, and refuses
as stale what the sender sent while the ids it did not keep could have been fresh.
"""

from __future__ import annotations

import asyncio
import tracemalloc
from pathlib import Path

from rcan_rtps.governance import outcomes
from rcan_rtps.governance.audit import AuditEvent, AuditLog, AuditRecord
from rcan_rtps.governance.clock import ManualClock
from rcan_rtps.governance.replay import FORGOTTEN_AT_START, ReplayWindow

T = 1_800_000_000.0


def msg_id(n: int) -> str:
    return f"{n:08x}-0000-4000-8000-000000000000"  # (a UUID: the log keeps it as it is)


async def _flooded(path: Path, entries: int, *, step_s: float, sender: str = "guest",
                   batch_of: int = 1) -> None:
    """`entries` refusals of `sender`'s messages (their ids logged), `step_s` apart from T
    (logged `batch_of` at a time: those of a batch at its first's time)."""
    clock = ManualClock(T)
    log = await AuditLog.open(path, path.with_name("k.key"), clock=clock)
    for start in range(0, entries, batch_of):
        batch = range(start, min(entries, start + batch_of))
        await asyncio.gather(*(log.append(AuditRecord(
            event=AuditEvent.COMMAND_REJECTED, principal=sender, message_id=msg_id(n),
            deny_reason="RATE_LIMITED:replay_window_full")) for n in batch))
        clock.advance(step_s * len(batch))
    await log.close()


def test_a_dense_window_is_read_back_within_the_bound(tmp_path: Path) -> None:
    path = tmp_path / "audit.jsonl"
    asyncio.run(_flooded(path, 20_000, step_s=0.001, batch_of=500))  # 20 s of a flood
    window = ReplayWindow(ManualClock(T + 25), max_entries=1000)
    tracemalloc.start()
    try:
        kept = window.remember_logged(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    size = path.stat().st_size
    assert peak < size / 4, (peak, size)
    assert kept == len(window) == 1000


async def test_a_restart_after_a_dense_window_refuses_a_replay_of_a_forgotten_id(
        tmp_path: Path) -> None:
    path = tmp_path / "audit.jsonl"
    await _flooded(path, 10, step_s=0.5, sender="planner")  # logged T, T+0.5 … T+4.5
    clock = ManualClock(T + 12)
    window = ReplayWindow(clock, max_entries=3)
    assert window.remember_logged(path) == 3  # the newest: 7, 8, 9
    assert window.check(msg_id(9), T + 4.5, sender="planner") == outcomes.REPLAY_DETECTED
    # m0 … m6 are not kept: m6 was logged at T + 3, so sent by T + 8 at the latest.
    for n, sent in ((0, T), (6, T + 3), (6, T + 8)):
        refused = window.check(msg_id(n), sent, sender="planner")
        assert refused is not None, (n, sent)
        assert (refused.http_status, refused.error_code.value, refused.reason) == (
            408, "MESSAGE_STALE", FORGOTTEN_AT_START)
        assert refused.deny_reason == f"MESSAGE_STALE:{FORGOTTEN_AT_START}"
    # What it sends after is new: refused only for its full window, as a run refuses it;
    # other principals as ever.
    full = window.check(msg_id(100), T + 8.01, sender="planner")
    assert full is not None and full.reason == "replay_window_full"
    assert window.check(msg_id(101), T + 1, sender="ops") is None
    # Once the window has passed all that could bear a forgotten id, nothing of it is kept.
    clock.advance(30)
    assert window.check(msg_id(102), clock.time(), sender="planner") is None
    assert window.check(msg_id(0), T + 8, sender="planner") is not None  # stale as ever
    assert not window._forgotten_until


async def test_a_start_under_the_bound_forgets_nothing(tmp_path: Path) -> None:
    """Up to the bound every id is kept, and nothing else is refused."""
    path = tmp_path / "audit.jsonl"
    await _flooded(path, 10, step_s=0.5, sender="planner")
    window = ReplayWindow(ManualClock(T + 12), max_entries=11)
    assert window.remember_logged(path) == 10
    assert window.check(msg_id(0), T, sender="planner") == outcomes.REPLAY_DETECTED
    assert window.check(msg_id(100), T, sender="planner") is None


async def test_a_forgotten_id_logged_before_a_step_back_is_refused_once_the_kept_go_stale(
        tmp_path: Path) -> None:
    """The ids kept are the log's last, not always its latest in time: the last run's clock
    went back 10 s after m0 … m6. Kept m7 … m9 go stale at T + 36; m0, sent at T + 10 and
    logged then, is fresh until T + 40 — a replay the full window no longer refuses."""
    clock = ManualClock(T + 10)
    log = await AuditLog.open(tmp_path / "audit.jsonl", tmp_path / "k.key", clock=clock)
    for n in range(10):
        if n == 7:
            clock.step(-10)
        await log.append(AuditRecord(event=AuditEvent.COMMAND_DISPATCHED, principal="planner",
                                     message_id=msg_id(n)))
    await log.close()
    now = ManualClock(T + 12)
    window = ReplayWindow(now, max_entries=3)
    assert window.remember_logged(tmp_path / "audit.jsonl") == 3
    now.advance(25)  # T + 37
    refused = window.check(msg_id(0), T + 10, sender="planner")
    assert refused is not None and refused.reason == FORGOTTEN_AT_START, refused
    assert window.check(msg_id(100), now.time(), sender="planner") is None  # new: as ever
