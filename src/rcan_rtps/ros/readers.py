"""One thread per node reads all of the node's DDS readers; Cyclone's threads never run Python.

Why not a Cyclone listener: cyclonedds-python's `write` (and `take`) keep the GIL while
inside Cyclone. A listener runs Python on Cyclone's receive thread while that thread holds
the reader's locks, so it waits for the GIL there; a `write` from Python that delivers
locally to the same reader then waits for those locks while holding the GIL. Neither
moves, and nothing else in the process does either (issue 9: the bridge froze for good).

Here a `ReaderThread` blocks in `dds_waitset_wait` (a ctypes call: the GIL is released
while it waits) on a WaitSet holding one ReadCondition per reader, the reader itself (its
status mask reduced to REQUESTED_INCOMPATIBLE_QOS), each watched writer (reduced to
OFFERED_INCOMPATIBLE_QOS, plus PUBLICATION_MATCHED for publishers, whose matched count it
keeps) and a GuardCondition that wakes it for attach/detach/close.
It takes the samples and delivers them from *this* thread; owners hop to asyncio with
`loop.call_soon_threadsafe` when they need the loop.

DEADLOCK INVARIANT (keep it): no thread that Cyclone owns ever needs the GIL — no
`Listener`, no `QueryCondition` filter anywhere in this package — and this thread holds no
Cyclone lock while it runs Python (wait, take and status reads return before a callback
runs). So a DDS write from any thread can only wait on Cyclone locks whose holders never
wait for the GIL.

(The binding itself takes the GIL in C in two rare places: comparing two distinct Python
types when a topic is created, and dropping a type whose last entity was deleted, which
Cyclone may do on its garbage-collector thread under its sertype lock. Neither a write nor
a take waits for that lock or that thread, so the invariant holds.)
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

from cyclonedds.core import (
    DDSException,
    DDSStatus,
    GuardCondition,
    InstanceState,
    ReadCondition,
    SampleState,
    ViewState,
    WaitSet,
)
from cyclonedds.internal import dds_infinity
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader

from . import raw_cdr

log = logging.getLogger(__name__)

ANY_SAMPLE = SampleState.Any | ViewState.Any | InstanceState.Any
INCOMPATIBLE_QOS = DDSStatus.RequestedIncompatibleQos
OFFERED_INCOMPATIBLE_QOS = DDSStatus.OfferedIncompatibleQos
PUBLICATION_MATCHED = DDSStatus.PublicationMatched
BATCH = 256  # samples taken per reader per wake-up; the rest stays triggered for the next
REMOVE_WAIT = 10.0  # s `remove` waits for the thread to drop a reader before giving up
BAD_LOG_S = 10.0  # s between two warnings of one reader's undecodable samples

Deliver = Callable[[list[Any]], None]
OnIncompatible = Callable[[Any], None]
Decode = Callable[[bytes], Any]


class Watch:
    """One reader on a `ReaderThread`: `deliver(samples)` gets its valid samples, decoded by
    `decode` (a generated codec; by default the topic type's own, slower one).

    `raw`: `deliver` gets every sample as it was taken — one `(CDR bytes, SampleInfo)` pair a
    call, invalid ones included, undecoded — for a reader whose samples a peer may make of
    any size: the owner looks at each (its size first) before the next is taken, so at most
    one is held here, and the reader keeps none waiting for a later take."""

    def __init__(self, reader: DataReader[Any], deliver: Deliver, label: str,
                 on_incompatible_qos: OnIncompatible | None = None,
                 decode: Decode | None = None, raw: bool = False) -> None:
        self.reader = reader
        self.raw = raw
        self.decode: Decode = decode or reader._topic.data_type.deserialize
        self.deliver = deliver
        self.label = label
        self.on_incompatible_qos = on_incompatible_qos
        self.condition = ReadCondition(reader, ANY_SAMPLE)
        if on_incompatible_qos is not None:
            reader.set_status_mask(INCOMPATIBLE_QOS)  # the reader triggers on this status only
        self.closed = False
        self.bad_samples = 0
        self.bad_logged_at: float | None = None  # monotonic time of the last such warning


class WriterWatch:
    """One writer on a `ReaderThread`: `on_incompatible_qos(status)` hears of readers that
    request what it does not offer (Cyclone reports that only as a status), and
    `on_matched(count)`, if given, of each change in the number of matched readers."""

    def __init__(self, writer: DataWriter[Any], on_incompatible_qos: OnIncompatible,
                 label: str, on_matched: Callable[[int], None] | None = None) -> None:
        self.writer = writer
        self.on_incompatible_qos = on_incompatible_qos
        self.on_matched = on_matched
        self.label = label
        self.mask = OFFERED_INCOMPATIBLE_QOS | (PUBLICATION_MATCHED if on_matched else 0)
        writer.set_status_mask(self.mask)  # it triggers on these statuses only
        self.closed = False


AnyWatch = Watch | WriterWatch
W = TypeVar("W", Watch, WriterWatch)


def take_valid(reader: DataReader[Any], n: int = BATCH,
               watch: Watch | None = None) -> tuple[list[Any], int]:
    """Up to `n` samples taken from `reader`: (the valid, decodable ones, how many were taken).
    Invalid samples (a writer left or disposed) are skipped; a sample that does not decode is
    logged and skipped, never the batch it came in."""
    raw = raw_cdr.take(reader, ANY_SAMPLE, n)
    decode = watch.decode if watch is not None else reader._topic.data_type.deserialize
    valid = []
    for data, info in raw:
        if not info.valid_data:
            continue
        try:
            sample = decode(data)
        except Exception:
            _bad_sample(reader, watch)
            continue
        sample.sample_info = info
        valid.append(sample)
    return valid, len(raw)


def _bad_sample(reader: DataReader[Any], watch: Watch | None) -> None:
    """Counts and logs a sample that does not decode. A peer may send thousands a second:
    a reader logs at most one warning per BAD_LOG_S, with the count so far."""
    if watch is None:
        log.warning("%s: dropped a sample that does not decode", reader,
                    exc_info=log.isEnabledFor(logging.DEBUG))
        return
    watch.bad_samples += 1
    now = time.monotonic()
    if watch.bad_logged_at is not None and now - watch.bad_logged_at < BAD_LOG_S:
        return
    watch.bad_logged_at = now
    log.warning("%s: dropped a sample that does not decode (%d so far; logged at most every "
                "%.0f s)", watch.label, watch.bad_samples, BAD_LOG_S,
                exc_info=log.isEnabledFor(logging.DEBUG))


class ReaderThread:
    """Waits for data on any number of readers of one participant and delivers it."""

    def __init__(self, participant: Any, name: str) -> None:
        self.name = name
        self._participant = participant
        self._lock = threading.Lock()
        self._watches: list[AnyWatch] = []
        self._attach: list[AnyWatch] = []
        self._detach: list[tuple[AnyWatch, threading.Event]] = []
        self._after_pass: list[Callable[[], None]] = []
        self._closing = False
        self._thread: threading.Thread | None = None
        self._waitset: WaitSet | None = None
        self._guard: GuardCondition | None = None
        self.errors = 0  # callbacks that raised

    # -- any thread ---------------------------------------------------------------------
    def add(self, watch: W) -> W:
        with self._lock:
            if self._closing:
                raise DDSException(-9, f"{self.name} is closed")  # ALREADY_DELETED
            if self._thread is None:
                # DDS calls under our lock, the one place: making a waitset and a guard
                # condition invokes no listener (nothing calls back into Python), and no
                # Cyclone thread ever takes this lock, so no wait cycle can run through it.
                self._waitset = WaitSet(self._participant)
                self._guard = GuardCondition(self._participant)
                self._waitset.attach(self._guard)
                self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
                self._thread.start()
            self._attach.append(watch)
        self._wake()
        return watch

    def remove(self, watch: AnyWatch, wait: bool = True) -> None:
        """Stops deliveries to `watch`: none starts after this returns (unless the thread
        itself is stuck in a callback for more than REMOVE_WAIT). `wait=False`: returns at
        once, for a watch whose late deliveries do no harm (the thread drops it at its next
        pass, and none starts after a delivery in flight)."""
        if watch.closed:
            return
        watch.closed = True
        done = threading.Event()
        with self._lock:
            running = self._thread is not None and not self._closing
            if running:
                self._detach.append((watch, done))
        if not running:
            return
        self._wake()
        if wait and threading.current_thread() is not self._thread and \
                not done.wait(REMOVE_WAIT):
            log.warning("%s: still busy after %.0f s; %s detached late", self.name,
                        REMOVE_WAIT, watch.label)

    def after_next_pass(self, done: Callable[[], None]) -> None:
        """Calls `done()` on this thread once every reader has been serviced in a pass that
        starts after this call: whatever any reader held now (and every sample delivered in
        the pass running now) has been delivered before `done` runs. If the thread is not
        running, `done()` is called at once (there is nothing to deliver)."""
        with self._lock:
            running = self._thread is not None and not self._closing
            if running:
                self._after_pass.append(done)
        if not running:
            done()
            return
        self._wake()

    def close(self) -> None:
        """Stops the thread and releases its conditions (idempotent). Callbacks in flight
        finish first; none starts afterwards."""
        with self._lock:
            if self._closing:
                thread = None
            else:
                self._closing = True
                thread = self._thread
        if thread is None:
            return
        self._wake()
        if thread is not threading.current_thread():
            thread.join(REMOVE_WAIT)
            if thread.is_alive():
                log.warning("%s did not stop within %.0f s", self.name, REMOVE_WAIT)

    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _wake(self) -> None:
        guard = self._guard
        if guard is not None:
            # ctypes: releases the GIL; takes only the waitset's lock. A DDSException: the
            # participant is gone, and the thread is leaving too.
            with contextlib.suppress(DDSException):
                guard.set(True)

    # -- the thread ---------------------------------------------------------------------
    def _run(self) -> None:
        assert self._waitset is not None and self._guard is not None
        waitset, guard = self._waitset, self._guard
        try:
            while True:
                guard.take()  # before the changes: a wake-up after this is not lost
                with self._lock:
                    after_pass, self._after_pass = self._after_pass, []
                if not self._apply_changes(waitset):
                    for call in after_pass:
                        self._call_plain(call)
                    return
                for watch in list(self._watches):
                    if not watch.closed:
                        self._service(watch)
                for call in after_pass:
                    self._call_plain(call)
                # The GIL is released while this waits (ctypes).
                waitset.wait(dds_infinity)
        except DDSException as exc:  # the participant was deleted under us
            log.debug("%s: leaving: %s", self.name, exc)
        except Exception:
            log.exception("%s: reader thread failed", self.name)
        finally:
            self._cleanup(waitset, guard)

    def _apply_changes(self, waitset: WaitSet) -> bool:
        with self._lock:
            attach, self._attach = self._attach, []
            detach, self._detach = self._detach, []
            closing = self._closing
        for watch in attach:
            if watch.closed:
                continue
            for entity in _entities(watch):
                waitset.attach(entity)
            self._watches.append(watch)
        for watch, done in detach:
            self._drop(waitset, watch)
            done.set()
        return not closing

    def _drop(self, waitset: WaitSet, watch: AnyWatch) -> None:
        if watch in self._watches:
            self._watches.remove(watch)
        for entity in _entities(watch):
            with contextlib.suppress(DDSException):
                waitset.detach(entity)
        if isinstance(watch, Watch):
            with contextlib.suppress(DDSException):
                watch.condition.__del__()  # dds_delete now, not whenever Python collects it

    def _service(self, watch: AnyWatch) -> None:
        if isinstance(watch, WriterWatch):
            self._service_writer(watch)
        else:
            self._service_reader(watch)

    def _service_writer(self, watch: WriterWatch) -> None:
        try:
            changed = watch.writer.take_status(watch.mask)
            matched = watch.writer.get_publication_matched_status().current_count \
                if changed & PUBLICATION_MATCHED else None
            incompatible = watch.writer.get_offered_incompatible_qos_status() \
                if changed & OFFERED_INCOMPATIBLE_QOS else None
        except DDSException:  # the writer was deleted under us (its owner closed it)
            watch.closed = True
            return
        if matched is not None and watch.on_matched is not None:
            self._call(watch, watch.on_matched, int(matched))
        if incompatible is not None:
            self._call(watch, watch.on_incompatible_qos, incompatible)

    def _service_reader(self, watch: Watch) -> None:
        try:
            if watch.on_incompatible_qos is not None and \
                    watch.reader.take_status(INCOMPATIBLE_QOS) & INCOMPATIBLE_QOS:
                status = watch.reader.get_requested_incompatible_qos_status()
                self._call(watch, watch.on_incompatible_qos, status)
            if not watch.condition.triggered:
                return
            if watch.raw:
                self._service_raw(watch)
                return
            samples, _taken = take_valid(watch.reader, BATCH, watch)
        except DDSException:  # the reader was deleted under us (its owner closed it)
            if not watch.closed:
                log.debug("%s: reader gone", watch.label, exc_info=True)
            watch.closed = True
            return
        except Exception:  # never let one reader end the thread that serves them all
            self.errors += 1
            log.exception("%s: taking samples failed", watch.label)
            return
        if samples and not watch.closed:
            self._call(watch, watch.deliver, samples)

    def _service_raw(self, watch: Watch) -> None:
        """Up to BATCH samples, taken and delivered one at a time (see `Watch`)."""
        for _ in range(BATCH):
            taken = raw_cdr.take(watch.reader, ANY_SAMPLE, 1)
            if not taken or watch.closed:
                return
            self._call(watch, watch.deliver, taken)
            del taken  # (before the next is taken)

    def _call(self, watch: AnyWatch, fn: Callable[[Any], None], arg: Any) -> None:
        try:
            fn(arg)
        except Exception:  # one bad delivery must not silence the reader, nor the others
            self.errors += 1
            log.exception("%s: delivery failed", watch.label)

    def _call_plain(self, fn: Callable[[], None]) -> None:
        try:
            fn()
        except Exception:
            self.errors += 1
            log.exception("%s: an after-pass callback failed", self.name)

    def _cleanup(self, waitset: WaitSet, guard: GuardCondition) -> None:
        with self._lock:
            self._closing = True
            pending, self._detach = self._detach, []
            after_pass, self._after_pass = self._after_pass, []
            self._attach = []
        for call in after_pass:
            self._call_plain(call)
        for watch in list(self._watches):
            watch.closed = True
            self._drop(waitset, watch)
        for _, done in pending:
            done.set()
        for entity in (waitset, guard):
            with contextlib.suppress(DDSException):
                entity.__del__()


def _entities(watch: AnyWatch) -> list[Any]:
    """What `watch` puts on the WaitSet."""
    if isinstance(watch, WriterWatch):
        return [watch.writer]
    if watch.on_incompatible_qos is not None:
        return [watch.condition, watch.reader]
    return [watch.condition]
