"""Issue 24 item 8: new audit entries are RCAN canonical JSON v1; old logs keep verifying.

The oracles: rcan-spec's canonical-JSON vectors (tests/data/rcan-spec, with their source) and
the rcan SDK's `rcan.encoding.canonical_json`, which must recompute every new entry's id.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rcan.encoding import canonical_json

from rcan_rtps.governance import AuditEvent, AuditLog, AuditRecord, ManualClock, verify
from rcan_rtps.governance.audit import canonical_v1, load_public_key

DATA = Path(__file__).parents[1] / "data"
VECTORS = json.loads((DATA / "rcan-spec" / "canonical-json-v1.json").read_text())
OLD = DATA / "audit-before-v1"
RURI = "rcan://registry.local/clearpath/husky/v1/a200-0001"


@pytest.mark.parametrize("case", VECTORS["cases"], ids=lambda c: c["name"])
def test_rcan_spec_canonical_json_vectors(case: dict[str, Any]) -> None:
    assert canonical_v1(case["input"]) == base64.b64decode(case["expected_bytes_base64"])


_TEXT = st.text(st.characters(blacklist_categories=("Cs",)), max_size=12)
_JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | _TEXT
    | st.floats(allow_nan=False, allow_infinity=False),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(_TEXT, inner, max_size=4),
    max_leaves=20)


@settings(max_examples=400, deadline=None)
@given(st.dictionaries(_TEXT, _JSON, max_size=6))
def test_the_sdk_writes_the_same_bytes(body: dict[str, Any]) -> None:
    assert canonical_v1(body) == canonical_json(body)


def _record(n: int, **kw: Any) -> AuditRecord:
    fields: dict[str, Any] = dict(
        event=AuditEvent.COMMAND_DISPATCHED, principal="planner", role="USER",
        message_id=f"m{n}", action_type="move",
        params={"linear_x": 1.0, "duration_s": 2.0, "note": "café ☕"},
        applied={"linear_x": 1.0, "angular_z": -0.0, "ramp_from": [0.0, 0.5, 2.5e-05]},
        outcome="executed", ros2_topic="/robot1/cmd_vel",
        ai={"provider": "acme", "model": "m", "confidence": 1.0, "thought_id": None})
    fields.update(kw)
    return AuditRecord(**fields)


def _sdk_recomputes(line: bytes) -> bool:
    entry = json.loads(line)
    body = {k: v for k, v in entry.items() if k not in ("audit_id", "sig")}
    return bool(entry["audit_id"] == "sha256:" + hashlib.sha256(canonical_json(body)).hexdigest()
                and canonical_json(entry) == line)


async def test_the_sdk_recomputes_every_new_audit_id(tmp_path: Path) -> None:
    log = await AuditLog.open(tmp_path / "audit.jsonl", tmp_path / "audit.key", ruri=RURI,
                              clock=ManualClock())
    for n in range(5):
        await log.append(_record(n))
    await log.close()
    lines = (tmp_path / "audit.jsonl").read_bytes().splitlines()
    assert len(lines) == 5 and all(_sdk_recomputes(line) for line in lines)
    assert b'"linear_x":1,' in lines[0] and b'"angular_z":0,' in lines[0]  # 1.0, -0.0
    assert b"2.5e-05" in lines[0]  # Python's spelling, as the SDK's
    verify(tmp_path / "audit.jsonl", load_public_key(tmp_path / "audit.jsonl.pub"))


def _copy_old_log(tmp_path: Path) -> Path:
    for item in OLD.iterdir():
        shutil.copy(item, tmp_path / item.name)
    os.chmod(tmp_path / "audit.key", 0o600)
    return tmp_path / "audit.jsonl"


async def test_an_old_log_verifies_and_goes_on_with_v1_entries(tmp_path: Path) -> None:
    path = _copy_old_log(tmp_path)
    old_lines = path.read_bytes().splitlines()
    assert not _sdk_recomputes(old_lines[0])  # written before v1: "linear_x":1.0
    pubkey = load_public_key(tmp_path / "audit.jsonl.pub")
    assert verify(path, pubkey).count == 3
    log = await AuditLog.open(path, tmp_path / "audit.key", ruri=RURI, clock=ManualClock())
    await log.append(_record(4))
    await log.append(_record(5, event=AuditEvent.ESTOP, action_type="estop"))
    await log.close()
    lines = path.read_bytes().splitlines()
    assert lines[:3] == old_lines  # never rewritten
    assert all(_sdk_recomputes(line) for line in lines[3:])
    assert verify(path, pubkey).count == len(lines)
    cli = subprocess.run([sys.executable, "-m", "rcan_rtps", "audit", "verify", str(path)],
                         capture_output=True, text=True, env={**os.environ})
    assert cli.returncode == 0, cli.stdout + cli.stderr  # chain, tree heads, checkpoint


@pytest.mark.parametrize("edit", ["drop the marker", "claim v1 for an old entry"])
async def test_no_entry_can_change_its_canonical_form(tmp_path: Path, edit: str) -> None:
    path = _copy_old_log(tmp_path)
    log = await AuditLog.open(path, tmp_path / "audit.key", ruri=RURI, clock=ManualClock())
    await log.append(_record(4))
    await log.close()
    lines = path.read_bytes().splitlines()
    seq = 4 if edit == "drop the marker" else 1
    entry = json.loads(lines[seq - 1])
    if edit == "drop the marker":
        del entry["canonical"]
    else:
        entry["canonical"] = "rcan-canonical-json-v1"
    lines[seq - 1] = canonical_v1(entry) if "canonical" in entry else json.dumps(
        entry, sort_keys=True, separators=(",", ":")).encode()
    path.write_bytes(b"\n".join(lines) + b"\n")
    cli = subprocess.run([sys.executable, "-m", "rcan_rtps", "audit", "verify", str(path)],
                         capture_output=True, text=True)
    assert cli.returncode == 1 and f"seq {seq}" in (cli.stdout + cli.stderr), cli.stdout
