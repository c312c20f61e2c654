"""The waiting helpers themselves: they pass when the condition comes true, and fail loudly."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from waiting import eventually, eventually_sync, take

pytestmark = pytest.mark.offline


async def test_eventually_returns_the_first_truthy_value() -> None:
    polls: list[int] = []

    def ready() -> list[int] | None:
        polls.append(1)
        return polls if len(polls) == 3 else None

    assert await eventually(ready, timeout=5) == [1, 1, 1]


async def test_eventually_accepts_an_async_predicate() -> None:
    flag = asyncio.Event()
    asyncio.get_running_loop().call_later(0.05, flag.set)

    async def is_set() -> bool:
        await asyncio.sleep(0)
        return flag.is_set()

    assert await eventually(is_set, timeout=5) is True


async def test_eventually_times_out_naming_the_wait_and_the_last_value() -> None:
    with pytest.raises(AssertionError, match=r"not within 0.1 s: the door opens \(last value: 0\)"):
        await eventually(lambda: 0, timeout=0.1, what="the door opens")


async def test_a_failing_assertion_means_not_yet_and_is_reported() -> None:
    def check() -> bool:
        assert 1 + 1 == 3, "arithmetic still holds"
        return True

    with pytest.raises(AssertionError, match="last error: arithmetic still holds"):
        await eventually(check, timeout=0.1, what=lambda: "computed description")


async def test_other_exceptions_are_bugs_and_propagate_at_once() -> None:
    def broken() -> bool:
        raise KeyError("x")

    with pytest.raises(KeyError):
        await eventually(broken, timeout=30)


async def test_without_what_the_lambda_source_names_the_wait() -> None:
    with pytest.raises(AssertionError, match=r"lambda: \[\] != \[\]"):
        await eventually(lambda: [] != [], timeout=0.05)


def test_eventually_sync_has_the_same_contract() -> None:
    counter = iter(range(10))
    assert eventually_sync(lambda: next(counter) >= 2, timeout=5) is True
    with pytest.raises(AssertionError, match="never"):
        eventually_sync(lambda: False, timeout=0.05, what="never")


class FakeOracle:
    def __init__(self, batches: list[list[Any]]) -> None:
        self.batches = batches

    async def acall(self, op: str, timeout: float = 30.0, **args: Any) -> Any:
        assert op == "take"
        return self.batches.pop(0) if self.batches else []


async def test_take_gathers_samples_until_enough() -> None:
    oracle = FakeOracle([[], [1], [], [2, 3], [4]])
    assert await take(oracle, "/t") == [1]
    assert await take(oracle, "/t", until=lambda got: 3 in got) == [2, 3]
    with pytest.raises(AssertionError, match=r"samples on /t: \[4\]"):
        await take(oracle, "/t", until=lambda got: len(got) > 1, timeout=0.1)
