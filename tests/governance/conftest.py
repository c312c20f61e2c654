"""Fixtures of the governance tests: a manual clock, an audit log, a governor harness."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from govhelpers import RURI, Harness

from rcan_rtps.governance.audit import AuditLog
from rcan_rtps.governance.clock import ManualClock
from rcan_rtps.governance.governor import Governor


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


@pytest.fixture
async def audit_log(tmp_path: Path, clock: ManualClock) -> AsyncIterator[AuditLog]:
    log = await AuditLog.open(tmp_path / "audit.jsonl", tmp_path / "audit.key",
                              ruri=RURI, clock=clock)
    yield log
    await log.close()


@pytest.fixture
async def harness(tmp_path: Path, clock: ManualClock) -> AsyncIterator[Harness]:
    h = Harness(tmp_path, clock)
    yield h
    await h.restart()


@pytest.fixture
async def gov(harness: Harness) -> Governor:
    return await harness.governor()

