"""Fixtures shared by the interop tests."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from oracle.client import OracleEnv, RclpyOracle

from tests.interop.cpu_load import burning_cpus
from tests.interop.test_demo import Demo, _run_demo


@pytest.fixture
def sim(tmp_path: Path, domain_id: int) -> Iterator[Demo]:
    """`rcan-rtps run --sim` as a user starts it (its own process, the demo's config and
    tokens), with its state in this test's directory; a test module may define its own."""
    yield from _run_demo(tmp_path, domain_id, "--state-dir", str(tmp_path / "state"))


@pytest.fixture
def cpu_load() -> Iterator[None]:
    """One busy process per core for the test's duration (a robot computer at work)."""
    with burning_cpus():
        yield


@pytest.fixture
def echo_server(jazzy_oracle: OracleEnv, domain_id: int) -> Iterator[RclpyOracle]:
    """An rclpy node serving /echo (its RMW: `oracle_rmw`), for echo_callers.py's callers."""
    with RclpyOracle(jazzy_oracle, "echo_host", "/", domain_id=domain_id) as agent:
        agent.call("echo_server", name="/echo")
        yield agent
