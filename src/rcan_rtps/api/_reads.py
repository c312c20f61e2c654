"""The costly reads (GET /api/audit, GET /api/audit/verify), kept off the event loop and away
from the audit writer, with bounded concurrency.

- Never the default executor: the audit log writes and fsyncs through `asyncio.to_thread`, so a
  pool full of reads would hold every command's reply (an e-stop's too) behind them.
- Pages: at most `limit` entries, and no more than `max_bytes` of them (`PAGE_BYTES`) unless
  one entry alone is larger (then it is the page: paging goes on by `since` either way). An
  entry holds a command's params as requested, and a stop's body is taken up to 4× the body
  limit (`_intake.STOP_ROOM`; that limit may be 16 MiB): a thousand such entries made a page
  of gigabytes. One dedicated reader thread; at most `backlog` pages wait for it, beyond that the
  caller answers 429 RATE_LIMITED `reads_busy` (with Retry-After). A page is read a chunk
  at a time from a line found by halving the file (`_first_after`): it holds the page, never
  the log, and a page deep in a long log reads a few blocks to get there.
  A line that is not an entry (edited or damaged on disk while the bridge runs) raises
  AuditUnreadable, answered 503: reads never verify, but they never fail on what they find.
- Verification is CPU-bound Python (decode, canonical re-encode, SHA-256, Ed25519 per entry):
  in a thread it would fight the event loop for the GIL. It runs in one spawned worker process
  at lowered priority (the robot's commands come first on a small CPU). One run at a time;
  concurrent requests coalesce. A request joins the run that has not started reading the file
  yet, or queues the next one, so every answer covers at least every entry that was durable
  when the request arrived. Waiting is bounded by one run in progress plus one queued, however
  many ask, so verify requests are never refused. Where no process can be started, the reader
  thread verifies instead (logged once).
- Starting that process leaves the signal mask of the thread that starts it as it was:
  multiprocessing's resource tracker unblocks SIGINT and SIGTERM there, and `rcan-rtps run`
  keeps them blocked in every thread (one thread takes them with sigwait and stops the robot
  in order; a SIGTERM delivered anywhere else would kill the bridge on the spot). The worker
  itself ignores SIGINT and SIGHUP (a Ctrl-C or a hangup reaches the whole process group;
  the bridge ends the worker) and takes SIGTERM, which is how the bridge ends it.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import logging
import os
import signal
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import msgspec
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from rcan_rtps.governance.log_tail import lines_forwards, next_newline

from ._bodies import VerifyReport
from ._errors import AuditUnreadable, ReadsBusy

log = logging.getLogger(__name__)
_NICE = 10  # verification yields the CPU to the bridge
T = TypeVar("T")
_SCAN_BELOW = 256 * 1024  # a page's search stops halving here and reads on
PAGE_BYTES = 4 * 1024 * 1024  # a page's entries, together (one larger entry is a page alone)


class _Seq(msgspec.Struct):
    seq: int


_SEQ = msgspec.json.Decoder(_Seq)


class _Who(msgspec.Struct):
    seq: int
    principal: str | None = None


_WHO = msgspec.json.Decoder(_Who)


def decoded(decoder: msgspec.json.Decoder[T], line: bytes) -> T:
    """`decoder.decode(line)`; raises AuditUnreadable for a line that is not such an entry
    (msgspec raises RecursionError, not DecodeError, for a value nested thousands deep)."""
    try:
        return decoder.decode(line)
    except (msgspec.DecodeError, RecursionError) as exc:
        raise AuditUnreadable(AuditUnreadable.REASON) from exc


def entries_after(path: Path, since: int, limit: int,
                  max_bytes: int = PAGE_BYTES) -> list[bytes]:
    """The first entries with seq > since: at most `limit`, and `max_bytes` together unless
    the first alone is larger."""
    return _first(_lines_after(path, since), limit, max_bytes)


def entries_of(path: Path, principal: str, since: int, limit: int, last: bool,
               max_bytes: int = PAGE_BYTES) -> list[bytes]:
    """One principal's entries with seq > since: the first `limit`, or with `last` the newest
    `limit` (a whole scan: the log has no index by principal); `max_bytes` together unless
    one alone is larger (with `last`, the newest that fit)."""
    lines = (line for line in _lines_after(path, since)
             if decoded(_WHO, line).principal == principal)
    return _newest(lines, limit, max_bytes) if last else _first(lines, limit, max_bytes)


def _first(lines: Iterator[bytes], limit: int, max_bytes: int) -> list[bytes]:
    """The first lines, up to `limit` and `max_bytes` (at least one: paging must move on)."""
    found: list[bytes] = []
    size = 0
    for line in lines:
        size += len(line)
        if found and size > max_bytes:
            break
        found.append(line)
        if len(found) == limit:
            break
    return found


def _newest(lines: Iterator[bytes], limit: int, max_bytes: int) -> list[bytes]:
    """The last lines, up to `limit` and `max_bytes` (at least the last one)."""
    found: collections.deque[bytes] = collections.deque(maxlen=limit)
    size = 0
    for line in lines:
        if len(found) == limit:
            size -= len(found[0])  # (the deque drops it)
        found.append(line)
        size += len(line)
        while size > max_bytes and len(found) > 1:
            size -= len(found.popleft())
    return list(found)


def _lines_after(path: Path, since: int) -> Iterator[bytes]:
    """The log's complete lines (one being appended right now is not one yet) of the entries
    with seq > since, read a chunk at a time. Before, each page read the whole log into
    memory twice (the file, then its lines): a month-long log of 700 MB took 1.4 GB a page."""
    with open(path, "rb") as file:
        fd = file.fileno()
        size = os.fstat(fd).st_size
        for _, line in lines_forwards(fd, _first_after(fd, size, since), size):
            if decoded(_SEQ, line).seq > since:
                yield line


def _first_after(fd: int, size: int, since: int) -> int:
    """A line's start at or before the first line with seq > since, found by halving the file
    (seqs grow line by line: the writer appends them in order, and opening the log verified
    it): a page deep in a long log reads a few blocks to get there, not the log."""
    low, high = 0, size  # low: a line's start; the lines before it have seq <= since
    while high - low > _SCAN_BELOW:
        newline = next_newline(fd, (low + high) // 2, high)
        if newline is None or newline + 1 >= high:
            break  # one line spans the middle: scanned from low
        start = newline + 1
        end = next_newline(fd, start, size)
        if end is None:  # an unterminated tail: not an entry yet
            break
        try:
            seq = decoded(_SEQ, os.pread(fd, end - start, start)).seq
        except AuditUnreadable:  # read on from low: only a line a page reaches refuses it
            break
        if seq <= since:
            low = start
        else:
            high = start
    return low


def line_seq(line: bytes) -> int:
    return decoded(_SEQ, line).seq


def last_line(path: Path, block: int = 4096) -> bytes | None:
    """The last complete line of a file (without its newline), read from the end; None if
    the file is missing or holds no complete line."""
    try:
        with path.open("rb") as file:
            end = file.seek(0, os.SEEK_END)
            tail, start = b"", end
            while start > 0:
                start = max(0, start - block)
                file.seek(start)
                tail = file.read(end - start)
                body = tail[: tail.rfind(b"\n") + 1]  # a line being appended is not one yet
                if body.count(b"\n") >= 2 or (start == 0 and body):
                    return body[:-1].rsplit(b"\n", 1)[-1]
    except FileNotFoundError:
        return None
    return None


def verify_file(path: str, public_key: bytes) -> VerifyReport:
    """Chain, signatures, tree heads and start-up checkpoint of what is on disk, as
    `rcan-rtps audit verify` checks them, a line at a time (runs in the worker process: the
    log of a long run is never held)."""
    # Imported here, in the worker process: the bridge itself never checks its whole log.
    from rcan_rtps.governance.logcheck import check_log

    key = Ed25519PublicKey.from_public_bytes(public_key)
    report = check_log(Path(path), key, live=True)
    newest = report.newest.tree_size if report.newest is not None else None
    return VerifyReport(
        ok=report.ok, count=report.entries, last_seq=report.entries,
        last_audit_id=report.last_audit_id, bad_seq=report.bad_seq,
        detail=report.problems[0] if report.problems else None,
        tree_heads=report.heads, tree_size=newest, problems=report.problems or None)


def _worker_start() -> None:
    """In the worker process: below the bridge's priority; SIGINT and SIGHUP ignored (they
    reach the whole process group: the bridge ends the worker), SIGTERM taken (the worker
    inherits whatever mask the thread that spawned it had)."""
    with contextlib.suppress(OSError, AttributeError):
        os.nice(_NICE)
    for ignored in (signal.SIGINT, signal.SIGHUP):
        signal.signal(ignored, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM, signal.SIGHUP})


@contextlib.contextmanager
def keep_signal_mask() -> Iterator[None]:
    """The calling thread's signal mask as it was once the block is done, whatever the block
    did to it: multiprocessing's resource tracker, when it starts, blocks SIGINT and SIGTERM
    around its spawn and then *unblocks* them instead of restoring the mask."""
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, ())
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


class AuditReads:
    """The audit reads of one app; `close` on app cleanup."""

    def __init__(self, path: Path, public_key: Ed25519PublicKey, *, backlog: int = 8,
                 page_bytes: int = PAGE_BYTES) -> None:
        self._path = path
        self.page_bytes = page_bytes
        self._key = public_key.public_bytes_raw()
        self._thread = concurrent.futures.ThreadPoolExecutor(
            1, thread_name_prefix="rcan-audit-read")
        self._page_room = 1 + backlog  # the one being read, and those waiting
        self._pages = 0
        self._process: concurrent.futures.ProcessPoolExecutor | None = None
        self._no_process = False
        self._current: asyncio.Future[Any] | None = None  # reading the file now
        self._queued: asyncio.Task[VerifyReport] | None = None  # starts after _current
        self.runs = 0  # verification runs started (coalescing shows as fewer runs than asks)

    @property
    def verifying(self) -> bool:
        """A verification run is reading the log right now."""
        return self._current is not None

    @property
    def pages_in_flight(self) -> int:
        """Pages being read or waiting for the reader thread."""
        return self._pages

    async def read(self, fn: Callable[..., T], *args: Any) -> T:
        """`fn(*args)` on the reader thread, among the pages (raises ReadsBusy beyond the
        backlog): audit exports read their chunks and the safety manifest its tails here."""
        if self._pages >= self._page_room:
            raise ReadsBusy
        self._pages += 1
        try:
            return await asyncio.get_running_loop().run_in_executor(self._thread, fn, *args)
        finally:
            self._pages -= 1

    async def page(self, since: int, limit: int) -> list[bytes] | None:
        """Entries with seq > since (at most `limit`, and `page_bytes`: `entries_after`), or
        None when too many pages wait."""
        if self._pages >= self._page_room:
            return None
        self._pages += 1
        try:
            loop = asyncio.get_running_loop()
            return await loop.run_in_executor(self._thread, entries_after, self._path, since,
                                              limit, self.page_bytes)
        finally:
            self._pages -= 1

    async def verify(self) -> VerifyReport:
        """A verification that started reading after this call: joined, queued or new."""
        if self._queued is None:
            self._queued = asyncio.create_task(self._run(self._current))
        # Shielded: a caller that goes away must not cancel the run others wait for.
        return await asyncio.shield(self._queued)

    async def _run(self, previous: asyncio.Future[Any] | None) -> VerifyReport:
        if previous is not None:
            await asyncio.wait([previous])  # its outcome is its callers' business
        # From here this run reads the file: later callers must queue a new one.
        me = asyncio.current_task()
        self._queued, self._current = None, me
        self.runs += 1
        try:
            return await self._verify_once()
        except concurrent.futures.BrokenExecutor:  # the worker died (OOM, killed): again
            log.warning("audit verifier process died; starting a new one")
            self._drop_process()
            return await self._verify_once()
        finally:
            if self._current is me:
                self._current = None

    async def _verify_once(self) -> VerifyReport:
        pool = self._verifier()
        path = str(self._path)
        try:
            with keep_signal_mask():  # starts the worker (and the resource tracker) if need be
                future = pool.submit(verify_file, path, self._key)
        except OSError:  # no worker process can be started here
            if pool is self._thread:
                raise
            log.warning("cannot start an audit verifier process; using a thread",
                        exc_info=True)
            self._no_process = True
            self._drop_process()
            future = self._thread.submit(verify_file, path, self._key)
        return await asyncio.wrap_future(future)

    def _verifier(self) -> concurrent.futures.Executor:
        if self._process is None and not self._no_process:
            import multiprocessing  # here: a bridge that never verifies never loads it

            try:
                with keep_signal_mask():  # its queues' semaphores start the resource tracker
                    self._process = concurrent.futures.ProcessPoolExecutor(
                        1, mp_context=multiprocessing.get_context("spawn"),
                        initializer=_worker_start)
            except (OSError, NotImplementedError, ValueError):  # e.g. no POSIX semaphores
                log.warning("no process for audit verification; using a thread",
                            exc_info=True)
                self._no_process = True
        return self._process or self._thread

    def _drop_process(self, *, stop_running: bool = False) -> None:
        process, self._process = self._process, None
        if process is None:
            return
        # The executor keeps no public handle on its worker (3.14 adds terminate_workers).
        workers = list(getattr(process, "_processes", {}).values()) if stop_running else []
        process.shutdown(wait=False, cancel_futures=True)
        for worker in workers:
            worker.terminate()

    async def close(self) -> None:
        """Stop both workers. A verification in progress is stopped too: at exit Python waits
        for a pool's running task, and a long log's verification (a minute, at low priority on
        a busy robot) must not hold the bridge's shutdown."""
        self._drop_process(stop_running=True)
        self._thread.shutdown(wait=False, cancel_futures=True)
