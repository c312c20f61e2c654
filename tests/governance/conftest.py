"""Shared fixtures of the governance tests: a manual clock and a fresh audit log per test."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from rcan_rtps.governance.audit import AuditLog
from rcan_rtps.governance.clock import ManualClock

RURI = "rcan://registry.local/clearpath/husky/a200-0001"


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


@pytest.fixture
async def audit_log(tmp_path: Path, clock: ManualClock) -> AsyncIterator[AuditLog]:
    log = await AuditLog.open(tmp_path / "audit.jsonl", tmp_path / "audit.key",
                              ruri=RURI, clock=clock)
    yield log
    await log.close()
