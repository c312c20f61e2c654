"""The files a start opens — the audit signing key, the audit log, the e-stop latch, a `file:`
witness — judged before it opens them, in one list: `run` refuses the first problem before it
joins the domain, `config check` reports them all, so the two cannot disagree about a file.

`config check` also reads an existing log back as the start will (`read_log_back`): `run`
does not here, its start reads the log back itself, under the log's lock (`AuditLog.open`).
"""

from __future__ import annotations

from typing import NamedTuple

from rcan_rtps.config import BridgeConfig, estop_state_file

from .audit import check_key_file, check_log_contents, check_log_file
from .errors import AuditError, AuditKeyError, EstopStateError
from .estop import check_latch_file
from .witness import check_witness_file


class StartFileProblem(NamedTuple):
    """What a start would raise about one file, and the config key that names the file."""

    key: str
    error: Exception

    def __str__(self) -> str:
        return f"{self.key}: {self.error}"


def start_file_problems(bridge: BridgeConfig, *, read_log_back: bool = False,
                        notes: list[str] | None = None) -> list[StartFileProblem]:
    """Every start file's problem, in the order a start meets them. With `read_log_back`, an
    existing log is also read back as the start reads it (read only: beside a running bridge
    too) — unless its key or the log file itself is refused already (it cannot be judged);
    a log too large to read back is added to `notes` instead."""
    audit = bridge.audit
    problems: list[StartFileProblem] = []
    try:
        check_key_file(audit.key_path)
    except AuditKeyError as exc:
        problems.append(StartFileProblem("bridge.audit.key_path", exc))
    try:
        check_log_file(audit.path)
        if read_log_back and not problems:
            note = check_log_contents(audit.path, audit.key_path)
            if note is not None and notes is not None:
                notes.append(note)
    except AuditError as exc:
        problems.append(StartFileProblem("bridge.audit.path", exc))
    try:
        check_latch_file(estop_state_file(bridge))
    except EstopStateError as exc:
        problems.append(StartFileProblem("bridge.safety.estop_state_path", exc))
    try:
        if audit.witness is not None:
            check_witness_file(audit.witness)
    except ValueError as exc:
        problems.append(StartFileProblem("bridge.audit.witness", exc))
    return problems
