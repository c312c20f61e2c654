"""The §6 chain: format, signatures, durability hooks, group commit, tamper detection, recovery."""

from __future__ import annotations

import asyncio
import base64
import functools
import json
import os
import stat
import tempfile
import threading
from pathlib import Path

import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from hypothesis import given, settings
from hypothesis import strategies as st

from rcan_rtps.governance import audit as audit_mod
from rcan_rtps.governance.audit import (
    GENESIS,
    AuditEvent,
    AuditLog,
    AuditReceipt,
    AuditRecord,
    canonical,
    entry_id,
    load_or_create_key,
    load_public_key,
    verify,
    verify_bytes,
)
from rcan_rtps.governance.clock import ManualClock
from rcan_rtps.governance.errors import (
    AuditError,
    AuditIntegrityError,
    AuditKeyError,
    AuditWriteError,
)

RURI = "rcan://registry.local/clearpath/husky/a200-0001"


def record(i: int = 0, **kw: object) -> AuditRecord:
    fields: dict[str, object] = dict(
        event=AuditEvent.COMMAND_DISPATCHED, principal="ops", role="OWNER",
        message_id=f"m{i}", action_type="move", params={"linear_x": 0.1 * i, "note": "é✓"},
        applied={"linear_x": 0.1 * i}, outcome="executed", ros2_topic="/robot1/cmd_vel",
    )
    fields.update(kw)
    return AuditRecord(**fields)  # type: ignore[arg-type]


def lines_of(path: Path) -> list[dict[str, object]]:
    return [json.loads(line) for line in path.read_text().splitlines()]


async def test_entries_carry_the_profile_fields_and_link(audit_log: AuditLog) -> None:
    await audit_log.append(record(1, ai={"provider": "openai", "model": "gpt-4o",
                                         "confidence": 0.94, "thought_id": "t"}))
    await audit_log.append(record(2))
    first, second = lines_of(audit_log.path)
    assert set(first) == {
        "seq", "audit_id", "prev_hash", "timestamp", "timestamp_ms", "ruri", "principal",
        "role", "message_id", "event", "action_type", "params", "applied", "outcome",
        "deny_reason", "ai", "bridge", "ros2_topic", "sig", "canonical",
    }
    assert first["canonical"] == "rcan-canonical-json-v1"  # issue 24: the SDK's encoding
    assert "ai" not in second  # only when given
    assert first["seq"] == 1 and second["seq"] == 2
    assert first["prev_hash"] == GENESIS
    assert second["prev_hash"] == first["audit_id"]
    assert first["bridge"] == "ros2" and first["ruri"] == RURI
    assert first["timestamp"] == "2027-01-15T08:00:00.000Z"
    assert first["timestamp_ms"] == 1_800_000_000_000
    assert first["audit_id"] == entry_id(first)
    sig = base64.b64decode(str(first["sig"]))
    audit_log.public_key.verify(sig, str(first["audit_id"]).encode())


async def test_audit_id_is_sha256_of_sorted_compact_utf8(audit_log: AuditLog) -> None:
    await audit_log.append(record(3))
    raw = audit_log.path.read_bytes().rstrip(b"\n")
    entry = json.loads(raw)
    assert raw == json.dumps(entry, sort_keys=True, separators=(",", ":"),
                             ensure_ascii=False).encode()
    body = {k: v for k, v in entry.items() if k not in ("audit_id", "sig")}
    import hashlib

    want = hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":"),
                                     ensure_ascii=False).encode()).hexdigest()
    assert entry["audit_id"] == "sha256:" + want


def test_canonical_floats_are_stable() -> None:
    for value in (0.1, 1.0, -0.0, 1e300, 5e-324, 123456789.123456789, 2**53 + 1):
        once = canonical({"v": value})
        assert canonical(json.loads(once)) == once


async def test_key_is_private_and_reused(tmp_path: Path, clock: ManualClock) -> None:
    log = await AuditLog.open(tmp_path / "a.jsonl", tmp_path / "k.key", clock=clock)
    await log.append(record())
    pub = log.public_key
    await log.close()
    assert stat.S_IMODE(os.stat(tmp_path / "k.key").st_mode) == 0o600
    log = await AuditLog.open(tmp_path / "a.jsonl", tmp_path / "k.key", clock=clock)
    receipt = await log.append(record())
    await log.close()
    assert receipt.seq == 2
    assert log.public_key.public_bytes_raw() == pub.public_bytes_raw()
    assert verify(tmp_path / "a.jsonl", pub).count == 2


def test_a_created_key_is_the_pem_cryptography_writes(tmp_path: Path) -> None:
    # Written without cryptography's serialization module: the same bytes its PEM writer makes,
    # and what any PKCS#8 reader (here cryptography's own) loads as that key.
    from cryptography.hazmat.primitives import serialization

    key = load_or_create_key(tmp_path / "k.key")
    written = (tmp_path / "k.key").read_bytes()
    assert written == key.private_bytes(serialization.Encoding.PEM,
                                        serialization.PrivateFormat.PKCS8,
                                        serialization.NoEncryption())
    loaded = serialization.load_pem_private_key(written, password=None)
    assert isinstance(loaded, Ed25519PrivateKey)
    assert loaded.private_bytes_raw() == key.private_bytes_raw()


async def test_key_readable_by_others_is_refused(tmp_path: Path) -> None:
    (await AuditLog.open(tmp_path / "a.jsonl", tmp_path / "k.key"))
    os.chmod(tmp_path / "k.key", 0o644)
    with pytest.raises(AuditKeyError, match="open to others"):
        await AuditLog.open(tmp_path / "b.jsonl", tmp_path / "k.key")


async def test_second_writer_is_refused(audit_log: AuditLog, tmp_path: Path) -> None:
    with pytest.raises(AuditError, match="in use"):
        await AuditLog.open(audit_log.path, tmp_path / "audit.key")


async def test_wrong_key_fails_verification(audit_log: AuditLog, tmp_path: Path) -> None:
    await audit_log.append(record())
    other = await AuditLog.open(tmp_path / "x.jsonl", tmp_path / "other.key")
    with pytest.raises(AuditIntegrityError) as info:
        verify(audit_log.path, other.public_key)
    assert info.value.seq == 1 and "signature" in info.value.detail
    await other.close()


async def test_group_commit_batches_concurrent_appends(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    writes: list[int] = []
    real = audit_mod._write_durable

    def counting(fd: int, data: bytes) -> float:
        writes.append(data.count(b"\n"))
        return real(fd, data)

    monkeypatch.setattr(audit_mod, "_write_durable", counting)
    for group, path in ((True, "g.jsonl"), (False, "s.jsonl")):
        writes.clear()
        log = await AuditLog.open(tmp_path / path, tmp_path / "k.key", group_commit=group)
        await asyncio.gather(*(log.append(record(i)) for i in range(50)))
        await log.close()
        assert sum(writes) == 50
        if group:
            assert len(writes) < 50 and max(writes) > 1
        else:
            assert writes == [1] * 50
        assert verify(tmp_path / path, log.public_key).count == 50


async def test_append_returns_only_after_the_write(
    audit_log: AuditLog, monkeypatch: pytest.MonkeyPatch
) -> None:
    gate = asyncio.Event()
    writing = threading.Event()
    real = audit_mod._write_durable
    loop = asyncio.get_running_loop()

    def slow(fd: int, data: bytes) -> float:
        writing.set()
        asyncio.run_coroutine_threadsafe(gate.wait(), loop).result()
        return real(fd, data)

    monkeypatch.setattr(audit_mod, "_write_durable", slow)
    monkeypatch.setattr(audit_mod, "INLINE_FSYNC_S", 0.0)  # a slow disk: the writer thread
    task = asyncio.create_task(audit_log.append(record()))
    # Sentinel: the write has started (and waits for the gate), not just "some time passed".
    assert await asyncio.to_thread(writing.wait, 30)
    assert not task.done()
    assert audit_log.path.read_bytes() == b""
    gate.set()
    receipt = await task
    assert receipt.audit_id in audit_log.path.read_text()


async def test_a_failed_write_is_cut_back_and_the_log_goes_on(
    audit_log: AuditLog, monkeypatch: pytest.MonkeyPatch
) -> None:
    await audit_log.append(record(0))
    durable = audit_log.path.read_bytes()
    real = audit_mod._write_durable

    def half_then_full(fd: int, data: bytes) -> float:
        os.write(fd, data[: len(data) // 2])  # a torn write: part of the batch reached the file
        raise OSError(28, "No space left on device")

    for slow_disk in (False, True):  # inline / loop group commit, and the writer thread
        monkeypatch.setattr(audit_mod, "INLINE_FSYNC_S", 0.0 if slow_disk else 1.0)
        monkeypatch.setattr(audit_mod, "_write_durable", half_then_full)
        results = await asyncio.gather(*(audit_log.append(record(i)) for i in range(3)),
                                       return_exceptions=True)
        assert all(isinstance(r, AuditWriteError) for r in results)  # inline or queued alike
        assert audit_log.path.read_bytes() == durable  # cut back: no torn or refused entry
        assert audit_log.healthy and audit_log.head.last_seq == 1 + slow_disk
        monkeypatch.setattr(audit_mod, "_write_durable", real)
        receipt = await audit_log.append(record(9))  # space is back: the chain goes on
        durable = audit_log.path.read_bytes()
        assert verify(audit_log.path, audit_log.public_key).count == receipt.seq == 2 + slow_disk


async def test_a_write_that_cannot_be_cut_back_poisons_the_log(
    audit_log: AuditLog, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(fd: int, data: bytes) -> float:
        raise OSError(5, "Input/output error")

    def no_truncate(fd: int, length: int) -> None:
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(audit_mod, "_write_durable", broken)
    monkeypatch.setattr(audit_mod.os, "ftruncate", no_truncate)
    results = await asyncio.gather(*(audit_log.append(record(i)) for i in range(3)),
                                   return_exceptions=True)
    assert all(isinstance(r, AuditWriteError) for r in results)
    assert not audit_log.healthy  # the tail is unknown: nothing more may chain onto it
    with pytest.raises(AuditWriteError):
        await audit_log.append(record())


# -- tamper detection (property) ------------------------------------------------------------

N_ENTRIES = 8


@functools.lru_cache(maxsize=1)
def sample_chain() -> tuple[bytes, bytes]:
    """A signed chain of N_ENTRIES entries and its raw public key, built once."""

    async def build() -> tuple[bytes, bytes]:
        with tempfile.TemporaryDirectory() as tmp:
            log = await AuditLog.open(Path(tmp, "a.jsonl"), Path(tmp, "k.key"), ruri=RURI,
                                      clock=ManualClock())
            for i in range(N_ENTRIES):
                await log.append(record(i))
            await log.close()
            return Path(tmp, "a.jsonl").read_bytes(), log.public_key.public_bytes_raw()

    return asyncio.run(build())


def chain() -> tuple[bytes, Ed25519PublicKey, list[bytes]]:
    data, raw = sample_chain()
    return data, Ed25519PublicKey.from_public_bytes(raw), data.splitlines(keepends=True)


def seq_at(data: bytes, offset: int) -> int:
    """The seq of the line holding byte `offset` (a newline belongs to the line it ends)."""
    return data.count(b"\n", 0, offset) + 1


def test_untouched_sample_verifies() -> None:
    data, pub, _ = chain()
    assert verify_bytes(data, pub).count == N_ENTRIES


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_any_single_byte_change_is_detected_at_its_seq(draw: st.DataObject) -> None:
    data, pub, _ = chain()
    offset = draw.draw(st.integers(0, len(data) - 1))
    new = draw.draw(st.integers(0, 255).filter(lambda b: b != data[offset]))
    tampered = data[:offset] + bytes([new]) + data[offset + 1 :]
    with pytest.raises(AuditIntegrityError) as info:
        verify_bytes(tampered, pub)
    assert info.value.seq == seq_at(data, offset)


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_any_byte_deletion_is_detected_at_its_seq(draw: st.DataObject) -> None:
    data, pub, _ = chain()
    offset = draw.draw(st.integers(0, len(data) - 1))
    with pytest.raises(AuditIntegrityError) as info:
        verify_bytes(data[:offset] + data[offset + 1 :], pub)
    assert info.value.seq == seq_at(data, offset)


@settings(max_examples=50, deadline=None)
@given(st.integers(1, N_ENTRIES - 1))
def test_line_deletion_is_detected_at_the_missing_seq(seq: int) -> None:
    _data, pub, lines = chain()
    with pytest.raises(AuditIntegrityError) as info:
        verify_bytes(b"".join(lines[: seq - 1] + lines[seq:]), pub)
    assert info.value.seq == seq


@settings(max_examples=50, deadline=None)
@given(st.lists(st.integers(0, N_ENTRIES - 1), min_size=2, max_size=2, unique=True))
def test_reordering_is_detected_at_the_first_moved_seq(pair: list[int]) -> None:
    _data, pub, lines = chain()
    i, j = sorted(pair)
    lines[i], lines[j] = lines[j], lines[i]
    with pytest.raises(AuditIntegrityError) as info:
        verify_bytes(b"".join(lines), pub)
    assert info.value.seq == i + 1


@settings(max_examples=100, deadline=None)
@given(st.data())
def test_truncation_inside_a_line_is_detected_at_its_seq(draw: st.DataObject) -> None:
    data, pub, _ = chain()
    boundaries = {i + 1 for i, b in enumerate(data) if b == ord("\n")} | {0}
    cut = draw.draw(st.integers(1, len(data) - 1).filter(lambda c: c not in boundaries))
    with pytest.raises(AuditIntegrityError) as info:
        verify_bytes(data[:cut], pub)
    assert info.value.seq == seq_at(data, cut)


def test_rehashed_but_unsigned_entry_is_detected() -> None:
    _data, pub, lines = chain()
    forged = json.loads(lines[3])
    forged["params"] = {"linear_x": 9.0}
    forged["audit_id"] = entry_id(forged)  # recomputed, but not re-signed
    lines[3] = canonical(forged) + b"\n"
    with pytest.raises(AuditIntegrityError) as info:
        verify_bytes(b"".join(lines), pub)
    assert info.value.seq == 4  # entry 4's own signature, or entry 5's link, breaks


# -- recovery on open -----------------------------------------------------------------------


@pytest.mark.parametrize("cut_back", [1, 10, 60])
async def test_torn_last_line_is_cut_and_audited(
    tmp_path: Path, clock: ManualClock, cut_back: int
) -> None:
    path = tmp_path / "a.jsonl"
    log = await AuditLog.open(path, tmp_path / "k.key", clock=clock)
    for i in range(3):
        await log.append(record(i))
    await log.close()
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - cut_back])
    with pytest.raises(AuditIntegrityError) as info:
        verify(path, log.public_key)
    assert info.value.seq == 3
    log = await AuditLog.open(path, tmp_path / "k.key", clock=clock)
    await log.close()
    entries = lines_of(path)
    assert [e["seq"] for e in entries] == [1, 2, 3]
    assert entries[2]["event"] == "AUDIT_TAIL_RECOVERED"
    assert entries[2]["params"]["cut_bytes"] == len(data.splitlines()[2]) + 1 - cut_back  # type: ignore[index]
    assert verify(path, log.public_key).count == 3


async def test_break_before_the_tail_refuses_to_open(tmp_path: Path, clock: ManualClock) -> None:
    path = tmp_path / "a.jsonl"
    log = await AuditLog.open(path, tmp_path / "k.key", clock=clock)
    for i in range(4):
        await log.append(record(i))
    await log.close()
    lines = path.read_bytes().splitlines(keepends=True)
    path.write_bytes(b"".join(lines[:1] + lines[2:]))
    with pytest.raises(AuditIntegrityError, match="refusing to start") as info:
        await AuditLog.open(path, tmp_path / "k.key", clock=clock)
    assert info.value.seq == 2


async def test_public_key_export_round_trip(audit_log: AuditLog, tmp_path: Path) -> None:
    from rcan_rtps.governance.audit import load_private_key, public_key_pem

    pem = public_key_pem(load_private_key(tmp_path / "audit.key"))
    (tmp_path / "pub.pem").write_bytes(pem)
    assert load_public_key(tmp_path / "pub.pem").public_bytes_raw() == (
        audit_log.public_key.public_bytes_raw()
    )


async def test_an_idle_fast_log_writes_inline_and_a_burst_shares_fsyncs(
    audit_log: AuditLog, monkeypatch: pytest.MonkeyPatch
) -> None:
    threads: list[bool] = []
    real = audit_mod._write_durable
    loop_thread = threading.get_ident()

    def where(fd: int, data: bytes) -> float:
        threads.append(threading.get_ident() == loop_thread)
        return real(fd, data)

    monkeypatch.setattr(audit_mod, "_write_durable", where)
    # The disk counts as fast whatever this machine's load makes an fsync take right now.
    monkeypatch.setattr(audit_mod, "INLINE_FSYNC_S", 60.0)
    await asyncio.sleep(0.01)
    await audit_log.append(record())  # alone: written on the loop, no thread hand-off
    assert threads == [True]
    threads.clear()
    await asyncio.gather(*(audit_log.append(record(i)) for i in range(30)))
    # A burst on a fast disk: group commits at the end of loop turns, no thread hand-off.
    assert all(threads) and len(threads) < 30
    monkeypatch.setattr(audit_mod, "INLINE_FSYNC_S", 0.0)  # a slow disk: never on the loop
    threads.clear()
    await asyncio.sleep(0.01)
    await audit_log.append(record())
    assert threads == [False]
    threads.clear()
    await asyncio.gather(*(audit_log.append(record(i)) for i in range(30)))
    assert not any(threads) and len(threads) < 30  # the writer thread's group commits


async def _loop_commits(log: AuditLog, monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Entries per write+fsync from here on (after one first entry); the disk reads as fast
    and never idle, so every append goes to a group commit on the loop (neither inline nor
    the writer thread)."""
    writes: list[int] = []
    real = audit_mod._write_durable

    def fast(fd: int, data: bytes) -> float:
        real(fd, data)
        writes.append(data.count(b"\n"))
        return 0.0

    monkeypatch.setattr(audit_mod, "_write_durable", fast)
    monkeypatch.setattr(audit_mod, "INLINE_GAP_S", 1e9)
    await log.append(record(0))
    writes.clear()
    return writes


async def _a_turn_later(log: AuditLog, i: int, *, urgent: bool = False) -> AuditReceipt:
    await asyncio.sleep(0)  # one loop turn
    return await log.append(record(i), urgent=urgent)


async def test_a_loop_group_commit_holds_one_turn_for_more_entries(
    audit_log: AuditLog, monkeypatch: pytest.MonkeyPatch
) -> None:
    writes = await _loop_commits(audit_log, monkeypatch)
    # Sealed a turn apart: one write+fsync for both (committing at the end of the first
    # entry's turn would have taken two).
    await asyncio.gather(audit_log.append(record(1)), _a_turn_later(audit_log, 2))
    assert writes == [2]
    # A turn is held once, not again and again: a third turn's entry gets a commit of its own.
    writes.clear()

    async def two_turns_later() -> AuditReceipt:
        await asyncio.sleep(0)
        return await _a_turn_later(audit_log, 5)

    await asyncio.gather(audit_log.append(record(3)), _a_turn_later(audit_log, 4),
                         two_turns_later())
    assert writes == [2, 1]
    assert verify(audit_log.path, audit_log.public_key).count == 6


async def test_a_stop_in_a_loop_group_commit_is_not_held(
    audit_log: AuditLog, monkeypatch: pytest.MonkeyPatch
) -> None:
    writes = await _loop_commits(audit_log, monkeypatch)
    # The urgent entry's batch is written at the first chance; the next turn's entry waits
    # for a commit of its own instead of holding the stop back.
    await asyncio.gather(audit_log.append(record(1)), audit_log.append(record(2), urgent=True),
                         _a_turn_later(audit_log, 3))
    assert writes == [2, 1]
    # Urgency belongs to the batch it was in: the next batch holds its turn again.
    writes.clear()
    await asyncio.gather(audit_log.append(record(4)), _a_turn_later(audit_log, 5))
    assert writes == [2]
    # An urgent entry sealed in the held turn joins its batch, written as already scheduled.
    writes.clear()
    await asyncio.gather(audit_log.append(record(6)), _a_turn_later(audit_log, 7, urgent=True))
    assert writes == [2]
    assert verify(audit_log.path, audit_log.public_key).count == 8


async def test_a_sealed_entry_is_chained_in_the_call_and_written_after_the_next_step(
    audit_log: AuditLog, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A stop's entry: its place in the chain is fixed by `seal` itself, nothing is written
    in the call (a task made just before it runs first: the stop's publish), and an append
    right after it, on an idle fast log that writes inline, does not jump ahead of it."""
    monkeypatch.setattr(audit_mod, "INLINE_FSYNC_S", 60.0)  # fast: an idle append is inline
    await audit_log.append(record(0))
    await asyncio.sleep(0.01)  # idle
    size = audit_log.path.stat().st_size

    async def publish() -> int:  # the stop's signal, started before its entry is sealed
        return audit_log.path.stat().st_size

    published = asyncio.ensure_future(publish())
    durable = audit_log.seal(record(1, action_type="stop"), urgent=True)
    assert audit_log.head.last_seq == 2 and audit_log.path.stat().st_size == size
    later = await audit_log.append(record(2))
    stopped = await durable
    assert await published == size  # its first step ran before the entry was written
    assert (stopped.seq, later.seq) == (2, 3)
    assert [e["message_id"] for e in lines_of(audit_log.path)] == ["m0", "m1", "m2"]
    assert verify(audit_log.path, audit_log.public_key).count == 3


async def test_an_unwritable_log_refuses_to_seal_at_once(
    audit_log: AuditLog, monkeypatch: pytest.MonkeyPatch
) -> None:
    await audit_log.close()
    with pytest.raises(AuditWriteError):
        audit_log.seal(record(1), urgent=True)


async def test_entries_are_written_while_a_checkpoint_hook_runs(
        tmp_path: Path, clock: ManualClock, monkeypatch: pytest.MonkeyPatch) -> None:
    """A checkpoint's hooks (the start point: a replay of up to 1000 entries) run beside the
    writer thread: entries appended meanwhile become durable without waiting for them
    (before: the hook held the writer thread, and on a slow disk — where every entry is
    written by that thread — every command's entry waited)."""
    monkeypatch.setattr(audit_mod, "INLINE_FSYNC_S", 0.0)  # a slow disk: the thread writes
    log = await AuditLog.open(tmp_path / "audit.jsonl", tmp_path / "audit.key", ruri=RURI,
                              clock=clock)
    entered, release = threading.Event(), threading.Event()
    seen: list[int] = []

    def slow_hook(cp: audit_mod.Checkpoint) -> None:
        seen.append(cp.seq)
        entered.set()
        release.wait(60)

    log.on_checkpoint(slow_hook)
    try:
        await log.append(record(1))
        checkpointing = asyncio.create_task(log.checkpoint())
        assert await asyncio.to_thread(entered.wait, 60)
        receipt = await asyncio.wait_for(log.append(record(2)), 30)  # (hangs before)
        assert receipt.seq == 2 and not checkpointing.done()
    finally:
        release.set()
    await checkpointing
    await log.append(record(3))
    await log.close()  # its closing checkpoint runs the hook too, and waits for it
    assert seen == [1, 3]
    assert [e["seq"] for e in lines_of(tmp_path / "audit.jsonl")] == [1, 2, 3]
