"""`config check` reads an existing audit log back as a start would, and says what the start
would refuse — read only, so beside a running bridge too (it holds the log's lock)."""

from __future__ import annotations

import asyncio
import os
import resource
import subprocess
import sys
from pathlib import Path

import pytest

from rcan_rtps.cli.main import main
from rcan_rtps.governance import (
    AuditEvent,
    AuditIntegrityError,
    AuditKeyError,
    AuditLog,
    AuditRecord,
)
from rcan_rtps.governance.audit import READ_BACK_LIMIT, load_or_create_key

CONFIG = """\
robot: {ruri: rcan://registry.local/acme/bot/v1/abcdefgh01}
bridge:
  api: {auth_token_env: RT_OPS}
  safety: {max_linear_vel: 1.0, max_angular_vel: 1.0}
  audit: {path: "%(dir)s/audit.jsonl", key_path: "%(dir)s/audit.key"}
"""


@pytest.fixture
def config(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("RT_OPS", "x" * 32)
    path = tmp_path / "robot.rcan.yaml"
    path.write_text(CONFIG % {"dir": tmp_path})
    return path


async def _write_log(where: Path, entries: int = 5) -> None:
    log = await AuditLog.open(where / "audit.jsonl", where / "audit.key")
    for i in range(entries):
        await log.append(AuditRecord(event=AuditEvent.COMMAND_REJECTED, principal="ops",
                                     params={"n": i}))
    await log.close()


def _check(config: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = main(["config", "check", str(config)])
    out = capsys.readouterr()
    return code, out.out + out.err


async def _start_refusal(where: Path) -> str:
    with pytest.raises((AuditIntegrityError, AuditKeyError)) as info:
        await AuditLog.open(where / "audit.jsonl", where / "audit.key")
    return str(info.value)


async def test_a_good_log_and_no_log_pass(config: Path, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    assert _check(config, capsys)[0] == 0  # no log yet: the first start makes it
    await _write_log(tmp_path)
    code, said = _check(config, capsys)
    assert code == 0, said


async def test_an_edited_last_entry_is_refused_as_the_start_refuses_it(
        config: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    await _write_log(tmp_path)
    log = tmp_path / "audit.jsonl"
    lines = log.read_bytes().splitlines(keepends=True)
    lines[-1] = lines[-1].replace(b'"n":4', b'"n":7')
    log.write_bytes(b"".join(lines))
    code, said = _check(config, capsys)
    refusal = await _start_refusal(tmp_path)
    assert code == 1
    assert f"bridge.audit.path: {refusal}" in said, (said, refusal)


async def test_a_replaced_key_is_named(config: Path, tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    await _write_log(tmp_path)
    (tmp_path / "audit.key").unlink()
    load_or_create_key(tmp_path / "audit.key")  # another key at key_path
    code, said = _check(config, capsys)
    assert code == 1
    assert "the signing key is not the one audit.jsonl.pub holds" in said, said
    assert f"bridge.audit.path: {await _start_refusal(tmp_path)}" in said


async def test_a_log_without_its_key_is_refused(config: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    await _write_log(tmp_path)
    (tmp_path / "audit.key").unlink()
    code, said = _check(config, capsys)
    assert code == 1
    assert "is missing, but the log" in said and "has entries" in said, said
    assert not (tmp_path / "audit.key").exists()  # config check made no key


async def test_a_torn_tail_passes_and_is_left_for_the_start_to_cut(
        config: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    await _write_log(tmp_path)
    log = tmp_path / "audit.jsonl"
    with log.open("ab") as f:
        f.write(b'{"seq":6,"half a line')
    before = log.read_bytes()
    code, said = _check(config, capsys)
    assert code == 0, said
    assert log.read_bytes() == before  # read only: the start cuts it, and audits the cut


async def test_beside_a_running_bridges_log_it_reads_and_disturbs_nothing(
        config: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    await _write_log(tmp_path)
    running = await AuditLog.open(tmp_path / "audit.jsonl", tmp_path / "audit.key")
    try:
        first = await running.append(AuditRecord(event=AuditEvent.COMMAND_REJECTED,
                                                 principal="ops"))
        code, said = await asyncio.to_thread(_check, config, capsys)
        assert code == 0, said
        then = await running.append(AuditRecord(event=AuditEvent.COMMAND_REJECTED,
                                                principal="ops"))
        assert then.seq == first.seq + 1  # the running log went on where it was
    finally:
        await running.close()
    assert _check(config, capsys)[0] == 0


async def test_it_reads_back_no_further_than_the_start_does(
        config: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The cost bound the start has (it verifies from its last checkpoint on): an entry
    edited before the checkpoint is seen by neither (`audit verify` reads it all), one
    after it by both. Guards the bound, not the check: a config check reading the whole
    chain on every call would refuse the first log, which the start takes."""
    log, checkpoint = tmp_path / "audit.jsonl", tmp_path / "audit.jsonl.checkpoint"
    await _write_log(tmp_path, 3)
    at_third = checkpoint.read_bytes()
    await _write_log(tmp_path, 3)
    checkpoint.write_bytes(at_third)  # a crashed run: entries 4 to 6 after the checkpoint
    lines = log.read_bytes().splitlines(keepends=True)
    lines[1] = lines[1].replace(b'"n":1', b'"n":7')  # entry 2, before the checkpoint
    log.write_bytes(b"".join(lines))
    assert _check(config, capsys)[0] == 0
    lines[4] = lines[4].replace(b'"n":1', b'"n":7')  # entry 5, after it
    log.write_bytes(b"".join(lines))
    code, said = _check(config, capsys)
    assert code == 1
    assert f"bridge.audit.path: {await _start_refusal(tmp_path)}" in said, said
    checkpoint.write_bytes(at_third)
    lines[4] = lines[4].replace(b'"n":7', b'"n":1')
    log.write_bytes(b"".join(lines))
    started = await AuditLog.open(log, tmp_path / "audit.key")  # the start takes it, too
    await started.close()


# Address space for the config check below: the interpreter and its imports fit, a log of
# LARGE_LOG read into memory (twice: its chunks, then their join) does not.
ADDRESS_SPACE = 1536 << 20
LARGE_LOG = 3 << 30


def _limited() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))


async def test_a_log_of_gigabytes_is_not_read_into_memory(
        config: Path, tmp_path: Path) -> None:
    """Red team 24: a sparse (or runaway) log of 3 GiB past its checkpoint was read whole
    into memory: a MemoryError's traceback under a memory limit, the OOM killer without one.
    More than READ_BACK_LIMIT is left unread — said in a note, not a failure (a start reads
    it) — and nothing is written."""
    await _write_log(tmp_path)
    log = tmp_path / "audit.jsonl"
    os.truncate(log, LARGE_LOG)  # sparse: no disk, and no newline in the zeros
    done = await asyncio.to_thread(
        subprocess.run,
        [sys.executable, "-c", "import sys; from rcan_rtps.cli.main import main; "
         f"sys.exit(main(['config', 'check', {str(config)!r}]))"],
        capture_output=True, text=True, preexec_fn=_limited, timeout=120,
        env={**os.environ, "RT_OPS": "x" * 32})
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    assert f"note: audit log {log} not read back: " in done.stderr, done.stderr
    assert f"more than config check reads ({READ_BACK_LIMIT})" in done.stderr
    assert log.stat().st_size == LARGE_LOG  # read only: the start cuts what it must


async def test_a_log_within_the_bound_is_still_read_back(
        config: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The bound is on what is read, not a way around the check: an edited entry in a log
    below it is refused as before."""
    await _write_log(tmp_path)
    log = tmp_path / "audit.jsonl"
    lines = log.read_bytes().splitlines(keepends=True)
    lines[-1] = lines[-1].replace(b'"n":4', b'"n":7')
    log.write_bytes(b"".join(lines) + b"x" * (READ_BACK_LIMIT // 2))  # a torn tail of 128 MiB
    code, said = _check(config, capsys)
    assert code == 1 and "note:" not in said, said
    assert f"bridge.audit.path: {await _start_refusal(tmp_path)}" in said, said
