"""Red team 20: audit files that nest JSON thousands of levels deep.

msgspec gives up on deep nesting with RecursionError, not DecodeError, and the readers of the
audit log's files expected only the latter: `rcan-rtps audit verify` died with a traceback on
a log line, tree head or checkpoint of `[[[[…]]]]` (a few kB), and a start refused to run with
the same traceback instead of naming the line (or, for the checkpoint, ignoring it as it
ignores any unusable checkpoint). Each test failed on main (6969ad9).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import stat
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from rcan_rtps.governance import outcomes
from rcan_rtps.governance.audit import (
    AuditEvent,
    AuditLog,
    AuditRecord,
    carries_its_id,
    checkpoint_path,
)
from rcan_rtps.governance.clock import ManualClock
from rcan_rtps.governance.errors import AuditIntegrityError
from rcan_rtps.governance.replay import ReplayWindow
from rcan_rtps.governance.resume import point_path, resume
from rcan_rtps.governance.treehead import public_key_path, tree_head_path
from tests.governance.test_audit_cli import run, three_entries

DEEP = b"[" * 5000 + b"]" * 5000


@pytest.fixture
async def log_file(tmp_path: Path) -> Path:
    return await three_entries(tmp_path)


def _deep_entry(line: bytes, depth: int) -> bytes:
    """`line` (an entry) with its params `depth` arrays deep: every key an entry needs, so the
    check reaches the entry's canonical form (recursive: ~900 levels is too deep for it)."""
    entry = json.loads(line)
    entry["params"] = "X"
    text = json.dumps(entry, sort_keys=True, separators=(",", ":")).encode()
    return text.replace(b'"X"', b"[" * depth + b"]" * depth)


def _insert(path: Path, at: int, line: bytes) -> None:
    lines = path.read_bytes().splitlines(keepends=True)
    path.write_bytes(b"".join([*lines[:at], line + b"\n", *lines[at:]]))


@pytest.mark.parametrize("line", [b'{"x":' + DEEP + b"}", b"__entry_900__"])
@pytest.mark.parametrize("at", [1, 3])  # amid the log, and its last line
def test_verify_names_a_deep_line_without_a_traceback(
        log_file: Path, line: bytes, at: int, capsys: pytest.CaptureFixture[str]) -> None:
    if line == b"__entry_900__":
        line = _deep_entry(log_file.read_bytes().splitlines()[1], 900)
    _insert(log_file, at, line)
    assert run("audit", "verify", str(log_file)) == 1
    err = capsys.readouterr().err
    assert f"seq {at + 1}" in err and "Traceback" not in err, err


def test_verify_names_damage_followed_by_a_deep_entry(
        log_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Damage amid the log, then an entry too deep to hash: whether anything well-formed
    follows the damage is asked of that entry too (`carries_its_id`), which must say no,
    not raise."""
    deep = _deep_entry(log_file.read_bytes().splitlines()[1], 900)
    _insert(log_file, 1, b"not an entry")
    _insert(log_file, 2, deep)  # the first line after the damage
    assert run("audit", "verify", str(log_file)) == 1
    err = capsys.readouterr().err
    assert "seq 2" in err and "Traceback" not in err, err


def test_an_entry_too_deep_to_hash_carries_no_id() -> None:
    entry = json.loads(_deep_entry(json.dumps({"seq": 1}).encode(), 900))
    assert not _deeper_by(200, lambda: carries_its_id(entry, "sha256:00"))


def _deeper_by(frames: int, call: Callable[[], bool]) -> bool:
    """`call()` with `frames` more on the stack (the bridge calls from deeper than a test)."""
    return call() if frames == 0 else _deeper_by(frames - 1, call)


def test_verify_names_a_deep_tree_head_and_checkpoint(
        log_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    tree_head_path(log_file).write_bytes(b'{"x":' + DEEP + b"}\n")
    checkpoint_path(log_file).write_bytes(b'{"x":' + DEEP + b"}")
    assert run("audit", "verify", str(log_file)) == 1
    err = capsys.readouterr().err
    assert "tree heads line 1: not a tree head" in err, err
    assert "start-up checkpoint" in err and "malformed" in err, err


async def test_a_start_refuses_a_deep_line_by_name(log_file: Path, tmp_path: Path) -> None:
    checkpoint_path(log_file).unlink()  # verify from the start
    _insert(log_file, 1, b'{"x":' + DEEP + b"}")
    with pytest.raises(AuditIntegrityError, match="seq 2: not JSON"):
        await AuditLog.open(log_file, tmp_path / "k.key")


async def test_a_start_ignores_a_deep_checkpoint(log_file: Path, tmp_path: Path) -> None:
    """A checkpoint no one can read is no reason not to start: the whole log is verified
    instead (as for any unusable checkpoint)."""
    checkpoint_path(log_file).write_bytes(b'{"x":' + DEEP + b"}")
    log = await AuditLog.open(log_file, tmp_path / "k.key")
    try:
        assert log.head.last_seq == 3
    finally:
        await log.close()


async def test_the_replay_ignores_a_deep_start_point(log_file: Path, tmp_path: Path) -> None:
    """The start point (`<log>.resume`) likewise: replayed from the boundary instead."""
    point_path(log_file).write_bytes(b'{"x":' + DEEP + b"}")
    log = await AuditLog.open(log_file, tmp_path / "k.key")
    try:
        found = resume(log_file, pubkey=log.public_key)
    finally:
        await log.close()
    assert not found.latched


def test_the_replay_fails_closed_on_a_deep_line(log_file: Path) -> None:
    """A line the replay cannot read (the log changed since it was verified) latches the
    e-stop, as any unreadable tail does: never a traceback at start."""
    _insert(log_file, 3, b'{"x":' + DEEP + b"}")
    found = resume(log_file)
    assert found.latched and "unreadable" in str(found.latched_by)


@pytest.mark.parametrize("kind", ["prove", "consistency"])
@pytest.mark.parametrize("content", [b"[" * 100_000 + b"]" * 100_000,
                                     b'{"seq":' + b"9" * 5000 + b"}"])
def test_a_proof_file_python_cannot_read_is_named(
        log_file: Path, tmp_path: Path, kind: str, content: bytes,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Nested too deeply (RecursionError) or a number of more digits than Python converts
    (ValueError): a traceback, where any other file that is not JSON is named."""
    proof = tmp_path / "proof.json"
    proof.write_bytes(content)
    assert run("audit", kind, "--verify", str(proof), "--pubkey", f"{log_file}.pub") == 1
    assert "is not JSON" in capsys.readouterr().err


def test_a_consistency_proof_with_a_root_that_is_not_hex_is_refused(
        log_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A tree head in the proof whose root_hash is not hex raised ValueError (a traceback
    through `audit consistency --verify`, with or without a key)."""
    assert run("audit", "consistency", str(log_file), "1") == 0
    doc = json.loads(capsys.readouterr().out)
    doc["new_tree_head"]["root_hash"] = "zz" * 32
    proof = tmp_path / "c.json"
    proof.write_text(json.dumps(doc))
    assert run("audit", "consistency", "--verify", str(proof)) == 1
    assert "not a consistency proof" in capsys.readouterr().err


# -- FIFOs beside the log --------------------------------------------------------------------


def _fifo_at(path: Path) -> None:
    path.unlink(missing_ok=True)
    os.mkfifo(path)


class _Drain:
    """Reads a FIFO empty until stopped, on a thread: what lets a writer blocked on it (the
    failure these tests look for) go on, so that a failing test ends instead of hanging."""

    def __init__(self, path: Path) -> None:
        self._fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.01):
            with contextlib.suppress(BlockingIOError):
                while os.read(self._fd, 1 << 16):
                    pass

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        os.close(self._fd)


def _feed(path: Path) -> None:
    """Give a reader blocked on the FIFO at `path` its end of file (if it still is one)."""
    if stat.S_ISFIFO(path.stat().st_mode):
        fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
        os.close(fd)


async def test_a_fifo_at_the_public_key_does_not_hold_a_start(
        log_file: Path, tmp_path: Path) -> None:
    """A start read `<log>.pub` to see whether it holds the key: a FIFO there (its name is no
    secret) held the start — and its e-stop — for a writer that never comes. It is replaced
    by the key, as a file that is not the key is."""
    pub = public_key_path(log_file)
    _fifo_at(pub)
    opening = asyncio.ensure_future(AuditLog.open(log_file, tmp_path / "k.key"))
    done, _ = await asyncio.wait([opening], timeout=10)
    if not done:
        _feed(pub)
    await (await opening).close()
    assert done, "the start was held by the FIFO"
    assert pub.is_file() and pub.read_bytes().startswith(b"-----BEGIN PUBLIC KEY-----")


async def test_a_fifo_at_the_tree_heads_does_not_stall_the_log(
        log_file: Path, tmp_path: Path) -> None:
    """Tree heads were appended to a FIFO at `<log>.sth` until its buffer filled (~300
    heads), then the writer blocked: every append after it (every governed command) hung.
    The log now writes no tree heads there (as when the file cannot be opened)."""
    heads = tree_head_path(log_file)
    _fifo_at(heads)
    log = await AuditLog.open(log_file, tmp_path / "k.key")
    stalled, drain = None, None
    try:
        for i in range(600):
            append = asyncio.ensure_future(log.append(
                AuditRecord(event=AuditEvent.COMMAND_DISPATCHED, params={"i": i})))
            done, _ = await asyncio.wait([append], timeout=10)
            if not done:
                stalled, drain = i, _Drain(heads)
                await append
                break
    finally:
        await log.close()
        if drain is not None:
            drain.stop()
    assert stalled is None, f"append {stalled} stalled"


@pytest.mark.parametrize("sidecar", [public_key_path, tree_head_path])
def test_verify_names_a_fifo_beside_the_log(
        log_file: Path, sidecar: Callable[[Path], Path],
        capsys: pytest.CaptureFixture[str]) -> None:
    """`audit verify` read a FIFO at `<log>.pub` or `<log>.sth` for ever."""
    _fifo_at(sidecar(log_file))
    with ThreadPoolExecutor(1) as pool:
        code = pool.submit(run, "audit", "verify", str(log_file))
        try:
            assert code.result(timeout=10) == 1
        finally:
            if not code.done():
                _feed(sidecar(log_file))
    assert "not a regular file" in capsys.readouterr().err


# -- the replay window read back from the log ------------------------------------------------


async def _logged(tmp_path: Path, at: float, ids: list[str]) -> Path:
    log = await AuditLog.open(tmp_path / "r.jsonl", tmp_path / "k.key", clock=ManualClock(at))
    for msg_id in ids:
        await log.append(AuditRecord(event=AuditEvent.COMMAND_DISPATCHED, principal="p",
                                     message_id=msg_id))
    await log.close()
    return tmp_path / "r.jsonl"


async def test_a_start_remembers_only_ids_that_could_still_be_fresh(tmp_path: Path) -> None:
    path = await _logged(tmp_path, 1_800_000_000.0, ["m-1", "m-2"])
    window = ReplayWindow(ManualClock(1_800_000_010.0))  # 10 s later: both could be
    assert window.remember_logged(path) == 2
    assert window.check("m-1", 1_800_000_009.0) == outcomes.REPLAY_DETECTED
    later = ReplayWindow(ManualClock(1_800_000_040.0))  # past window_s + ahead_s
    assert later.remember_logged(path) == 0
