"""How tests wait: poll a condition until it holds, or fail saying what never happened.

`eventually` replaces hand-written `while ...: await asyncio.sleep(...)` loops: it never
returns False quietly, so a wait that times out is an AssertionError naming what was awaited
and the last thing seen. `take` collects what the rclpy oracle receives on a topic.
"""

from __future__ import annotations

import asyncio
import inspect
import time
from collections.abc import Callable
from typing import Any, Protocol

POLL_S = 0.02
TIMEOUT_S = 10.0
# The discovery window of a graph command (`node list`, `topic info`, ...) that must see a
# peer: the CLI lists what it found in `--spin-time` (1.5 s by default, for people), and on a
# busy machine (the suite's own workers beside it) a fresh participant can take longer than
# that to meet its peers. 5 s also covers Fast DDS's 3 s heartbeat for late readers.
SPIN = ("--spin-time", "5")

Describe = str | Callable[[], str] | None


def _describe(what: Describe, predicate: Callable[[], Any]) -> str:
    if callable(what):
        return what()
    if what:
        return what
    try:  # a lambda names itself best by its source line
        return inspect.getsource(predicate).strip()
    except (OSError, TypeError):
        return repr(predicate)


def _timed_out(what: Describe, predicate: Callable[[], Any], timeout: float, last: Any,
               error: AssertionError | None) -> AssertionError:
    seen = f"last error: {error}" if error is not None else f"last value: {last!r}"
    return AssertionError(f"not within {timeout} s: {_describe(what, predicate)} ({seen})")


async def eventually(predicate: Callable[[], Any], *, timeout: float = TIMEOUT_S,
                     what: Describe = None, interval: float = POLL_S) -> Any:
    """Poll `predicate` (plain or async) until it gives a truthy value, and return that value.

    An AssertionError from the predicate means "not yet"; any other exception is a bug and
    propagates at once. `what` (text, or a function giving it) names the wait on timeout.
    """
    deadline = time.monotonic() + timeout
    last: Any = None
    error: AssertionError | None = None
    while True:
        try:
            last = predicate()
            if inspect.isawaitable(last):
                last = await last
            error = None
        except AssertionError as exc:
            error = exc
        if error is None and last:
            return last
        if time.monotonic() >= deadline:
            raise _timed_out(what, predicate, timeout, last, error) from error
        await asyncio.sleep(interval)


def eventually_sync(predicate: Callable[[], Any], *, timeout: float = TIMEOUT_S,
                    what: Describe = None, interval: float = POLL_S) -> Any:
    """`eventually` for plain (non-async) tests: the same contract, blocking."""
    deadline = time.monotonic() + timeout
    last: Any = None
    error: AssertionError | None = None
    while True:
        try:
            last, error = predicate(), None
        except AssertionError as exc:
            error = exc
        if error is None and last:
            return last
        if time.monotonic() >= deadline:
            raise _timed_out(what, predicate, timeout, last, error) from error
        time.sleep(interval)


class Oracle(Protocol):
    async def acall(self, op: str, timeout: float = ..., **args: Any) -> Any: ...


async def take(oracle: Oracle, topic: str, *, until: Callable[[list[Any]], bool] = bool,
               timeout: float = TIMEOUT_S) -> list[Any]:
    """Every sample the oracle took on `topic`, gathered until `until(samples)` holds.

    By default: until anything arrived. The samples are returned in arrival order.
    """
    got: list[Any] = []

    async def enough() -> bool:
        got.extend(await oracle.acall("take", topic=topic))
        return until(got)

    await eventually(enough, timeout=timeout, what=lambda: f"samples on {topic}: {got!r}")
    return got
