"""The e-stop as one serialized state machine: one owner, one order.

E-stop and clear requests are applied one at a time, in arrival order, by one worker task. Each
transition is persisted, audited, published and acknowledged before the next one starts, so the
order of acknowledgements is the audit order. Two rules make an acknowledged e-stop stick:

- an e-stop latches in memory the moment it arrives (before any await), so no motion command
  passes from then on, even while earlier transitions are still being written; unless
  another e-stop is under way or waiting, its work also begins right there (its audit entry
  sealed where it took effect: `EstopLane.estop`), else at its turn; its reply comes in
  order all the same;
- a clear unlatches only if no e-stop arrived after it; otherwise that e-stop keeps the robot
  stopped: one that came before the clear was decided gets it refused (`overtaken`), one
  that came after leaves it audited, publishing nothing.

The latch file fails closed: unreadable means latched, and missing means latched unless the
audit log is new too (a first start).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import inspect
import logging
import os
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any, TypeVar

import msgspec

from ._durable import atomic_write, not_regular_problem, read_small
from .errors import EstopStateError

log = logging.getLogger(__name__)
T = TypeVar("T")


MAX_LATCH_BYTES = 64 * 1024  # a latch file holds a bool, a name and a time: larger is not one


def check_latch_file(path: str | os.PathLike[str]) -> None:
    """Raises EstopStateError if something is at `path` that is no regular file. Loading one
    starts latched (fails closed), but a configured path that is a device or a FIFO is a
    mistake said before the start: `/dev/null` would swallow the latch."""
    problem = not_regular_problem(path)
    if problem is not None:
        raise EstopStateError(f"e-stop state {problem}")


class LatchState(msgspec.Struct, frozen=True, kw_only=True):
    """What `estop.state` holds."""

    latched: bool
    by: str | None = None
    at_ms: int | None = None


class LatchFile:
    """The persisted latch; written atomically (fsynced) on its own thread."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._writer = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="rcan-estop")
        self._found_at_load: bool | None = None

    def load(self, *, first_start: bool) -> tuple[bool, str | None]:
        """(latched, why it starts latched); fails closed on anything but a clear `false`."""
        self._found_at_load = True
        try:
            state = msgspec.json.decode(read_small(self.path, MAX_LATCH_BYTES), type=LatchState)
        except FileNotFoundError:
            self._found_at_load = False
            if first_start:
                return False, None
            return True, f"e-stop state {self.path} is missing: latched until cleared"
        except (OSError, ValueError) as exc:  # (msgspec.DecodeError is one; so is a FIFO)
            return True, f"e-stop state {self.path} is unreadable ({exc}): latched until cleared"
        if state.latched:
            return True, (f"e-stop latched by {state.by or 'unknown'} before this start; "
                          "held until a clear_estop")
        return False, None

    def missing(self) -> bool:
        """No file when it was loaded (the same read decided the latch), or now if never."""
        if self._found_at_load is None:
            return not self.path.exists()
        return not self._found_at_load

    async def write(self, latched: bool, by: str, at_ms: int) -> None:
        """Handed to the one writer thread in the call's first step (no await before), so
        writes land in the order they were called: a clear checks that no e-stop came, then
        writes `false`, in one step; an e-stop's `true` after that lands after it."""
        data = msgspec.json.encode(LatchState(latched=latched, by=by, at_ms=at_ms))
        try:
            await asyncio.get_running_loop().run_in_executor(
                self._writer, atomic_write, self.path, data)
        except OSError as exc:
            raise EstopStateError(f"cannot persist e-stop state to {self.path}: {exc}") from exc

    def close(self) -> None:
        """Idempotent."""
        self._writer.shutdown(wait=True)


# A transition's work (or, begun at once, its awaitable), its caller's future, engage or not.
_Job = tuple[Callable[[], Awaitable[Any]] | Awaitable[Any], "asyncio.Future[Any]", bool]


class EstopMachine:
    """Owns the latch in memory and the order of transitions.

    `engage` and `clear` take the transition's work (persist, audit, publish) as a coroutine
    factory; the machine runs them one at a time in arrival order and returns their results.
    """

    def __init__(self, file: LatchFile, *, latched: bool, reason: str | None = None) -> None:
        self.file = file
        self.reason = reason  # why it started latched, if it did
        self._latched = latched
        self._on_flip: Callable[[], None] | None = None  # the kernel's reflex (`bind`)
        self._engages_waiting = 0
        self._queue: asyncio.Queue[_Job] | None = None
        self._worker: asyncio.Task[None] | None = None
        self._unfinished = 0  # transitions submitted and not done
        self._unfinished_engages = 0  # of them, e-stops
        # E-stops that arrived (repeats while latched included): a clear held for a human
        # since fewer had is refused when approved (`Governor._run_approved`).
        self.arrived = 0

    @property
    def latched(self) -> bool:
        """True from the moment an e-stop arrives until a clear ordered after it completes."""
        return self._latched

    def engage(self, work: Callable[[], Awaitable[T]]) -> asyncio.Future[T]:
        """Latch now (synchronously), then run `work` in order: at once (`work()` called in
        this step) if it latched, or if no other e-stop is unfinished, so what it does before
        its first await happens with the flip: its entry is sealed where the e-stop took
        effect, before any refusal for its latch (a refusal waits for nothing: what latched
        is listed already). A clear under way cannot hold it up: one decided already neither
        unlatches nor publishes after it (`overtaken`), one not yet decided is refused for
        it. Nor can `then` work (recorded repeats), which may itself wait behind a clear.
        One that finds another e-stop unfinished (it latched nothing: that one did, and
        nothing unlatches while an e-stop is in line) waits for its turn, and a flood of them
        is counted as repeats (`EstopLane.estop`), not listed one entry each. Its result is
        returned in order either way."""
        flipped, self._latched = not self._latched, True
        self._engages_waiting += 1
        self.arrived += 1
        if flipped:
            self._tell()
        if self._unfinished_engages and not flipped:
            return self._submit(work, engage=True)
        try:
            begun = work()
        except Exception as exc:  # the caller gets it; the machine goes on
            begun = _raise(exc)
        return self._submit(begun, engage=True)

    def clear(self, work: Callable[[], Awaitable[T]]) -> asyncio.Future[T]:
        """Run `work` in order; it calls `unlatch()` once the clear is durable."""
        return self._submit(work, engage=False)

    def overtaken(self) -> bool:
        """From the clear under way: an e-stop arrived after it (it wins: the clear must not
        unlatch; one arriving before the clear is decided gets the clear refused)."""
        return self._engages_waiting > 0

    def then(self, work: Callable[[], Awaitable[T]]) -> asyncio.Future[T]:
        """Run `work` in order with the transitions, changing nothing of the latch itself.
        An e-stop does not wait for it (`engage`): it must write nothing whose place in the
        log matters against an e-stop's entry (recorded repeats: those of the e-stop holding
        the latch, which a later e-stop only repeats)."""
        return self._submit(work, engage=False)

    def unlatch(self) -> bool:
        """From a clear's work: unlatch unless an e-stop arrived after it (then False)."""
        if self.overtaken():
            return False
        self._latched = False
        self.reason = None
        self._tell()
        return True

    def bind(self, on_flip: Callable[[], None]) -> None:
        """The one reflex to `latched` flipping, called synchronously at the flip (the
        governor's: zero the stream, publish the e-stop Bool, tell STATUS). Set once."""
        if self._on_flip is not None:
            raise RuntimeError("the e-stop latch has its reflex already")
        self._on_flip = on_flip

    def _tell(self) -> None:
        if self._on_flip is None:
            return
        try:
            self._on_flip()
        except Exception:  # never undoes or delays a transition
            log.exception("e-stop reflex failed")

    async def settled(self) -> None:
        """Returns once every transition submitted so far has completed."""
        if self._queue is not None:
            await self._queue.join()

    async def close(self) -> None:
        """Finish every transition already submitted, then stop the worker. Idempotent."""
        if self._queue is not None:
            await self._queue.join()
        worker, self._worker = self._worker, None
        if worker is not None:
            worker.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await worker
        self.file.close()

    def _submit(self, work: Callable[[], Awaitable[T]] | Awaitable[T], *, engage: bool
                ) -> asyncio.Future[T]:
        loop = asyncio.get_running_loop()
        self._unfinished += 1
        self._unfinished_engages += engage
        if self._queue is None:
            self._queue = asyncio.Queue()
        if self._worker is None or self._worker.done():
            self._worker = loop.create_task(self._work(), name="estop-machine")
        done: asyncio.Future[T] = loop.create_future()
        self._queue.put_nowait((work, done, engage))
        return done

    async def _work(self) -> None:
        assert self._queue is not None
        while True:
            work, done, engage = await self._queue.get()
            if engage:
                self._engages_waiting -= 1
            try:
                if inspect.isawaitable(work):
                    result = await work
                else:
                    result = await work()  # an e-stop's first step seals its entry
            except Exception as exc:  # the caller gets it; the machine goes on
                if not done.done():
                    done.set_exception(exc)
            else:
                if not done.done():
                    done.set_result(result)
            finally:
                self._unfinished -= 1
                self._unfinished_engages -= engage
                self._queue.task_done()


async def _raise(exc: Exception) -> Any:
    """Work that failed as it began: its failure, in its turn."""
    raise exc


class Tally(msgspec.Struct, kw_only=True):
    """One principal's e-stops while already latched, since they were last recorded."""

    count: int = 0
    failed: int = 0  # the robot could not be told again
    first_ms: int = 0
    last_ms: int = 0
    # Distinct, at most MAX_WARNINGS: request content, so the entry's `warnings` (held to the
    # log's request bound, `entry_bound`), not its params (`EstopLane.record_repeats`).
    warnings: list[str] = msgspec.field(default_factory=list)


class EstopRepeats:
    """E-stops that arrive while an audited e-stop holds the latch: each is answered and sent
    to the robot again at once, and they are recorded together, one entry per principal (at
    the next clear, at the bridge's stop, or every `every_ms`), so a flood of them cannot fill
    the disk while the robot is already stopped."""

    MAX_WARNINGS = 8

    def __init__(self, every_ms: int = 60_000) -> None:
        self.every_ms = every_ms
        self._tallies: dict[str, Tally] = {}
        # When the oldest tally began, on the monotonic clock: the wall clock's `first_ms`
        # is what the entry says, not how long it has waited (a step back would hold it).
        self._since_mono: float | None = None

    def add(self, principal: str, at_ms: int, *, failed: bool,
            at_mono: float, warnings: tuple[str, ...] = ()) -> None:
        if self._since_mono is None:
            self._since_mono = at_mono
        tally = self._tallies.get(principal)
        if tally is None:
            tally = self._tallies[principal] = Tally(first_ms=at_ms)
        tally.count += 1
        tally.failed += failed
        tally.last_ms = at_ms
        for warning in warnings:
            if warning not in tally.warnings and len(tally.warnings) < self.MAX_WARNINGS:
                tally.warnings.append(warning)

    def due(self, now_mono: float) -> bool:
        """Some tally has waited `every_ms` to be recorded (`now_mono`: monotonic, s)."""
        since = self._since_mono
        return since is not None and (now_mono - since) * 1000 >= self.every_ms

    def take(self) -> dict[str, Tally]:
        taken, self._tallies, self._since_mono = self._tallies, {}, None
        return taken
