"""What a start takes up from the audit log: the e-stop latch and the motion locks held.

The latch file says whether the e-stop is latched, but a file can be rewritten (`latched:
false`) or lost; the audit chain is signed. A start therefore latches if *either* says so: the
log's last word on the latch is read from its tail, back to the last BRIDGE_STARTED or
BRIDGE_STOPPED (each records the latch, and the locks, as they were then).

Locks are taken up the same way: the locks of the last start or stop, plus the `lock`s and
less the `unlock`s executed after it. A start re-engages them (fail closed: a lock keeps lower
priorities off the base) and records them in its BRIDGE_STARTED entry; one the config no longer
declares is recorded there as released.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec

from rcan_rtps.rcan import Effect
from rcan_rtps.rcan.actions import with_effect

_CHUNK = 64 * 1024
_ENGAGED = ("ESTOP", "ESTOP_REPEATED")
_BOUNDARIES = ("BRIDGE_STARTED", "BRIDGE_STOPPED")


class Resumed(msgspec.Struct):
    """The log's last word: `latched` None when it never spoke of the e-stop."""

    latched: bool | None = None
    latched_by: str | None = None
    locks: dict[str, str] = msgspec.field(default_factory=dict)  # name → who engaged it


def resume(path: Path | str) -> Resumed:
    """Read the log's tail backwards to its last start or stop; a missing log is a first start.

    Entries are trusted as they stand: the log was verified when it was opened.
    """
    seen: list[dict[str, Any]] = []  # newest first, down to the boundary
    try:
        for entry in _backwards(Path(path)):
            seen.append(entry)
            if entry.get("event") in _BOUNDARIES:
                break
    except (OSError, ValueError) as exc:  # it verified at open: this is no time to trust it
        return Resumed(latched=True, latched_by=f"an unreadable audit tail ({exc})")
    found = Resumed()
    for entry in reversed(seen):  # replayed oldest first, from the boundary on
        _apply(found, entry)
    return found


def _apply(state: Resumed, entry: dict[str, Any]) -> None:
    event, action = entry.get("event"), entry.get("action_type")
    given = entry.get("params")
    params: dict[str, Any] = given if isinstance(given, dict) else {}
    if event in _BOUNDARIES:
        latched = params.get("estop_latched")
        if isinstance(latched, bool):
            state.latched = latched
            state.latched_by = "a latched start" if latched else None
        locks = params.get("locks")
        state.locks = dict(locks) if isinstance(locks, dict) else {}
    elif event in _ENGAGED:
        state.latched, state.latched_by = True, entry.get("principal")
    elif event == "ESTOP_CLEARED":
        state.latched, state.latched_by = False, None
    elif event == "COMMAND_FAILED" and action == with_effect(Effect.CLEAR_ESTOP).name:
        # The clear was audited but not persisted (the governor stayed latched).
        state.latched, state.latched_by = True, "a clear that failed"
    elif entry.get("outcome") == "executed":
        _lock_entry(state, entry, action)


def _lock_entry(state: Resumed, entry: dict[str, Any], action: Any) -> None:
    applied = entry.get("applied")
    name = applied.get("name") if isinstance(applied, dict) else None
    if not isinstance(name, str):
        return
    if action == with_effect(Effect.LOCK).name:
        state.locks[name] = str(entry.get("principal"))
    elif action == with_effect(Effect.UNLOCK).name:
        state.locks.pop(name, None)


def _backwards(path: Path) -> Iterator[dict[str, Any]]:
    """Parsed entries from the last line to the first, read in chunks from the end."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return
    try:
        end, tail = os.fstat(fd).st_size, b""
        while end > 0:
            start = max(0, end - _CHUNK)
            block = os.pread(fd, end - start, start) + tail
            end = start
            lines = block.split(b"\n")
            tail = lines.pop(0) if end > 0 else b""  # maybe cut: completed by the next read
            for line in reversed(lines):
                if line.strip():
                    yield json.loads(line)
    finally:
        os.close(fd)
