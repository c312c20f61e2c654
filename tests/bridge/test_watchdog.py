"""The event-loop watchdog of `rcan-rtps run`: one stall report with every stack, then the
recovery. The stall lasts until the report is out, so no timing is asserted."""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Iterator

import pytest

from rcan_rtps.bridge.watchdog import LoopWatchdog, thread_stacks


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []
        self.stalled = threading.Event()
        self.recovered = threading.Event()

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)
        message = record.getMessage()
        if "stalled" in message:
            self.stalled.set()
        if "recovered" in message:
            self.recovered.set()


@pytest.fixture
def records() -> Iterator[_Records]:
    handler = _Records()
    logger = logging.getLogger("rcan_rtps.bridge.watchdog")
    logger.addHandler(handler)
    yield handler
    logger.removeHandler(handler)


def _blocking_the_loop_until(event: threading.Event) -> None:
    assert event.wait(60), "the watchdog never reported the stall"


async def test_a_stall_is_reported_once_with_stacks_then_the_recovery(records: _Records) -> None:
    loop = asyncio.get_running_loop()
    watchdog = LoopWatchdog(loop, stall_after=0.2)
    watchdog.start()
    try:
        await asyncio.sleep(0.5)  # heartbeats flow: nothing to report
        assert not records.stalled.is_set()
        _blocking_the_loop_until(records.stalled)  # the loop is stuck in here
        stall_reports = [r for r in records.records if "stalled" in r.getMessage()]
        assert len(stall_reports) == 1 and stall_reports[0].levelno == logging.ERROR
        text = stall_reports[0].getMessage()
        assert "Thread MainThread" in text
        assert "_blocking_the_loop_until" in text  # the stuck frame is named
        assert await asyncio.to_thread(records.recovered.wait, 60)
        assert watchdog.stalls == 1
        # Once recovered it stays quiet while the loop runs.
        await asyncio.sleep(0.5)
        assert len([r for r in records.records if "stalled" in r.getMessage()]) == 1
    finally:
        watchdog.stop()
    watchdog.stop()  # idempotent


async def test_a_second_stall_is_reported_again(records: _Records) -> None:
    loop = asyncio.get_running_loop()
    watchdog = LoopWatchdog(loop, stall_after=0.2)
    watchdog.start()
    try:
        for n in (1, 2):
            _blocking_the_loop_until(records.stalled)
            assert await asyncio.to_thread(records.recovered.wait, 60)
            assert watchdog.stalls == n
            records.stalled.clear()
            records.recovered.clear()
    finally:
        watchdog.stop()


def test_thread_stacks_name_every_other_thread() -> None:
    release = threading.Event()
    worker = threading.Thread(target=release.wait, name="parked-worker", daemon=True)
    worker.start()
    try:
        text = thread_stacks()
        assert "Thread parked-worker" in text and "in wait" in text
    finally:
        release.set()
        worker.join()
