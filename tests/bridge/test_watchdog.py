"""The event-loop watchdog of `rcan-rtps run`: one stall report with every stack, then the
recovery. The stall lasts until the report is out, so no timing is asserted. And its signal
stopper's backstop, in a process of its own (it owns the process's signal handling)."""

from __future__ import annotations

import asyncio
import logging
import os
import subprocess
import sys
import threading
import time
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


class _Clock:
    """The watchdog's time, passing only when the test advances it: a loaded machine cannot
    stall the loop behind the test's back (a 0.2 s stall_after on real time once saw a
    second, genuine stall at load 10). Counts the watchdog thread's looks at it, one a check."""

    def __init__(self) -> None:
        self.now = 1000.0
        self.looks = 0
        self._looked = threading.Condition()

    def __call__(self) -> float:
        if threading.current_thread().name == "loop-watchdog":
            with self._looked:
                self.looks += 1
                self._looked.notify_all()
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds

    def looked(self, times: int) -> bool:
        """Wait until the watchdog has checked `times` more times."""
        with self._looked:
            target = self.looks + times
            return self._looked.wait_for(lambda: self.looks >= target, 60)


async def _running(watchdog: LoopWatchdog, clock: _Clock, steps: int) -> None:
    """The loop runs while `steps` heartbeat intervals pass (on the watchdog's clock), each
    checked by the watchdog: never a heartbeat more than an interval behind."""
    for _ in range(steps):
        clock.advance(watchdog.interval)
        while watchdog._beat < clock.now:  # its heartbeat has seen this time
            await asyncio.sleep(watchdog.interval / 4)
        assert await asyncio.to_thread(clock.looked, 1), "the watchdog stopped checking"


def _blocking_the_loop_until_reported(watchdog: LoopWatchdog, clock: _Clock,
                                      records: _Records) -> None:
    """The loop stuck in here while twice `stall_after` passes, until the watchdog reported
    it and then checked three more times, the loop still stuck."""
    clock.advance(2 * watchdog.stall_after)
    assert records.stalled.wait(60), "the watchdog never reported the stall"
    assert clock.looked(3), "the watchdog stopped checking"


def _blocking_the_loop_until(event: threading.Event) -> None:
    assert event.wait(60), "the watchdog never reported the stall"


def _stall_reports(records: _Records) -> list[logging.LogRecord]:
    return [r for r in records.records if "stalled" in r.getMessage()]


async def test_a_stall_is_reported_once_with_stacks_then_the_recovery(records: _Records) -> None:
    clock = _Clock()
    watchdog = LoopWatchdog(asyncio.get_running_loop(), stall_after=0.2, clock=clock)
    watchdog.start()
    try:
        await _running(watchdog, clock, 20)  # heartbeats flow: nothing to report
        assert not records.stalled.is_set()
        _blocking_the_loop_until_reported(watchdog, clock, records)
        stall_reports = _stall_reports(records)
        assert len(stall_reports) == 1 and stall_reports[0].levelno == logging.ERROR
        text = stall_reports[0].getMessage()
        assert "Thread MainThread" in text
        assert "_blocking_the_loop_until_reported" in text  # the stuck frame is named
        assert await asyncio.to_thread(records.recovered.wait, 60)
        assert watchdog.stalls == 1
        # Once recovered it stays quiet while the loop runs.
        await _running(watchdog, clock, 20)
        assert len(_stall_reports(records)) == 1
    finally:
        watchdog.stop()
    watchdog.stop()  # idempotent


async def test_a_second_stall_is_reported_again(records: _Records) -> None:
    clock = _Clock()
    watchdog = LoopWatchdog(asyncio.get_running_loop(), stall_after=0.2, clock=clock)
    watchdog.start()
    try:
        for n in (1, 2):
            _blocking_the_loop_until_reported(watchdog, clock, records)
            assert await asyncio.to_thread(records.recovered.wait, 60)
            assert watchdog.stalls == len(_stall_reports(records)) == n
            records.stalled.clear()
            records.recovered.clear()
            await _running(watchdog, clock, 8)
    finally:
        watchdog.stop()


def _blocked_in_stop(ident: int) -> bool:
    """Whether thread `ident` is inside `LoopWatchdog.stop`, waiting in `threading` (a join)."""
    frame = sys._current_frames().get(ident)
    if frame is None or frame.f_code.co_filename != threading.__file__:
        return False
    while frame is not None:
        if frame.f_code is LoopWatchdog.stop.__code__:
            return True
        frame = frame.f_back
    return False


async def test_stopping_does_not_wait_for_a_slow_stall_report(records: _Records) -> None:
    """The shutdown stops the watchdog on the loop's thread, inside its 10 s bound: a stall
    report still being written (every stack, on a loaded machine) must not hold it. It used
    to be joined for up to 5 s, and one `run` under load exited 1 for it. The report, slow
    until the stop returns or is seen waiting for it, says which happened: no timing."""
    stopping_thread = threading.get_ident()
    in_report, stop_returned = threading.Event(), threading.Event()
    stop_waited: list[bool] = []

    def slow_stacks() -> str:
        in_report.set()
        for _ in range(6000):  # at most a minute: a hang guard, not a measure
            if stop_returned.is_set() or _blocked_in_stop(stopping_thread):
                stop_waited.append(not stop_returned.is_set())
                break
            time.sleep(0.01)
        return "(stacks)"

    watchdog = LoopWatchdog(asyncio.get_running_loop(), stall_after=0.2, stacks=slow_stacks)
    watchdog.start()
    try:
        _blocking_the_loop_until(in_report)  # stalled until its report has begun
        watchdog.stop()  # as the shutdown does, while the report is being written
        stop_returned.set()
        assert await asyncio.to_thread(records.stalled.wait, 60)  # the report still came out
        assert stop_waited == [False], "stop() waited for the stall report"
    finally:
        stop_returned.set()
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


# -- SignalStopper: a signal delivered past the block still stops in order --------------------

_UNBLOCKED_THREAD = """
import asyncio, signal, sys, threading
from rcan_rtps.bridge.watchdog import SignalStopper
from rcan_rtps.cli.run_cmd import run_loop

sig = signal.Signals[sys.argv[1]]
stopper = SignalStopper()


async def main() -> int:
    stop = asyncio.Event()
    stopper.attach(asyncio.get_running_loop(), stop.set)
    ready = threading.Event()

    def careless() -> None:  # what multiprocessing's resource tracker does to its thread
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {sig})
        ready.set()
        threading.Event().wait(60)

    thread = threading.Thread(target=careless, daemon=True)
    thread.start()
    ready.wait()
    signal.pthread_kill(thread.ident, sig)  # the kernel's pick: a thread not blocking it
    await asyncio.wait_for(stop.wait(), 60)
    print("stop requested", flush=True)
    return 0


try:
    code = run_loop(main())
finally:
    stopper.finished()
sys.exit(code)
"""


@pytest.mark.parametrize("loop", ["asyncio", "uvloop"])
@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT", "SIGHUP"])
def test_a_signal_taken_by_a_thread_that_unblocked_it_still_stops_in_order(
        sig: str, loop: str) -> None:
    """The first signal reaches the stopper's graceful path (not SIGTERM's default action,
    not a KeyboardInterrupt) even when some thread has unblocked it and the kernel hands it
    to that thread; the idle loop is woken for it."""
    if loop == "uvloop":
        pytest.importorskip("uvloop")
    env = {**os.environ, "RCAN_RTPS_LOOP": loop}
    done = subprocess.run([sys.executable, "-c", _UNBLOCKED_THREAD, sig], env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, (done.returncode, done.stderr)
    assert "stop requested" in done.stdout
    assert f"{sig}: shutting down" in done.stderr and "Traceback" not in done.stderr
