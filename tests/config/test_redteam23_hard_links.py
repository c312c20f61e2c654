"""Red team 23: one file named twice through a hard link. Red team 22's check resolved `..`
and symbolic links, so two names of one inode passed: a `file:` witness (appended to) that is
a second name of the config file or of the audit log loaded, and the bridge's first tree
head went into the config (the next start could not read it) or the log (its chain broken
by a line that is no entry). The same check is what stands between a case-insensitive file
system (macOS's) and `estop_state_path: Audit.jsonl` replacing `audit.jsonl`."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests.config.test_redteam22_paths import _refused, _write


@pytest.mark.parametrize(("target", "at", "also"), [
    ("robot.rcan.yaml", "$.bridge.audit.witness", "the config file"),
    ("audit/audit.jsonl", "$.bridge.audit.path", "bridge.audit.witness"),
])
def test_a_hard_link_to_a_file_the_bridge_writes_is_that_file(
        target: str, at: str, also: str, tmp_path: Path) -> None:
    (tmp_path / "audit").mkdir()
    (tmp_path / "audit" / "audit.jsonl").touch()
    config = _write(tmp_path, audit=f"    witness: file://{tmp_path}/witness.jsonl")
    os.link(tmp_path / target, tmp_path / "witness.jsonl")
    path, message = _refused(config)
    assert path == at
    assert f" is also {also}: the bridge writes it, so it must be a file of its own" in message
