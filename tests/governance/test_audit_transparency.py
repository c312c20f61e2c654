"""The audit log's transparency: signed tree heads per commit, `audit verify` against its
anchors (tree heads, checkpoint, witness), `audit prove` / `audit consistency`, the witness, and
recovery from a full disk."""

from __future__ import annotations

import asyncio
import functools
import http.server
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rcan_rtps.governance import audit as audit_mod
from rcan_rtps.governance.audit import AuditEvent, AuditLog, AuditRecord, Checkpoint
from rcan_rtps.governance.clock import ManualClock
from rcan_rtps.governance.merkle import leaf_hash, root_of
from rcan_rtps.governance.treehead import TreeHead, parse_tree_heads
from tests.governance.test_audit_cli import run

N_ENTRIES = 8
FIXTURES = [HealthCheck.function_scoped_fixture]  # capsys and a read-only laid-out log
FILES = ("a.jsonl", "a.jsonl.sth", "a.jsonl.pub", "a.jsonl.checkpoint", "witness.sth")


def record(i: int) -> AuditRecord:
    return AuditRecord(event=AuditEvent.COMMAND_DISPATCHED, principal="ops", role="OWNER",
                       message_id=f"m{i}", action_type="move", params={"linear_x": 0.1 * i},
                       outcome="executed")


@functools.lru_cache(maxsize=1)
def sample() -> dict[str, bytes]:
    """A log of N_ENTRIES (one commit each) with its tree heads, key, checkpoint and the heads
    a file witness received; built once."""

    async def build(tmp: Path) -> None:
        log = await AuditLog.open(tmp / "a.jsonl", tmp / "k.key", clock=ManualClock(),
                                  witness=f"file://{tmp / 'witness.sth'}")
        for i in range(N_ENTRIES):
            await log.append(record(i))
        await log.close()

    with tempfile.TemporaryDirectory() as tmp:
        asyncio.run(build(Path(tmp)))
        return {name: Path(tmp, name).read_bytes() for name in FILES}


def lay_out(tmp: Path, **changed: bytes | None) -> Path:
    """The sample's files in `tmp`, with some replaced (None: removed); the log's path."""
    files = {name: sample()[name] for name in FILES}
    files.update({k.replace("_", "."): v for k, v in changed.items()})
    for name, data in files.items():
        target = tmp / name
        if target.exists():
            target.unlink()
        if data is not None:
            target.write_bytes(data)
    return tmp / "a.jsonl"


def verify_cli(capsys: pytest.CaptureFixture[str], *extra: str, **changed: bytes | None
               ) -> tuple[int, str]:
    with tempfile.TemporaryDirectory() as tmp:
        path = lay_out(Path(tmp), **changed)
        witness = [a.replace("WITNESS", str(Path(tmp, "witness.sth"))) for a in extra]
        code = run("audit", "verify", str(path), *witness)
    out = capsys.readouterr()
    assert "Traceback" not in out.err
    return code, out.out + out.err


def log_lines() -> list[bytes]:
    return sample()["a.jsonl"].splitlines(keepends=True)


def last_line_start() -> int:
    data = sample()["a.jsonl"]
    return data.rindex(b"\n", 0, len(data) - 1) + 1


def heads_up_to(size: int, data: bytes) -> bytes:
    """The tree-head lines of `data` whose size is at most `size` (an attacker's cut)."""
    heads, _ = parse_tree_heads(data)
    return b"".join(h.line() for h in heads if isinstance(h, TreeHead) and h.tree_size <= size)


# -- the sample --------------------------------------------------------------------------------


def test_one_signed_head_per_commit_and_the_witness_got_them(
    capsys: pytest.CaptureFixture[str],
) -> None:
    heads, torn = parse_tree_heads(sample()["a.jsonl.sth"])
    assert not torn and all(isinstance(h, TreeHead) for h in heads)
    assert [h.tree_size for h in heads if isinstance(h, TreeHead)] == list(range(1, 9))
    assert sample()["witness.sth"] == sample()["a.jsonl.sth"]
    # The root is RFC 6962 over the entries' lines (no newline).
    last = heads[-1]
    assert isinstance(last, TreeHead)
    assert last.root == root_of([leaf_hash(line.rstrip(b"\n")) for line in log_lines()])
    code, out = verify_cli(capsys, "--witness", "WITNESS")
    assert code == 0, out
    assert "8 entries" in out and "8 tree heads and 8 witnessed match" in out
    assert "a.jsonl.pub" in out


async def test_a_group_commit_gets_one_head_and_a_reopened_log_goes_on(tmp_path: Path) -> None:
    log = await AuditLog.open(tmp_path / "a.jsonl", tmp_path / "k.key")
    await asyncio.gather(*(log.append(record(i)) for i in range(40)))
    await log.close()
    heads = [h for h in parse_tree_heads((tmp_path / "a.jsonl.sth").read_bytes())[0]
             if isinstance(h, TreeHead)]
    assert len(heads) < 40 and heads[-1].tree_size == 40
    # Reopened: the tree comes back from the checkpoint's peaks and grows from there.
    log = await AuditLog.open(tmp_path / "a.jsonl", tmp_path / "k.key")
    await log.append(record(41))
    await log.close()
    heads = [h for h in parse_tree_heads((tmp_path / "a.jsonl.sth").read_bytes())[0]
             if isinstance(h, TreeHead)]
    assert [h.tree_size for h in heads[-2:]] == [40, 41]  # at open, then the new commit
    assert run("audit", "verify", str(tmp_path / "a.jsonl")) == 0


async def test_old_logs_keep_verifying_and_get_heads_when_opened(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = await AuditLog.open(tmp_path / "a.jsonl", tmp_path / "k.key")
    for i in range(5):
        await log.append(record(i))
    await log.close()
    # What an older version leaves: no tree heads, no key beside, a checkpoint without peaks.
    for name in ("a.jsonl.sth", "a.jsonl.pub"):
        (tmp_path / name).unlink()
    cp = json.loads((tmp_path / "a.jsonl.checkpoint").read_bytes())
    audit_mod._write_checkpoint(tmp_path / "a.jsonl.checkpoint",
                                audit_mod.load_private_key(tmp_path / "k.key"),
                                Checkpoint(seq=cp["seq"], audit_id=cp["audit_id"],
                                           start=cp["start"], end=cp["end"]))
    assert run("audit", "verify", str(tmp_path / "a.jsonl")) == 0
    assert "hashes only" in capsys.readouterr().out
    log = await AuditLog.open(tmp_path / "a.jsonl", tmp_path / "k.key")
    await log.append(record(9))
    await log.close()
    assert run("audit", "verify", str(tmp_path / "a.jsonl")) == 0
    out = capsys.readouterr().out
    assert "6 entries" in out and "size 6" in out and "a.jsonl.pub" in out


# -- verify: every change fails ----------------------------------------------------------------


@settings(max_examples=150, deadline=None, suppress_health_check=FIXTURES)
@given(data=st.data())
def test_any_single_byte_change_fails(data: st.DataObject,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    log = sample()["a.jsonl"]
    offset = data.draw(st.integers(0, len(log) - 1))
    new = data.draw(st.integers(0, 255).filter(lambda b: b != log[offset]))
    code, out = verify_cli(capsys, a_jsonl=log[:offset] + bytes([new]) + log[offset + 1:])
    assert code != 0
    if offset >= last_line_start():
        assert "torn tail" in out
    else:
        seq = log.count(b"\n", 0, offset) + 1
        assert f"seq {seq}:" in out and "torn tail" not in out


@settings(max_examples=80, deadline=None, suppress_health_check=FIXTURES)
@given(data=st.data())
def test_any_byte_deletion_fails(data: st.DataObject,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    log = sample()["a.jsonl"]
    offset = data.draw(st.integers(0, len(log) - 1))
    code, out = verify_cli(capsys, a_jsonl=log[:offset] + log[offset + 1:])
    assert code != 0
    if offset >= last_line_start():
        assert "torn tail" in out


@settings(max_examples=40, deadline=None, suppress_health_check=FIXTURES)
@given(index=st.integers(0, N_ENTRIES - 1))
def test_any_line_deletion_fails(index: int, capsys: pytest.CaptureFixture[str]) -> None:
    lines = log_lines()
    code, out = verify_cli(capsys, a_jsonl=b"".join(lines[:index] + lines[index + 1:]))
    assert code != 0
    # The last line removed is a truncation: the tree heads name it.
    assert "truncated" in out if index == N_ENTRIES - 1 else f"seq {index + 1}" in out


@settings(max_examples=40, deadline=None, suppress_health_check=FIXTURES)
@given(pair=st.lists(st.integers(0, N_ENTRIES - 1), min_size=2, max_size=2, unique=True))
def test_any_reordering_fails(pair: list[int], capsys: pytest.CaptureFixture[str]) -> None:
    lines = log_lines()
    i, j = sorted(pair)
    lines[i], lines[j] = lines[j], lines[i]
    code, out = verify_cli(capsys, a_jsonl=b"".join(lines))
    assert code != 0 and f"seq {i + 1}" in out


@settings(max_examples=80, deadline=None, suppress_health_check=FIXTURES)
@given(data=st.data())
def test_any_truncation_fails(data: st.DataObject, capsys: pytest.CaptureFixture[str]) -> None:
    log = sample()["a.jsonl"]
    cut = data.draw(st.integers(0, len(log) - 1))
    code, out = verify_cli(capsys, a_jsonl=log[:cut])
    assert code != 0
    if cut > last_line_start():
        assert "torn tail" in out
    elif cut in (0, *(i + 1 for i, b in enumerate(log) if b == ord("\n"))):
        assert "truncated" in out


@settings(max_examples=30, deadline=None, suppress_health_check=FIXTURES)
@given(kept=st.integers(0, N_ENTRIES - 1))
def test_a_cut_covering_its_tracks_is_caught_by_the_witness(
    kept: int, capsys: pytest.CaptureFixture[str]
) -> None:
    """An attacker who cuts the log at a line and cuts the tree heads and checkpoint to match
    leaves a log that checks out on the box: only a witnessed head shows the cut."""
    cut = {"a_jsonl": b"".join(log_lines()[:kept]),
           "a_jsonl_sth": heads_up_to(kept, sample()["a.jsonl.sth"]),
           "a_jsonl_checkpoint": None}
    code, out = verify_cli(capsys, **cut)
    assert code == 0, out
    assert "no tree head" in out if kept == 0 else f"{kept} entries" in out
    code, out = verify_cli(capsys, "--witness", "WITNESS", **cut)
    assert code != 0
    assert f"witness.sth line {N_ENTRIES}: tree head of size {N_ENTRIES}" in out
    assert "truncated" in out


def test_an_empty_or_missing_log_fails_given_an_anchor(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, out = verify_cli(capsys, a_jsonl=b"")
    assert code != 0 and f"tree head of size {N_ENTRIES}" in out and "truncated" in out
    code, out = verify_cli(capsys, a_jsonl=None)
    assert code != 0 and "missing" in out
    # Only the checkpoint is left: it names the entries.
    code, out = verify_cli(capsys, a_jsonl=b"", a_jsonl_sth=None)
    assert code != 0 and f"checkpoint names seq {N_ENTRIES}" in out


def test_a_forged_or_foreign_head_fails(capsys: pytest.CaptureFixture[str]) -> None:
    heads = sample()["a.jsonl.sth"].splitlines(keepends=True)
    forged = heads[2].replace(b'"tree_size":3', b'"tree_size":2')
    code, out = verify_cli(capsys, a_jsonl_sth=b"".join([*heads[:2], forged, *heads[3:]]))
    assert code != 0 and "line 3" in out and "bad signature" in out
    # A pinned key that is not the log's: entries and heads fail.
    with tempfile.TemporaryDirectory() as tmp:
        other = audit_mod.load_or_create_key(Path(tmp, "other.key"))
        Path(tmp, "other.pub").write_bytes(audit_mod.public_key_pem(other))
        code, out = verify_cli(capsys, "--pubkey", str(Path(tmp, "other.pub")))
    assert code != 0 and "bad signature" in out


def test_a_torn_last_head_is_only_a_note(capsys: pytest.CaptureFixture[str]) -> None:
    sth = sample()["a.jsonl.sth"]
    code, out = verify_cli(capsys, a_jsonl_sth=sth[:-30])
    assert code == 0 and "incomplete last line" in out


# -- proofs ------------------------------------------------------------------------------------


@pytest.fixture
def laid_out(tmp_path: Path) -> Path:
    return lay_out(tmp_path)


def proof_of(capsys: pytest.CaptureFixture[str], *argv: str) -> dict[str, object]:
    assert run("audit", *argv) == 0
    doc: dict[str, object] = json.loads(capsys.readouterr().out)
    return doc


def check(capsys: pytest.CaptureFixture[str], verb: str, doc: object, log: Path) -> int:
    proof = log.with_name("proof.json")
    proof.write_text(json.dumps(doc))
    code = run("audit", verb, "--verify", str(proof), "--pubkey", str(log) + ".pub")
    assert "Traceback" not in capsys.readouterr().err
    return code


def _flip_hex(text: str, at: int) -> str:
    return text[:at] + ("0" if text[at] != "0" else "1") + text[at + 1:]


@settings(max_examples=40, deadline=None, suppress_health_check=FIXTURES)
@given(data=st.data())
def test_inclusion_proofs_verify_and_fail_on_tamper(
    data: st.DataObject, laid_out: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    seq = data.draw(st.integers(1, N_ENTRIES))
    size = data.draw(st.sampled_from([None, *range(seq, N_ENTRIES + 1)]))
    argv = ["prove", str(laid_out), str(seq)] + ([] if size is None else ["--size", str(size)])
    doc = proof_of(capsys, *argv)
    assert check(capsys, "prove", doc, laid_out) == 0
    head = doc["tree_head"]
    assert isinstance(head, dict) and head["tree_size"] == (size or N_ENTRIES)
    tampered = json.loads(json.dumps(doc))
    how = data.draw(st.sampled_from(["path", "seq", "size", "entry", "root"]))
    path = tampered["inclusion_path"]
    if how == "path" and path:
        i = data.draw(st.integers(0, len(path) - 1))
        path[i] = _flip_hex(path[i], data.draw(st.integers(0, 63)))
    elif how == "seq":
        other = data.draw(st.integers(1, N_ENTRIES).filter(lambda s: s != seq))
        tampered["seq"], tampered["leaf_index"] = other, other - 1
    elif how == "size":
        tampered["tree_head"]["tree_size"] += data.draw(st.sampled_from([-1, 1]))
    elif how == "entry":
        tampered["entry"] = tampered["entry"].replace('"move"', '"arm"')
        tampered["leaf_hash"] = leaf_hash(tampered["entry"].encode()).hex()
    else:
        tampered["tree_head"]["root_hash"] = _flip_hex(tampered["tree_head"]["root_hash"], 5)
    if tampered != doc:
        assert check(capsys, "prove", tampered, laid_out) != 0


@settings(max_examples=40, deadline=None, suppress_health_check=FIXTURES)
@given(data=st.data())
def test_consistency_proofs_verify_and_fail_on_tamper(
    data: st.DataObject, laid_out: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    new = data.draw(st.integers(1, N_ENTRIES))
    old = data.draw(st.integers(1, new))
    doc = proof_of(capsys, "consistency", str(laid_out), str(old), str(new))
    assert doc["old_tree_head"] is not None and doc["new_tree_head"] is not None
    assert check(capsys, "consistency", doc, laid_out) == 0
    tampered = json.loads(json.dumps(doc))
    how = data.draw(st.sampled_from(["path", "old", "new", "root", "head"]))
    path = tampered["consistency_path"]
    if how == "path" and path:
        i = data.draw(st.integers(0, len(path) - 1))
        path[i] = _flip_hex(path[i], data.draw(st.integers(0, 63)))
    # A size is only ever claimed with its signed head (RFC 9162 proofs bind a size through
    # its root, not on their own): a changed size no longer matches it.
    elif how == "old" and old > 1:
        tampered["old_size"] -= 1
    elif how == "new" and new < N_ENTRIES:
        tampered["new_size"] += 1
    elif how == "root":
        tampered["old_root"] = _flip_hex(tampered["old_root"], 7)
        tampered["old_tree_head"] = None
    elif how == "head":
        tampered["new_tree_head"]["timestamp_ms"] += 1  # no longer what the key signed
    if tampered != doc and (tampered["consistency_path"] or how != "path"):
        assert check(capsys, "consistency", tampered, laid_out) != 0


def test_proof_errors_are_messages(laid_out: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert run("audit", "prove", str(laid_out), str(N_ENTRIES + 1)) == 1
    capsys.readouterr()
    assert run("audit", "prove", str(laid_out), "0") == 1  # a 0-based index: said so
    assert "entries are counted from 1" in capsys.readouterr().err
    assert run("audit", "consistency", str(laid_out), "5", "3") == 1
    assert run("audit", "prove", "--verify", str(laid_out)) == 1  # not a proof (no key first)
    assert run("audit", "prove", "--verify", str(laid_out), "--pubkey",
               str(laid_out) + ".pub") == 1  # not JSON
    assert "Traceback" not in capsys.readouterr().err


# -- the witness ---------------------------------------------------------------------------


class _Receiver(http.server.BaseHTTPRequestHandler):
    bodies: list[bytes]
    hold: threading.Event

    def do_POST(self) -> None:
        self.hold.wait(30)
        self.bodies.append(self.rfile.read(int(self.headers["Content-Length"])))
        self.send_response(204)
        self.end_headers()

    def log_message(self, *args: object) -> None:
        pass


@pytest.fixture
def receiver() -> Iterator[tuple[str, type[_Receiver]]]:
    handler = type("Receiver", (_Receiver,), {"bodies": [], "hold": threading.Event()})
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}/heads", handler
    handler.hold.set()
    server.shutdown()
    server.server_close()


async def test_a_url_witness_gets_every_head_and_never_holds_an_append(
    tmp_path: Path, receiver: tuple[str, type[_Receiver]]
) -> None:
    url, handler = receiver
    log = await AuditLog.open(tmp_path / "a.jsonl", tmp_path / "k.key", witness=url)
    # The witness holds its first POST until we say: every append still returns.
    for i in range(5):
        await log.append(record(i))
    assert handler.bodies == []
    handler.hold.set()
    await log.close()
    sent = b"".join(body + b"\n" for body in handler.bodies)
    assert sent == (tmp_path / "a.jsonl.sth").read_bytes()
    (tmp_path / "witnessed.sth").write_bytes(sent)
    assert run("audit", "verify", str(tmp_path / "a.jsonl"), "--witness",
               str(tmp_path / "witnessed.sth")) == 0


async def test_an_unreachable_witness_is_logged_not_fatal(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    import socket

    with socket.socket() as s:  # a loopback port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    log = await AuditLog.open(tmp_path / "a.jsonl", tmp_path / "k.key",
                              witness=f"http://127.0.0.1:{port}/")
    for i in range(3):
        await log.append(record(i))
    await log.close()
    assert audit_mod.verify(tmp_path / "a.jsonl").count == 3
    assert any("witness" in r.getMessage() and "not sent" in r.getMessage()
               for r in caplog.records)


def test_witness_urls_are_checked() -> None:
    from rcan_rtps.governance.witness import witness_problem

    assert witness_problem("file:///var/lib/w.sth") is None
    assert witness_problem("https://witness.example/heads") is None
    for bad in ("file://relative/w", "ftp://x/y", "/var/lib/w.sth", "https:///nohost"):
        assert witness_problem(bad)


# -- a full disk, for real --------------------------------------------------------------------

FULL_DISK = Path(__file__).with_name("full_disk.py")


def _child_env() -> dict[str, str]:
    src = str(Path(audit_mod.__file__).parents[2])
    return {**os.environ, "PYTHONPATH": src + os.pathsep + os.environ.get("PYTHONPATH", "")}


def _full_disk_case(result: dict[str, object], out: Path,
                    capsys: pytest.CaptureFixture[str]) -> None:
    while_full, after = result["while_full"], result["after"]
    assert isinstance(while_full, list) and isinstance(after, list)
    assert while_full and all(r != "ok" for r in while_full), while_full
    assert result["size_after_failures"] == result["full_size"]  # cut back, nothing torn
    assert after == ["ok"] * len(after) and result["healthy"]
    assert run("audit", "verify", str(out / "audit.jsonl")) == 0
    assert f"{result['head']} entries" in capsys.readouterr().out


def test_the_audit_recovers_from_a_full_tmpfs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    if os.geteuid() != 0 or shutil.which("unshare") is None:
        pytest.skip("mounting a small tmpfs needs root and unshare")
    disk, out = tmp_path / "disk", tmp_path / "out"
    disk.mkdir()
    out.mkdir()
    script = (f"mount -t tmpfs -o size=64k tmpfs {disk} && "
              f"exec {sys.executable} {FULL_DISK} {disk} {out} --tmpfs")
    child = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True,
                           text=True, env=_child_env(), timeout=120)
    if "mount" in child.stderr and child.returncode != 0 and not child.stdout:
        pytest.skip(f"cannot mount a tmpfs here: {child.stderr.strip()}")
    assert child.returncode == 0, child.stderr
    result = json.loads(child.stdout)
    assert any("No space left" in r for r in result["while_full"])  # ENOSPC, from the kernel
    _full_disk_case(result, out, capsys)


def test_the_audit_recovers_from_efbig(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    disk, out = tmp_path / "disk", tmp_path / "out"
    disk.mkdir()
    out.mkdir()
    child = subprocess.run([sys.executable, str(FULL_DISK), str(disk), str(out), "--rlimit"],
                           capture_output=True, text=True, env=_child_env(), timeout=120)
    assert child.returncode == 0, child.stderr
    result = json.loads(child.stdout)
    assert any("File too large" in r for r in result["while_full"])  # EFBIG, from the kernel
    _full_disk_case(result, out, capsys)


def test_the_witness_is_a_checked_config_key() -> None:
    from rcan_rtps.config import ConfigError, loads_config

    base = ("robot: {ruri: rcan://registry.local/clearpath/husky/a200-0001}\n"
            "bridge:\n  api: {auth_token_env: RCAN_BRIDGE_TOKEN}\n"
            "  safety: {max_linear_vel: 1.5, max_angular_vel: 1.0}\n")
    config = loads_config(base + "  audit: {witness: 'file:///mnt/witness/robot1.sth'}\n", env={})
    assert config.bridge.audit.witness == "file:///mnt/witness/robot1.sth"
    assert loads_config(base, env={}).bridge.audit.witness is None
    with pytest.raises(ConfigError) as info:
        loads_config(base + "  audit: {witness: 'witness.sth'}\n", env={})
    [issue] = info.value.issues
    assert issue.path == "$.bridge.audit.witness" and "file://" in issue.message


def test_a_failed_atomic_write_leaves_no_temporary_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from rcan_rtps.governance import _durable

    def full(fd: int, data: bytes) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(_durable, "write_all", full)
    with pytest.raises(OSError):
        _durable.atomic_write(tmp_path / "state", b"x")
    assert list(tmp_path.iterdir()) == []  # no half-written copy taking the space freed


def test_the_public_key_beside_the_log_is_the_pem_cryptography_writes(tmp_path: Path) -> None:
    from cryptography.hazmat.primitives import serialization

    key = audit_mod.load_or_create_key(tmp_path / "k.key")
    assert audit_mod.public_key_pem(key) == key.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo)
