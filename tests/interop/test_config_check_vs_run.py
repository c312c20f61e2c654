"""`rcan-rtps config check` says what a real `rcan-rtps run` then refuses about an existing
audit log, in the same words, and is read only beside a `run` that is writing the log.

Both are real processes (the `run`s inside `scripts/netns`: they join a DDS domain). A log is
damaged as it is found on robots: an entry edited after the last checkpoint (a crashed run's
tail, the part a start verifies), a last line torn but terminated (the start cuts only an
unterminated one), the signing key replaced, a log another key signed put in its place.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path

import pytest

from rcan_rtps.governance import AuditEvent, AuditLog, AuditRecord
from rcan_rtps.governance.audit import checkpoint_path, load_or_create_key

from .run_process import RunProcess, child_env, post

TOKEN = "t" * 32
TOKEN_ENV = "RCAN_BRIDGE_TOKEN"


def _config(tmp: Path, domain_id: int) -> Path:
    path = tmp / "robot.rcan.yaml"
    path.write_text(textwrap.dedent(f"""\
        robot: {{ruri: rcan://registry.local/acme/rover/unit-0001}}
        bridge:
          ros2: {{namespace: /robot1, node_name: rcan_bridge, domain_id: {domain_id}}}
          api: {{host: 127.0.0.1, auth_token_env: {TOKEN_ENV}}}
          safety: {{max_linear_vel: 1.0, max_angular_vel: 1.0}}
          audit: {{path: {tmp / "audit.jsonl"}, key_path: {tmp / "audit.key"}}}
        """))
    return path


def _env(domain_id: int) -> dict[str, str]:
    return child_env(domain_id, **{TOKEN_ENV: TOKEN})


def _cli(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rcan_rtps", *args], capture_output=True,
                          text=True, env=env, timeout=120)


def _config_check(config: Path, env: dict[str, str]) -> tuple[int, list[str]]:
    """config check's exit status and the audit log's problems it lists."""
    done = _cli(env, "config", "check", str(config))
    return done.returncode, re.findall(r"^  - bridge\.audit\.path: (.*)$", done.stderr, re.M)


def _run_refusal(config: Path, env: dict[str, str]) -> tuple[int, str]:
    """A real start's exit status and its error line."""
    done = _cli(env, "run", "--config", str(config), "--port", "0", "--no-mdns")
    said = re.findall(r"^rcan-rtps: error: (.*)$", done.stderr, re.M)
    assert len(said) == 1, done.stdout + done.stderr
    return done.returncode, said[0]


async def _sessions(where: Path, *entries: int) -> None:
    """Runs of the log, each closed: `entries` entries each."""
    for count in entries:
        log = await AuditLog.open(where / "audit.jsonl", where / "audit.key")
        for i in range(count):
            await log.append(AuditRecord(event=AuditEvent.COMMAND_REJECTED, principal="ops",
                                         params={"n": i}))
        await log.close()


def _crashed_log(where: Path) -> None:
    """Six entries whose last checkpoint is at the third: a run after it ended without its
    closing checkpoint (killed), so the next start verifies entries 4 to 6."""
    asyncio.run(_sessions(where, 3))
    at_third = checkpoint_path(where / "audit.jsonl").read_bytes()
    asyncio.run(_sessions(where, 3))
    checkpoint_path(where / "audit.jsonl").write_bytes(at_third)


def _edit_line(log: Path, seq: int, old: bytes, new: bytes) -> None:
    lines = log.read_bytes().splitlines(keepends=True)
    assert old in lines[seq - 1]
    lines[seq - 1] = lines[seq - 1].replace(old, new)
    log.write_bytes(b"".join(lines))


def _edited_after_the_checkpoint(where: Path) -> None:
    _crashed_log(where)
    _edit_line(where / "audit.jsonl", 4, b'"n":0', b'"n":9')


def _torn_but_terminated(where: Path) -> None:
    """A last line cut short, then a newline: no unterminated tail, so not cut at a start."""
    asyncio.run(_sessions(where, 5))
    with (where / "audit.jsonl").open("ab") as log:
        log.write(b'{"seq":6,"half a line\n')


def _key_replaced(where: Path) -> None:
    asyncio.run(_sessions(where, 5))
    (where / "audit.key").unlink()
    load_or_create_key(where / "audit.key")  # audit.jsonl.pub still holds the log's key


def _signed_by_another_key(where: Path) -> None:
    """Another robot's log (and its checkpoint) copied over this one's: the key beside the
    log is this robot's, so nothing says the key changed — the entries just do not verify."""
    other = where / "other"
    other.mkdir()
    asyncio.run(_sessions(other, 5))
    asyncio.run(_sessions(where, 2))
    for name in ("audit.jsonl", "audit.jsonl.checkpoint"):
        os.replace(other / name, where / name)


DAMAGE: dict[str, tuple[Callable[[Path], None], str]] = {
    "edited after the checkpoint": (_edited_after_the_checkpoint,
                                    "seq 4: audit_id does not match"),
    "torn but terminated": (_torn_but_terminated, "seq 6: the last line is damaged"),
    "key replaced": (_key_replaced, "the signing key is not the one audit.jsonl.pub holds"),
    "signed by another key": (_signed_by_another_key, "seq 1: bad signature"),
}


@pytest.mark.parametrize("damage", DAMAGE)
def test_config_check_says_what_the_start_refuses_in_its_words(
        damage: str, tmp_path: Path, domain_id: int) -> None:
    make, expected = DAMAGE[damage]
    make(tmp_path)
    config, env = _config(tmp_path, domain_id), _env(domain_id)
    log_before = (tmp_path / "audit.jsonl").read_bytes()
    checked, problems = _config_check(config, env)
    assert (tmp_path / "audit.jsonl").read_bytes() == log_before  # read only
    started, refusal = _run_refusal(config, env)
    assert started == 1
    assert expected in refusal and refusal.endswith("refusing to start"), refusal
    assert (checked, problems) == (1, [refusal])


def _live_log(where: Path) -> list[dict[str, object]]:
    return [json.loads(line) for line in (where / "audit.jsonl").read_text().splitlines()]


async def _refused_moves(url: str, count: int | None = None,
                         until: asyncio.Event | None = None) -> list[int]:
    """Moves over the speed limit, `count` of them or until `until` is set: refused (no
    motion), each one an audit entry."""
    body = {"action": "move", "params": {"linear_x": 9.0}}
    statuses: list[int] = []
    while (len(statuses) < count) if count is not None else not (until and until.is_set()):
        statuses.append((await post(url, TOKEN, body))[0])
    return statuses


CHECKS_WHILE_WRITING = 3


def test_beside_a_running_bridge_it_reads_the_log_and_disturbs_nothing(
        tmp_path: Path, domain_id: int) -> None:
    config, env = _config(tmp_path, domain_id), _env(domain_id)
    proc = RunProcess(["run", "--config", str(config), "--port", "0", "--no-mdns"], env,
                      demo=False)
    try:
        key = tmp_path / "audit.key"
        bridge_key = key.read_bytes()
        checks: list[tuple[int, list[str]]] = []

        async def check_while_writing() -> list[int]:
            done = asyncio.Event()
            writing = asyncio.ensure_future(_refused_moves(proc.url, until=done))
            while len(checks) < CHECKS_WHILE_WRITING:  # the log grows meanwhile
                checks.append(await asyncio.to_thread(_config_check, config, env))
            done.set()
            return await writing

        written = asyncio.run(check_while_writing())
        assert written and set(written) == {409}, proc.output()
        assert checks == [(0, [])] * CHECKS_WHILE_WRITING
        # The next start's view: the key at key_path replaced under the running bridge (it
        # signs with the key it loaded). config check reads the live log, and names it.
        key.unlink()
        load_or_create_key(key)
        checked, problems = _config_check(config, env)
        assert checked == 1 and len(problems) == 1, problems
        assert "the signing key is not the one audit.jsonl.pub holds" in problems[0]
        key.unlink()
        key.write_bytes(bridge_key)
        key.chmod(0o600)
        assert _config_check(config, env) == (0, [])
        assert asyncio.run(_refused_moves(proc.url, 3)) == [409] * 3  # it ran on, unharmed
        assert proc.stop() == 0, proc.output()
    finally:
        proc.kill()
    entries = _live_log(tmp_path)
    assert [e["event"] for e in entries].count("COMMAND_REJECTED") == len(written) + 3
    assert "AUDIT_TAIL_RECOVERED" not in {e["event"] for e in entries}
    verified = _cli(env, "audit", "verify", str(tmp_path / "audit.jsonl"))
    assert verified.returncode == 0, verified.stdout + verified.stderr
    assert _config_check(config, env) == (0, [])
