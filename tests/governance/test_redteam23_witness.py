"""Red team 23: a `file:` audit witness at something that is no regular file. Red team 22
refused the audit log and the latch at /dev/null or a FIFO, not the witness — the copy of
the tree heads kept where the log's writer cannot rewrite them. At /dev/null the heads went
nowhere, with nothing said; at a FIFO its thread waited for good for a reader, every head
after kept from it, and `config check` said ok to both."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from rcan_rtps.cli.main import main
from rcan_rtps.governance.witness import Witness
from tests.config.test_redteam22_state_files import TOKEN, _config, _prepare_refuses


@pytest.fixture(autouse=True)
def token(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RT22_TOKEN", TOKEN)


def _witnessed_at(tmp_path: Path, target: str) -> Path:
    config = _config(tmp_path)
    config.write_text(config.read_text().replace(
        "key_path: audit.key}", f"key_path: audit.key, witness: 'file://{target}'}}"))
    return config


@pytest.mark.parametrize("kind", ["dev_null", "fifo", "link_to_dev_null"])
def test_a_witness_that_is_no_regular_file_is_refused_before_the_start(
        kind: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    target = tmp_path / "witness.jsonl"
    if kind == "fifo":
        os.mkfifo(target, 0o600)
    elif kind == "link_to_dev_null":
        target.symlink_to(os.devnull)
    config = _witnessed_at(tmp_path, os.devnull if kind == "dev_null" else str(target))
    assert main(["config", "check", str(config)]) == 1
    err = capsys.readouterr().err
    assert "bridge.audit.witness: " in err and "is not a regular file" in err, err
    assert "is not a regular file" in _prepare_refuses(config)


def test_a_fifo_put_at_the_witness_later_does_not_hold_its_thread(tmp_path: Path) -> None:
    fifo = tmp_path / "witness.jsonl"
    os.mkfifo(fifo, 0o600)
    witness = Witness(f"file://{fifo}")
    witness.submit(b'{"tree_size": 1}\n')
    witness.close(timeout=5)
    stuck = witness._thread.is_alive()
    if stuck:  # let it go: a reader opens the FIFO
        with open(fifo, "rb"):
            witness._thread.join(5)
    assert not stuck, "the witness thread waited on the FIFO for a reader"
    assert witness.sent == 0
