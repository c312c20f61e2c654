"""`rcan-rtps audit verify` / `audit export-pubkey`: exit codes and messages, never a traceback."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from rcan_rtps.cli import audit_cmd
from rcan_rtps.governance.audit import AuditEvent, AuditLog, AuditRecord


def run(*argv: str) -> int:
    parser = argparse.ArgumentParser()
    audit_cmd.register(parser.add_subparsers(required=True))
    args = parser.parse_args(list(argv))
    code: int = args.func(args)
    return code


async def three_entries(tmp_path: Path) -> Path:
    """A signed log of three dispatched commands (and its key), closed."""
    log = await AuditLog.open(tmp_path / "a.jsonl", tmp_path / "k.key")
    for i in range(3):
        await log.append(AuditRecord(event=AuditEvent.COMMAND_DISPATCHED, params={"i": i}))
    await log.close()
    return tmp_path / "a.jsonl"


@pytest.fixture
async def chain_file(tmp_path: Path) -> Path:
    return await three_entries(tmp_path)


def test_verify_ok_with_exported_key(
    chain_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert run("audit", "export-pubkey", str(tmp_path / "k.key")) == 0
    pem = capsys.readouterr().out
    assert pem.startswith("-----BEGIN PUBLIC KEY-----")
    (tmp_path / "pub.pem").write_text(pem)
    assert run("audit", "verify", str(chain_file), "--pubkey", str(tmp_path / "pub.pem")) == 0
    assert "OK" in capsys.readouterr().out
    assert run("audit", "verify", str(chain_file)) == 0  # with the key beside the log
    assert "a.jsonl.pub" in capsys.readouterr().out
    (tmp_path / "a.jsonl.pub").unlink()
    assert run("audit", "verify", str(chain_file)) == 0
    assert "signatures need --pubkey" in capsys.readouterr().out


def test_verify_prints_first_bad_seq(
    chain_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lines = chain_file.read_bytes().splitlines(keepends=True)
    chain_file.write_bytes(lines[0] + lines[2])
    assert run("audit", "verify", str(chain_file)) == 1
    err = capsys.readouterr().err
    assert "seq 2" in err and "Traceback" not in err


def test_verify_missing_file_and_bad_key(
    tmp_path: Path, chain_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert run("audit", "verify", str(tmp_path / "nope.jsonl")) == 1
    (tmp_path / "junk.pem").write_text("junk")
    assert run("audit", "verify", str(chain_file), "--pubkey", str(tmp_path / "junk.pem")) == 1
    assert run("audit", "export-pubkey", str(tmp_path / "nope.key")) == 1
    assert "Traceback" not in capsys.readouterr().err


def test_export_pubkey_given_the_public_key_says_which_file_it_wants(
    chain_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The `.pub` beside the log is the file a newcomer finds; its 0644 mode was reported as
    a signing key readable by others."""
    public = chain_file.with_name("a.jsonl.pub")
    public.chmod(0o644)
    assert run("audit", "export-pubkey", str(public)) == 1
    err = capsys.readouterr().err
    assert err == (f"FAIL {public} is a public key already: export-pubkey reads the bridge's "
                   "signing key (bridge.audit.key_path)\n")
