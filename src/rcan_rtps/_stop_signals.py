"""How a command ends on a stop signal: SIGINT (Ctrl-C), SIGTERM (a supervisor) and SIGHUP
(its terminal or ssh session closed) all alike, in order, nothing left half-done.

- `stop_rules()`: around the whole command line; the rules below apply within it.
- `run(main)`: `asyncio.run` for a command. The first stop signal cancels `main`: its `with`
  blocks and `finally`s unwind (its DDS participant deleted, files complete), then
  `KeyboardInterrupt` (`stopped`), which the command line turns into exit status 128 + the
  signal (`exit_status`), as a shell reports a signal's end.
- `taking_over(react)`: within it, the first stop signal calls `react(signal)` instead, and
  the command ends its own way (`sim` stops its robot, `bag record` closes its bag, `action
  send_goal` cancels its goal, `mcp` stops the motion its agent started).

After the first, a SIGHUP is ignored: a closed terminal sends its foreground job two (its
shell hangs up its jobs, then the kernel hangs up the foreground group as the shell, the
session leader, exits), and the ordered end must be let finish. A SIGINT or SIGTERM then is
someone insisting: the kernel's default action ends the process at once. A SIGHUP ignored
when the process started stays ignored: `nohup rcan-rtps …` outlives its terminal, as nohup
promises. A SIGINT ignored at start is still a stop: a non-interactive shell starts its
background jobs (`cmd &`) so, and a script stops them with `kill -INT`. Before a command's
loop runs (the command line loading), SIGTERM and SIGHUP take their default action: nothing
has started, and an exception thrown into whatever Python runs then (imports, logging's
locks) is no safer than Ctrl-C's there.

`rcan-rtps run` takes the same signals on a `sigwait` thread of its own, which works with
its event loop stuck (`bridge.watchdog.SignalStopper`), by the same rules: `taken()`,
`insists()`.
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
import threading
from collections.abc import Callable, Coroutine, Iterator
from typing import Any, TypeVar

T = TypeVar("T")
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
RECANCEL_S = 1.0  # s between cancellations of a command that runs on after one (`_cancel`)
# Read when first imported, before anything of ours replaces a handler (`cli.main` imports
# this first): whether the process was started with SIGHUP ignored (`nohup`). Only SIGHUP: a
# non-interactive shell starts its background jobs (`cmd &`) with SIGINT ignored, and a
# script stops such a job with `kill -INT`; a stop asked for is a stop.
_IGNORED_AT_START = frozenset(sig for sig in (signal.SIGHUP,)
                              if signal.getsignal(sig) is signal.SIG_IGN)


def stopped(signum: int) -> KeyboardInterrupt:
    """What a stop signal raises: a Ctrl-C's exception (so everything that handles one
    handles it), naming the signal."""
    return KeyboardInterrupt(signal.Signals(signum))


def exit_status(interrupt: KeyboardInterrupt) -> int:
    """128 + the signal that raised `interrupt` (a plain Ctrl-C: SIGINT), as a shell reports
    a signal's end."""
    named = interrupt.args[0] if interrupt.args else None
    return 128 + (named if isinstance(named, signal.Signals) else signal.SIGINT)


def taken() -> tuple[signal.Signals, ...]:
    """The stop signals this process takes: all but a SIGHUP it was started ignoring."""
    return tuple(sig for sig in STOP_SIGNALS if sig not in _IGNORED_AT_START)


def insists(again: int) -> bool:
    """Whether a stop signal arriving during the ordered end asks to end it at once: not a
    SIGHUP (one closed terminal sends two)."""
    return again != signal.SIGHUP


class _Stopping:
    """The process's one record of stop signals: which came first, and who reacts to it (the
    innermost `run` or `taking_over`)."""

    def __init__(self, *, handling: bool = False) -> None:
        self.received: int | None = None
        self.reactions: list[Callable[[int], object]] = []
        self.handling = handling  # within `stop_rules`: the handlers are ours to set

    def first(self, sig: int) -> None:
        self.received = sig
        if self.handling:
            _after_the_first()
        self.reactions[-1](sig)


_stopping = _Stopping()


def stopped_elsewhere(sig: int) -> None:
    """A stop signal another taker received (`run`'s sigwait thread), handled there: from
    now on, the rules for signals after the first."""
    _stopping.received = sig
    if _stopping.handling:
        _after_the_first()


def _after_the_first() -> None:
    """SIGHUP ignored, SIGINT and SIGTERM ending the process at once, in the kernel: so even
    with the main thread stuck in C."""
    for sig in taken():
        signal.signal(sig, signal.SIG_IGN if not insists(sig) else signal.SIG_DFL)


@contextlib.contextmanager
def stop_rules() -> Iterator[None]:
    """Within: the module's rules for signals after the first apply; the handlers found are
    put back after. Off the main thread (a program calling the command line from a thread of
    its own) nothing is set: Python lets only the main thread take signals."""
    global _stopping
    if not _on_main_thread():
        _stopping = _Stopping()
        yield
        return
    _stopping = _Stopping(handling=True)
    before = {sig: signal.getsignal(sig) for sig in taken()}
    try:
        yield
    finally:
        _stopping.handling = False
        for sig, handler in before.items():
            signal.signal(sig, handler)


def run(main: Coroutine[Any, Any, T]) -> T:
    """`main` on a new event loop; the first stop signal cancels it, then raises
    `KeyboardInterrupt` (`stopped`)."""
    try:
        finished = asyncio.run(_until_stopped(main))
    finally:
        _outside_the_loop()
    if finished is None:
        assert _stopping.received is not None
        raise stopped(_stopping.received)
    return finished[0]


async def _until_stopped(main: Coroutine[Any, Any, T]) -> tuple[T] | None:
    """What `main` returned; None if a stop signal cancelled it."""
    task = asyncio.current_task()
    assert task is not None
    with _on_the_loop(lambda sig: _cancel(task)):
        try:
            return (await main,)
        except asyncio.CancelledError:
            if _stopping.received is None:
                raise
            return None


def _cancel(task: asyncio.Task[Any]) -> None:
    """Cancels `task`, and again each RECANCEL_S while it runs on: Python 3.11's wait_for
    drops a cancellation that lands as what it waits for completes (python/cpython#86296),
    and `topic echo` then went on reading for good (1 in ~40 stops under load)."""
    if not task.done():
        task.cancel()
        asyncio.get_running_loop().call_later(RECANCEL_S, _cancel, task)


@contextlib.contextmanager
def taking_over(react: Callable[[int], object]) -> Iterator[_Stopping]:
    """Within (on the loop of `run`): the first stop signal calls `react(signal)`, once; a
    signal already received calls it at once. Yields the record: `received` says which."""
    with _on_the_loop(react):
        if _stopping.received is not None:
            react(_stopping.received)
        yield _stopping


@contextlib.contextmanager
def _on_the_loop(react: Callable[[int], object]) -> Iterator[None]:
    """The loop's own signal handling (it wakes the loop) calls `react` on the first one."""
    loop = asyncio.get_running_loop()
    _stopping.reactions.append(react)
    if _stopping.received is None and _on_main_thread():
        for sig in taken():
            loop.add_signal_handler(sig, _first_on_the_loop, sig)
    try:
        yield
    finally:
        _stopping.reactions.pop()


def _on_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _first_on_the_loop(sig: int) -> None:
    loop = asyncio.get_running_loop()
    for each in taken():
        loop.remove_signal_handler(each)
    _stopping.first(sig)


def _outside_the_loop() -> None:
    """The closed loop put the signals' default actions back: after a first, its rules."""
    if _stopping.handling and _stopping.received is not None:
        _after_the_first()
