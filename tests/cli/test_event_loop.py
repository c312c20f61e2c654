"""`rcan-rtps run`'s event loop: uvloop when importable (the `fast` extra), else asyncio's."""

from __future__ import annotations

import asyncio
import sys

import pytest

from rcan_rtps.cli import run_cmd


async def loop_module() -> str:
    return type(asyncio.get_running_loop()).__module__


def ran_on() -> str:
    found: list[str] = []

    async def main() -> int:
        found.append(await loop_module())
        return 0

    assert run_cmd.run_loop(main()) == 0
    return found[0]


def test_uvloop_when_installed(monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("uvloop")
    monkeypatch.delenv(run_cmd.LOOP_ENV, raising=False)
    assert ran_on().startswith("uvloop")


def test_a_run_on_uvloop_leaves_the_next_loop_of_the_process_alone(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """uvloop drives the run's own loop only: on Python 3.10, where asyncio.run takes no loop
    factory, setting uvloop's policy for the run made every later loop of the process a
    uvloop one, RCAN_RTPS_LOOP=asyncio or not (and other threads' loops during the run)."""
    pytest.importorskip("uvloop")
    monkeypatch.delenv(run_cmd.LOOP_ENV, raising=False)
    policy = asyncio.get_event_loop_policy()
    assert ran_on().startswith("uvloop")
    assert asyncio.get_event_loop_policy() is policy
    assert asyncio.run(loop_module()).startswith("asyncio")
    monkeypatch.setenv(run_cmd.LOOP_ENV, "asyncio")
    assert ran_on().startswith("asyncio")


def test_asyncio_without_uvloop(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "uvloop", None)  # `import uvloop` raises ImportError
    assert ran_on().startswith("asyncio")


def test_asyncio_when_asked(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(run_cmd.LOOP_ENV, "asyncio")
    assert ran_on().startswith("asyncio")
