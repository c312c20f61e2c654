"""Liveness of `rcan-rtps run`: a stalled event loop is reported, and signals always end it.

`LoopWatchdog` is a thread that expects a heartbeat from the asyncio loop every
`stall_after / 4` s. With none for `stall_after` s it logs the stall once, with every
thread's stack, and logs the recovery when heartbeats resume.

`SignalStopper` blocks SIGINT, SIGTERM and SIGHUP (a closed terminal or ssh session: the
robot must be stopped in order then too) in the calling (main) thread before any other
thread exists, so every later thread inherits the block, and a dedicated thread takes them
with `sigwait`: the first asks the loop to shut down gracefully and, if that has not
finished within `bound` s, logs the stacks and `os._exit`s; a second SIGINT or SIGTERM exits
at once, a second SIGHUP is ignored (a closed terminal sends two). A signal the process was
started ignoring (SIGHUP under `nohup`) stays ignored. These are every command's rules
(`rcan_rtps._stop_signals`); `run` takes the signals on a thread because its loop may be
stuck. As a backstop that needs no GIL, the first signal also arms faulthandler to dump the
stacks and exit a few seconds after the bound.

Whatever a thread later unblocks (multiprocessing's resource tracker unblocks both in the
thread that starts it; the API's audit verifier puts that mask back), a signal the kernel
hands to such a thread is not lost to a default action: the handlers installed here pass it
on to the sigwait thread, so it takes the same path. They are Python handlers, run by the
main thread (through the event loop, which they wake, once one is attached): a backstop that
needs the interpreter. The block is what works with the loop stuck.
"""

from __future__ import annotations

import asyncio
import contextlib
import faulthandler
import linecache
import logging
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable
from types import FrameType

from .. import _stop_signals

log = logging.getLogger(__name__)

DEFAULT_STALL_S = 2.0
DEFAULT_SHUTDOWN_BOUND_S = 10.0
EXIT_STUCK = 1
EXIT_SECOND_SIGNAL = 130


def thread_stacks() -> str:
    """Every Python thread's stack, named, most recent call last."""
    names = {t.ident: t.name for t in threading.enumerate()}
    frames = sys._current_frames()
    me, main = threading.get_ident(), threading.main_thread().ident
    parts = []
    for ident, frame in sorted(frames.items(), key=lambda item: item[0] != main):
        if ident == me:
            continue
        stack = "".join(traceback.format_stack(frame))
        parts.append(f"Thread {names.get(ident, '?')} ({ident}):\n{stack}")
    # The source lines read for the report are not kept: a stall once at start-up would
    # otherwise hold every file on the stacks in memory for good (~1 MB, issue 27).
    linecache.clearcache()
    return "\n".join(parts)


class LoopWatchdog:
    """Detects a stalled asyncio loop from a thread of its own."""

    def __init__(self, loop: asyncio.AbstractEventLoop, stall_after: float = DEFAULT_STALL_S,
                 *, stacks: Callable[[], str] = thread_stacks,
                 clock: Callable[[], float] = time.monotonic) -> None:
        """`clock`: what silence is measured in (tests use one only they advance: a loaded
        machine then cannot stall the loop behind their back)."""
        self.loop = loop
        self.stall_after = stall_after
        self.interval = stall_after / 4
        self.stalls = 0
        self._stacks = stacks
        self._clock = clock
        self._beat = clock()
        self._handle: asyncio.TimerHandle | None = None
        self._stop = threading.Event()
        self._reporting = threading.Event()  # a stall report is being written
        self._thread = threading.Thread(target=self._watch, name="loop-watchdog", daemon=True)

    def start(self) -> None:
        """Call on the loop's thread."""
        self._heartbeat()
        self._thread.start()

    def _heartbeat(self) -> None:
        self._beat = self._clock()
        self._handle = self.loop.call_later(self.interval, self._heartbeat)

    def _watch(self) -> None:
        stalled_at: float | None = None
        while not self._stop.wait(self.interval):
            now, beat = self._clock(), self._beat
            if stalled_at is None and now - beat > self.stall_after:
                stalled_at = beat
                self.stalls += 1
                self._report(now - beat)
            elif stalled_at is not None and beat > stalled_at:
                log.warning("event loop recovered after a %.1f s stall", beat - stalled_at)
                stalled_at = None

    def _report(self, silent_for: float) -> None:
        self._reporting.set()
        try:
            log.error("event loop stalled: no heartbeat for %.1f s; thread stacks:\n%s",
                      silent_for, self._stacks())
        finally:
            self._reporting.clear()

    def stop(self) -> None:
        """Idempotent; call on the loop's thread (or after the loop ended).

        Never waits for a stall report being written: it runs on the loop's thread, inside
        the shutdown's bound, and a report on a loaded machine (every thread's stack, read
        from source files, then logged) once took the 5 s this used to wait, and the
        shutdown past its 10 s. The thread is a daemon; it ends once its report is out.
        Otherwise the thread ends at its next wake-up (within `interval`)."""
        self._stop.set()
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None
        if (self._thread.is_alive() and self._thread is not threading.current_thread()
                and not self._reporting.is_set()):
            self._thread.join(self.interval)


class SignalStopper:
    """SIGINT/SIGTERM/SIGHUP through `sigwait` on a thread of its own; see the module docs.

    Create it on the main thread, before any other thread starts; `finished` when done."""

    def __init__(self, bound: float = DEFAULT_SHUTDOWN_BOUND_S,
                 exit_now: Callable[[int], None] = os._exit) -> None:
        self.bound = bound
        self._exit = exit_now
        self._lock = threading.Lock()
        self._request: Callable[[], None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._pending = False  # a signal came before a loop was attached
        self._done = threading.Event()
        self.received: list[int] = []
        self._signals = _stop_signals.taken()
        # Before any thread starts: threads inherit the mask, so none of them (Cyclone's
        # included) runs a handler for these; only the sigwait below sees them.
        self._old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, self._signals)
        self._thread = threading.Thread(target=self._wait, name="signals", daemon=True)
        self._thread.start()
        # The backstop (module docs). It also keeps asyncio.Runner from installing its own
        # SIGINT handler, which would cancel the main task instead of stopping in order.
        self._old_handlers = {sig: signal.signal(sig, self._forward) for sig in self._signals}

    def attach(self, loop: asyncio.AbstractEventLoop, request_stop: Callable[[], None]) -> None:
        """`request_stop` runs on `loop` when the first signal arrives. Call on the loop's
        (main) thread."""
        with self._lock:
            self._loop, self._request = loop, request_stop
            pending = self._pending
        if pending:
            loop.call_soon_threadsafe(request_stop)
        # The backstop through the loop from here on: a plain Python handler runs only when
        # the main thread next runs Python, and an idle loop may sleep in epoll for long; the
        # loop's own signal handling wakes it. (Closing the loop removes these handlers.)
        for sig in self._signals:
            with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                loop.add_signal_handler(sig, self._forward, sig, None)

    def finished(self) -> None:
        """The graceful shutdown is over: no forced exit any more. Restores the handlers,
        then the mask (a signal still pending then takes its default action)."""
        self._done.set()
        faulthandler.cancel_dump_traceback_later()
        for sig, handler in self._old_handlers.items():
            signal.signal(sig, handler)
        if self.received:  # e.g. a closed terminal's second SIGHUP, still to come: ignored
            _stop_signals.stopped_elsewhere(self.received[0])
        signal.pthread_sigmask(signal.SIG_SETMASK, self._old_mask)

    def _forward(self, signum: int, frame: FrameType | None) -> None:
        """A signal delivered to a thread that did not block it: to the sigwait thread."""
        ident = self._thread.ident
        if ident is not None and self._thread.is_alive():
            with contextlib.suppress(OSError):  # it has just ended: the process is exiting
                signal.pthread_kill(ident, signum)

    def _wait(self) -> None:
        self._first(signal.sigwait(self._signals))
        while not _stop_signals.insists(again := signal.sigwait(self._signals)):
            pass  # SIGHUP again: one closed terminal sends two; the stop goes on
        self._again(again)

    def _first(self, sig: int) -> None:
        self.received.append(sig)
        log.warning("%s: shutting down (a second Ctrl-C or SIGTERM exits at once)",
                    signal.Signals(sig).name)
        # Without the GIL, should Python never run again: dump and exit after the bound.
        faulthandler.dump_traceback_later(self.bound + 5.0, exit=True)
        with self._lock:
            loop, request = self._loop, self._request
            self._pending = request is None
        if loop is not None and request is not None:
            # A RuntimeError: the loop has already closed, so shutdown is under way.
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(request)
        threading.Thread(target=self._bounded, name="signals-bound", daemon=True).start()

    def _bounded(self) -> None:
        if not self._done.wait(self.bound):
            log.error("shutdown did not finish within %.0f s; exiting now. Thread stacks:\n%s",
                      self.bound, thread_stacks())
            logging.shutdown()
            self._exit(EXIT_STUCK)

    def _again(self, sig: int) -> None:
        if self._done.is_set():
            return
        self.received.append(sig)
        log.warning("%s again: exiting now", signal.Signals(sig).name)
        logging.shutdown()
        self._exit(EXIT_SECOND_SIGNAL)
