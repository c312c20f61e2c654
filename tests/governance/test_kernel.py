"""The safety kernel's edges: message-id reuse, write-ahead audit, bounded memory, fail-closed
latch file, audit directories, and a start-up that does not grow with the log."""

from __future__ import annotations

import asyncio
import json
import os
import stat
from pathlib import Path

import pytest
from govhelpers import ADMIN, OPS, PLANNER, VIEWER, Harness, command

from rcan_rtps.governance.audit import (
    AuditEvent,
    AuditLog,
    AuditRecord,
    checkpoint_path,
    verify,
)
from rcan_rtps.governance.errors import AuditIntegrityError
from rcan_rtps.rcan import ErrorCode, Outcome, Reason

MID = "7d2c8f8e-0d64-4a43-9f5b-2d7b0f3f6a11"


# -- message ids ----------------------------------------------------------------------------


async def test_reusing_a_message_id_for_another_command_is_a_conflict(harness: Harness) -> None:
    gov = await harness.governor()
    first = await gov.decide(command("move", {"linear_x": 0.3}, message_id=MID), PLANNER)
    assert first.outcome is Outcome.EXECUTED
    other = await gov.decide(command("move", {"linear_x": 0.4}, message_id=MID), PLANNER)
    assert (other.http_status, other.error_code) == (409, ErrorCode.MESSAGE_ID_CONFLICT)
    nav = await gov.decide(command("navigate", {"x": 1, "y": 1, "yaw": 0}, message_id=MID),
                           PLANNER)
    assert nav.error_code is ErrorCode.MESSAGE_ID_CONFLICT
    entry = harness.entries[-1]
    assert (entry["event"], entry["deny_reason"], entry["message_id"]) == (
        "COMMAND_REJECTED", "MESSAGE_ID_CONFLICT", MID)
    assert [a for a, _ in harness.dispatcher.calls] == ["move"]


async def test_a_stop_reusing_a_moves_id_still_stops(harness: Harness) -> None:
    gov = await harness.governor()
    await gov.decide(command("move", {"linear_x": 0.3}, message_id=MID), PLANNER)
    for _ in range(3):  # and again: a stop is never answered from a cache
        d = await gov.decide(command("stop", message_id=MID), PLANNER)
        assert d.outcome is Outcome.EXECUTED and d.applied == {}
    e = await gov.decide(command("estop", message_id=MID), VIEWER)
    assert e.outcome is Outcome.EXECUTED
    assert [a for a, _ in harness.dispatcher.calls] == ["move", "stop", "stop", "stop", "estop"]


async def test_generated_ids_are_not_remembered(harness: Harness) -> None:
    gov = await harness.governor()
    for i in range(300):
        await gov.decide(command("move", {"linear_x": 0.001 * i}), ADMIN)
    assert len(gov._idem) == 0  # nothing grows with commands a client cannot retry
    await gov.decide(command("move", {"linear_x": 0.1}, message_id=MID), ADMIN)
    assert len(gov._idem) == 1


# -- write-ahead ------------------------------------------------------------------------------


def _spy_on_sends(harness: Harness) -> list[int]:
    """How many lines the audit file held at each send."""
    path = harness.tmp / "audit.jsonl"
    seen: list[int] = []

    async def dispatch(cmd, applied):  # type: ignore[no-untyped-def]
        seen.append(len(path.read_bytes().splitlines()))  # what is on disk at send time
        return await real(cmd, applied)

    real = harness.dispatcher.dispatch
    harness.dispatcher.dispatch = dispatch  # type: ignore[method-assign]
    return seen


async def test_nothing_is_sent_before_its_entry_is_durable(harness: Harness) -> None:
    gov = await harness.governor()
    path = harness.tmp / "audit.jsonl"
    seen = _spy_on_sends(harness)
    for action, params in [("move", {"linear_x": 0.2}), ("navigate", {"x": 1, "y": 1, "yaw": 0})]:
        before = len(path.read_bytes().splitlines())
        d = await gov.decide(command(action, params), OPS)
        assert d.outcome is Outcome.EXECUTED
        # Its own entry was already in the file.
        written = [json.loads(line) for line in path.read_bytes().splitlines()[before:seen[-1]]]
        assert [e["action_type"] for e in written if e["event"] != "STREAM_ENDED"] == [action]


@pytest.mark.parametrize("action", ["stop", "estop"])
async def test_a_stop_is_sent_first_and_durable_before_its_reply(harness: Harness,
                                                                  action: str) -> None:
    """The amended write-ahead rule: a stop's signals never wait for the disk, its entry
    (which says so) is durable before the reply."""
    gov = await harness.governor()
    path = harness.tmp / "audit.jsonl"
    seen = _spy_on_sends(harness)
    before = len(path.read_bytes().splitlines())
    d = await gov.decide(command(action), OPS)
    assert d.outcome is Outcome.EXECUTED
    assert seen == [before]  # nothing of it was on disk when it went out
    written = [json.loads(line) for line in path.read_bytes().splitlines()[before:]]
    [entry] = [e for e in written if e.get("action_type") == action]
    assert entry["sent_first"] is True and entry["audit_id"] == d.audit_id


@pytest.mark.logs_traceback  # (a fault injected on purpose)
async def test_audit_failure_sends_no_motion_but_the_estop_still_goes(harness: Harness) -> None:
    gov = await harness.governor()
    os.close(gov.audit._fd)  # every further write fails
    os.open(os.devnull, os.O_RDONLY)  # keep the fd number taken, read-only: writes fail
    d = await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    assert (d.http_status, d.outcome, d.reason) == (503, Outcome.FAILED,
                                                    Reason.AUDIT_UNAVAILABLE.value)
    assert harness.dispatcher.calls == []
    d = await gov.decide(command("move", {"linear_x": 0.2}), PLANNER)
    assert d.reason == Reason.AUDIT_UNAVAILABLE.value and harness.dispatcher.calls == []
    e = await gov.decide(command("estop"), VIEWER)
    assert [a for a, _ in harness.dispatcher.calls] == ["estop"]  # an e-stop always goes out
    assert e.reason == Reason.AUDIT_UNAVAILABLE.value and gov.latch.latched
    assert json.loads((harness.tmp / "estop.state").read_bytes())["latched"] is True
    gov.audit._fd = -1


async def test_a_broken_log_refuses_every_entry_yet_every_stop_still_goes(
        harness: Harness) -> None:
    """A log that refuses to seal at all (broken until a restart): a stop, a session-loss
    stop and an e-stop still reach the robot, each answered audit_unavailable."""
    gov = await harness.governor()
    gov.audit._broken = OSError("the tail could not be cut back")
    stopped = await gov.decide(command("stop"), OPS)
    lost = await gov.safe_stop(PLANNER)
    estopped = await gov.decide(command("estop"), VIEWER)
    assert [a for a, _ in harness.dispatcher.calls] == ["stop", "stop", "estop"]
    assert [d.reason for d in (stopped, lost, estopped)] == [Reason.AUDIT_UNAVAILABLE.value] * 3
    assert gov.latch.latched
    gov.audit._broken = None


# -- latch file ---------------------------------------------------------------------------


async def test_deleted_latch_file_starts_latched_and_says_why(harness: Harness) -> None:
    gov = await harness.governor()
    await gov.start()
    assert not gov.latch.latched
    assert (harness.tmp / "estop.state").exists()  # the first start records its state
    await gov.stop()
    await harness.restart()
    (harness.tmp / "estop.state").unlink()
    gov = await harness.governor()
    await gov.start()
    assert gov.latch.latched  # at once; the robot is told in the background
    await gov.latch.settled()
    started = harness.entries[-1]
    assert started["event"] == "BRIDGE_STARTED" and "missing" in started["params"]["estop_reason"]
    assert [a for a, _ in harness.dispatcher.calls] == ["estop"]  # the robot is told again
    d = await gov.decide(command("move", {"linear_x": 0.1}), PLANNER)
    assert d.reason == Reason.ESTOP_ACTIVE.value
    assert (await gov.decide(command("clear_estop"), OPS)).outcome is Outcome.EXECUTED
    assert (await gov.decide(command("move", {"linear_x": 0.1}), PLANNER)).outcome \
        is Outcome.EXECUTED
    await gov.stop()


@pytest.mark.logs_traceback  # (a fault injected on purpose)
async def test_a_clear_that_cannot_be_persisted_is_audited_as_failed(
        harness: Harness, monkeypatch: pytest.MonkeyPatch) -> None:
    gov = await harness.governor()
    await gov.decide(command("estop"), VIEWER)

    def disk_full(*_: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("rcan_rtps.governance.estop.atomic_write", disk_full)
    d = await gov.decide(command("clear_estop"), OPS)
    assert (d.http_status, d.reason) == (503, Reason.ESTOP_STATE_UNWRITABLE.value)
    assert gov.latch.latched
    assert harness.entries[-1]["event"] == "COMMAND_FAILED"


# -- audit directories and start-up --------------------------------------------------------


async def test_missing_audit_directories_are_created_private(tmp_path: Path) -> None:
    log = await AuditLog.open(tmp_path / "a" / "b" / "audit.jsonl", tmp_path / "k" / "key")
    await log.append(AuditRecord(event=AuditEvent.BRIDGE_STARTED))
    await log.close()
    for d in (tmp_path / "a", tmp_path / "a" / "b", tmp_path / "k"):
        assert stat.S_IMODE(d.stat().st_mode) == 0o700
    assert verify(tmp_path / "a" / "b" / "audit.jsonl").count == 1


async def _fill(path: Path, key: Path, n: int) -> None:
    log = await AuditLog.open(path, key)
    for i in range(n):
        await log.append(AuditRecord(event=AuditEvent.BRIDGE_STARTED, params={"i": i}))
    await log.close()


async def test_start_verifies_only_after_the_checkpoint(tmp_path: Path) -> None:
    path, key = tmp_path / "audit.jsonl", tmp_path / "audit.key"
    await _fill(path, key, 50)
    assert checkpoint_path(path).exists()
    # Damage an entry the checkpoint covers: start-up trusts it, the full check does not.
    lines = path.read_bytes().splitlines(keepends=True)
    lines[10] = lines[10].replace(b'"i":10', b'"i":99')
    path.write_bytes(b"".join(lines))
    log = await AuditLog.open(path, key)
    assert log.head.last_seq == 50
    await log.close()
    with pytest.raises(AuditIntegrityError) as info:
        verify(path)
    assert info.value.seq == 11


async def test_a_checkpoint_that_does_not_match_means_a_full_check(tmp_path: Path) -> None:
    path, key = tmp_path / "audit.jsonl", tmp_path / "audit.key"
    await _fill(path, key, 20)
    cp = json.loads(checkpoint_path(path).read_bytes())
    # Forged (not signed by our key) or stale checkpoints are ignored.
    checkpoint_path(path).write_bytes(json.dumps({**cp, "seq": 5}).encode())
    lines = path.read_bytes().splitlines(keepends=True)
    lines[3] = lines[3].replace(b'"i":3', b'"i":4')
    path.write_bytes(b"".join(lines))
    with pytest.raises(AuditIntegrityError) as info:
        await AuditLog.open(path, key)
    assert info.value.seq == 4


async def test_a_checkpoint_that_is_no_regular_file_means_a_full_check(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A FIFO in the checkpoint's place: the open does not wait on it for a writer that never
    comes (before: `read_bytes` blocked the start, and the e-stop with it, for good); it
    verifies the whole log, and says why."""
    import threading

    path, key = tmp_path / "audit.jsonl", tmp_path / "audit.key"
    await _fill(path, key, 20)
    checkpoint_path(path).unlink()
    os.mkfifo(checkpoint_path(path))
    heads: list[int] = []

    def open_log() -> None:
        async def opened() -> None:
            log = await AuditLog.open(path, key)
            heads.append(log.head.last_seq)
            await log.close()
        asyncio.run(opened())

    opening = threading.Thread(target=open_log, daemon=True)
    opening.start()
    opening.join(30)
    blocked = opening.is_alive()  # on the FIFO's open, for a writer
    if blocked:  # (let the blocked open go, so the thread ends)
        os.close(os.open(checkpoint_path(path), os.O_WRONLY | os.O_NONBLOCK))
        opening.join(30)
    assert not blocked
    assert heads == [20]
    assert "unusable" in caplog.text


async def test_entries_after_the_checkpoint_are_verified(tmp_path: Path) -> None:
    path, key = tmp_path / "audit.jsonl", tmp_path / "audit.key"
    await _fill(path, key, 20)
    saved = checkpoint_path(path).read_bytes()
    await _fill(path, key, 5)  # appends 5 more (and moves the checkpoint)
    checkpoint_path(path).write_bytes(saved)  # as if the process died before checkpointing
    lines = path.read_bytes().splitlines(keepends=True)
    lines[22] = lines[22].replace(b'"i":2', b'"i":3')
    path.write_bytes(b"".join(lines))
    with pytest.raises(AuditIntegrityError) as info:
        await AuditLog.open(path, key)
    assert info.value.seq == 23


@pytest.mark.slow
async def test_start_up_work_does_not_grow_with_the_log(tmp_path: Path) -> None:
    """Counted, not timed: the bytes start-up verifies are the tail, not the log."""
    path, key = tmp_path / "audit.jsonl", tmp_path / "audit.key"
    await _fill(path, key, 3000)
    size = path.stat().st_size
    import rcan_rtps.governance.audit as audit_mod

    scanned: list[int] = []
    real_scan = audit_mod._scan

    def counting_scan(lines, pubkey, **kw):  # type: ignore[no-untyped-def]
        read = list(lines)
        scanned.append(sum(len(line) + 1 for _, line in read))
        return real_scan(iter(read), pubkey, **kw)

    audit_mod._scan = counting_scan  # type: ignore[assignment]
    try:
        log = await AuditLog.open(path, key)
        await log.close()
    finally:
        audit_mod._scan = real_scan  # type: ignore[assignment]
    assert scanned == [0] and size > 0


async def test_a_command_still_in_flight_is_not_session_loss(harness: Harness) -> None:
    """Waiting for a subscriber longer than the session timeout is not silence."""
    gov = await harness.governor()
    entered, release = asyncio.Event(), asyncio.Event()

    async def slow_ready(cmd):  # type: ignore[no-untyped-def]
        entered.set()
        await release.wait()
        return None

    harness.dispatcher.ready = slow_ready  # type: ignore[method-assign]
    moving = asyncio.ensure_future(gov.decide(command("move", {"linear_x": 0.2}), PLANNER))
    await entered.wait()
    harness.clock.advance(60)  # far past session_timeout_s
    await gov.sweep()
    assert [e["event"] for e in harness.entries] == []  # no NETWORK_LOSS_SAFE_STOP
    release.set()
    assert (await moving).outcome is Outcome.EXECUTED
    await gov.sweep()
    assert "NETWORK_LOSS_SAFE_STOP" not in [e["event"] for e in harness.entries]
    harness.clock.advance(60)
    await gov.sweep()  # silence after the command: now it is session loss
    events = [e["event"] for e in harness.entries if e["event"] != "STREAM_ENDED"]
    assert events[-1] == "NETWORK_LOSS_SAFE_STOP"


async def test_the_estop_signal_goes_out_as_the_latch_engages(harness: Harness) -> None:
    """Issue 23: the e-stop Bool waited for the latch-file and audit fsyncs. It is published
    from the latch's listener now: before the e-stop's first await, before any dispatch."""
    gov = await harness.governor()
    pending = asyncio.ensure_future(gov.decide(command("estop"), VIEWER))
    await asyncio.sleep(0)  # the decision's first step: the latch engages, nothing awaited
    assert gov.latch.latched and harness.dispatcher.signals == [0]
    assert (await pending).outcome is Outcome.EXECUTED
    await gov.decide(command("estop"), VIEWER)  # already latched: no flip, no second signal
    assert harness.dispatcher.signals == [0]
