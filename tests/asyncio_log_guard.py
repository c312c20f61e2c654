"""The suite fails when asyncio logs an error: "Future exception was never retrieved", "Task
exception was never retrieved", "Task was destroyed but it is pending!", "Exception in
callback …". Each is a failure nobody observed — a bug, whichever test happens to be running.

A handler on the "asyncio" logger, for the whole session, keeps every ERROR record with the
test running when it was emitted. That test is not always the cause: the first two messages
come from a future's finaliser, so they appear when the garbage collector reaches it, possibly
one or more tests later (the guard says "after <test>" between tests). At the session's end
one `gc.collect()` flushes what is still waiting to be collected, then the records are printed
and the session's exit status made non-zero.

The same guard fails the suite when the bridge logs a traceback: a record of an `rcan_rtps`
logger carrying an exception (`log.exception`, `exc_info=`) — a request answered "internal
error", a listener or a check that raised. Bad input gets a clear error, never a traceback in
the log (non-negotiable 4); a test that injects a fault whose traceback the bridge logs on
purpose says so with `@pytest.mark.logs_traceback` (its records, and those that come after
it before the next test starts, are let pass).

Under pytest-xdist a worker's own exit status does not reach the run's (the controller only
looks at it for a keyboard interrupt), so each worker hands its records to the controller in
its `workeroutput`, and the controller prints them and fails the run.
"""

from __future__ import annotations

import gc
import logging
import os
from collections.abc import Generator
from typing import Any

import pytest

# The workeroutput key a worker's records travel under.
WORKEROUTPUT_KEY = "asyncio_log_errors"
# Printed in full up to this many; the rest are counted.
SHOWN = 30
# Set (to anything but "" or "0") to collect garbage after each test's call: a record then
# names the test whose garbage it is (slower: for finding a cause, not for CI).
GC_EACH_TEST = os.environ.get("RCAN_RTPS_ASYNCIO_GC_EACH_TEST", "") not in ("", "0")


class _AsyncioErrorHandler(logging.Handler):
    """Keeps each ERROR-or-worse record of the asyncio logger, formatted, with where the
    session was when it came."""

    def __init__(self, guard: AsyncioLogGuard) -> None:
        super().__init__(level=logging.ERROR)
        self._guard = guard
        self.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = self.format(record)
        except Exception:  # a record that cannot be formatted is still a record
            text = f"{record.levelname} {record.name}: {record.msg!r} (unformattable)"
        self._guard.seen.append({"when": self._guard.where(), "text": text})


class _TracebackHandler(logging.Handler):
    """Keeps each record of ours that carries an exception (a traceback in the bridge's log),
    unless the test running when it came injected that fault on purpose."""

    def __init__(self, guard: AsyncioLogGuard) -> None:
        super().__init__(level=logging.DEBUG)
        self._guard = guard
        self.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        if not record.exc_info or record.exc_info[0] is None or self._guard.traceback_expected():
            return
        try:
            text = self.format(record)
        except Exception:  # a record that cannot be formatted is still a record
            text = f"{record.levelname} {record.name}: {record.msg!r} (unformattable)"
        self._guard.seen.append({"when": self._guard.where(), "text": text})


class AsyncioLogGuard:
    """The plugin (registered by tests/conftest.py in every process of the run)."""

    def __init__(self, config: pytest.Config) -> None:
        self.config = config
        self.seen: list[dict[str, str]] = []
        self._test = "before the first test"
        self._phase = ""
        self._item: pytest.Item | None = None  # the test running, or the last one run
        self._handler = _AsyncioErrorHandler(self)
        logging.getLogger("asyncio").addHandler(self._handler)
        self._tracebacks = _TracebackHandler(self)
        logging.getLogger("rcan_rtps").addHandler(self._tracebacks)

    def traceback_expected(self) -> bool:
        return self._item is not None and \
            self._item.get_closest_marker("logs_traceback") is not None

    def where(self) -> str:
        return f"{self._test} ({self._phase})" if self._phase else self._test

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(self, item: pytest.Item) -> Generator[None, Any, None]:
        self._test, self._item = item.nodeid, item
        yield
        self._test, self._phase = f"after {item.nodeid}", ""

    @pytest.hookimpl(tryfirst=True)
    def pytest_runtest_setup(self) -> None:
        self._phase = "setup"

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_call(self) -> Generator[None, Any, None]:
        self._phase = "call"
        yield
        if GC_EACH_TEST:  # before teardown: its fixtures' loop would cancel what it dropped
            gc.collect()

    @pytest.hookimpl(tryfirst=True)
    def pytest_runtest_teardown(self) -> None:
        self._phase = "teardown"

    def pytest_testnodedown(self, node: Any, error: object) -> None:
        """Controller side: a worker's records (xdist calls this as each worker ends)."""
        output = getattr(node, "workeroutput", None) or {}
        worker = (getattr(node, "workerinput", None) or {}).get("workerid", "worker")
        for record in output.get(WORKEROUTPUT_KEY, ()):
            self.seen.append({"when": f"[{worker}] {record['when']}", "text": record["text"]})

    @pytest.hookimpl(trylast=True)
    def pytest_sessionfinish(self, session: pytest.Session) -> None:
        # What became garbage in the last tests is logged when collected: collect it now.
        self._test, self._phase = "at the session's end (gc.collect)", ""
        gc.collect()
        logging.getLogger("asyncio").removeHandler(self._handler)
        logging.getLogger("rcan_rtps").removeHandler(self._tracebacks)
        workeroutput = getattr(self.config, "workeroutput", None)
        if workeroutput is not None:  # an xdist worker: the controller decides
            workeroutput[WORKEROUTPUT_KEY] = list(self.seen)
            return
        if self.seen and session.exitstatus in (pytest.ExitCode.OK,
                                                pytest.ExitCode.NO_TESTS_COLLECTED):
            session.exitstatus = pytest.ExitCode.TESTS_FAILED

    def pytest_terminal_summary(self, terminalreporter: Any) -> None:
        if not self.seen or hasattr(self.config, "workerinput"):
            return
        terminalreporter.section("asyncio errors and bridge tracebacks logged (each a failure "
                                 "no test observed)",
                                 sep="=", red=True, bold=True)
        terminalreporter.line("The test named is the one running when the record came; a "
                              "future's finaliser logs when the garbage collector reaches it, "
                              "which may be tests after its cause.")
        for record in self.seen[:SHOWN]:
            terminalreporter.line(f"--- {record['when']}")
            terminalreporter.line(record["text"])
        if len(self.seen) > SHOWN:
            terminalreporter.line(f"... and {len(self.seen) - SHOWN} more")
        terminalreporter.line(f"{len(self.seen)} such record(s): the session fails",
                              red=True, bold=True)
