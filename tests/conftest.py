"""Shared fixtures: where the ROS 2 oracle lives, and the CI rule on skipped interop tests."""

from __future__ import annotations

import importlib.util
import os
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from asyncio_log_guard import AsyncioLogGuard  # noqa: E402
from oracle.client import RMWS, OracleEnv  # noqa: E402
from shm_sweep import segments, sweep  # noqa: E402

ON_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


def _oracle_python(distro: str) -> Path | None:
    env = os.environ.get(f"RCAN_RTPS_ORACLE_{distro.upper().replace('-', '_')}")
    candidate = Path(env) if env else ROOT / ".cache" / f"ros-{distro}" / "bin" / "python"
    return candidate if candidate.exists() else None


@pytest.fixture(scope="session")
def jazzy_python() -> Path:
    """The interpreter of the ROS 2 Jazzy oracle environment (rclpy + Fast DDS)."""
    found = _oracle_python("jazzy")
    if found is None:
        pytest.skip("ROS 2 Jazzy oracle not installed: run scripts/test.sh")
    return found


@pytest.fixture(scope="session")
def jazzy_cyclone_python() -> Path:
    """ROS 2 Jazzy whose rclpy also runs on rmw_cyclonedds_cpp (built by scripts/test.sh from
    tests/oracle/rmw-cyclonedds, or RCAN_RTPS_ORACLE_JAZZY_CYCLONE)."""
    found = _oracle_python("jazzy-cyclone")
    if found is None:
        why = os.environ.get("RCAN_RTPS_ORACLE_JAZZY_CYCLONE_ERROR", "run scripts/test.sh")
        pytest.skip(f"ROS 2 Jazzy on rmw_cyclonedds_cpp not available: {why}")
    return found


@pytest.fixture
def oracle_rmw() -> str:
    """The RMW rclpy oracles run on; tests that cover both parametrize it (`both_rmws`)."""
    return "fastrtps"


@pytest.fixture
def jazzy_oracle(oracle_rmw: str, request: pytest.FixtureRequest) -> OracleEnv:
    """The Jazzy oracle on `oracle_rmw`: hand it to RclpyOracle in place of a bare python."""
    if oracle_rmw not in RMWS:
        raise pytest.UsageError(f"unknown oracle RMW {oracle_rmw!r} (one of {RMWS})")
    fixture = "jazzy_python" if oracle_rmw == "fastrtps" else "jazzy_cyclone_python"
    return OracleEnv(request.getfixturevalue(fixture), oracle_rmw)


@pytest.fixture(scope="session")
def jazzy_share(jazzy_python: Path) -> Path:
    """`<oracle venv>/share`: the official .msg/.idl/.json files of every installed package."""
    return jazzy_python.parent.parent / "share"


@pytest.fixture(scope="session")
def kilted_python() -> Path:
    """ROS 2 Kilted, the optional second real graph (skipped where it did not install)."""
    found = _oracle_python("kilted")
    if found is None:
        pytest.skip("ROS 2 Kilted oracle not installed")
    return found


ORACLE_FIXTURES = frozenset({"jazzy_python", "jazzy_share", "kilted_python",
                             "jazzy_cyclone_python", "jazzy_oracle"})
# Under CI a test that needs the Cyclone oracle fails when skipped, wherever it lives.
CI_REQUIRED_FIXTURES = frozenset({"jazzy_cyclone_python", "jazzy_oracle"})


def _uses_the_load_generator(item: pytest.Item) -> bool:
    """The `cpu_load` fixture, or `burning_cpus` called in the test function itself."""
    code = getattr(getattr(item, "obj", None), "__code__", None)
    return "cpu_load" in getattr(item, "fixturenames", ()) or (
        code is not None and "burning_cpus" in code.co_names)


@pytest.hookimpl(tryfirst=True)  # before `-m` selects on the marks added here
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if "interop" in item.nodeid.split("/"):
            item.add_marker(pytest.mark.interop)
        # A load generator busies every core: its tests run alone, after the parallel phase
        # (beside other tests they would starve them, and be starved by them).
        if _uses_the_load_generator(item):
            item.add_marker(pytest.mark.serial)
        # An `offline` test must mean something on a machine without ROS: it may not
        # depend on the oracle, not even indirectly through another fixture.
        used = ORACLE_FIXTURES.intersection(getattr(item, "fixturenames", ()))
        if item.get_closest_marker("offline") is not None and used:
            raise pytest.UsageError(
                f"{item.nodeid} is marked offline but requests {', '.join(sorted(used))}")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]):  # type: ignore[no-untyped-def]
    outcome = yield
    report = outcome.get_result()
    # An offline test has nothing to wait for: skipping it would hide a missing data file.
    if report.skipped and item.get_closest_marker("offline") is not None:
        report.outcome = "failed"
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else report.longrepr
        report.longrepr = f"offline test skipped: {reason}"
        return
    # Under CI a skipped interop test is a failure: the real graph must have been there.
    # (A strict xfail ran against it: a known limit, and it fails the day it passes.)
    needs_oracle = bool(CI_REQUIRED_FIXTURES.intersection(getattr(item, "fixturenames", ())))
    if ON_CI and report.skipped and not hasattr(report, "wasxfail") and (
            item.get_closest_marker("interop") is not None or needs_oracle):
        report.outcome = "failed"
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else report.longrepr
        report.longrepr = f"interop test skipped under CI=true: {reason}"


# Test domains: 1..99 but 77/78 (benchmarks). Above ~100, DDS ports reach Linux's ephemeral
# range and can collide with other sockets. Under pytest-xdist the workers share one network
# namespace, so each takes a disjoint share of them (`worker_domains`): DDS ports and
# participant ids derive from the domain id, so disjoint domains never meet on the wire.
_TEST_DOMAINS = [d for d in range(1, 100) if d not in (77, 78)]


def _worker() -> tuple[int, int]:
    """(this worker's index, how many workers): (0, 1) without xdist."""
    name = os.environ.get("PYTEST_XDIST_WORKER", "")
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)
    index = int(name[2:]) if name.startswith("gw") and name[2:].isdigit() else 0
    return index, max(count, 1)


def worker_domains() -> list[int]:
    """This worker's share of the test domains (all of them when tests run in one process)."""
    index, count = _worker()
    share = _TEST_DOMAINS[index::count]
    if len(share) < 4:
        raise pytest.UsageError(f"{count} workers leave worker {index} only {len(share)} "
                                "DDS domains: run fewer workers")
    return share


# The worker's first domain is kept for module-scoped fixtures (`module_domain_id`); pytest
# tears a module's fixtures down before the next module's are set up, so one is enough.
# Its second is the default for processes given no domain (ROS_DOMAIN_ID, set below).
_MODULE_DOMAIN, _DEFAULT_DOMAIN, *_PER_TEST_DOMAINS = worker_domains()
_next_domain = [os.getpid() % len(_PER_TEST_DOMAINS)]


def next_domain_id() -> int:
    """A domain of this worker's not used by the last few dozen tests."""
    _next_domain[0] = (_next_domain[0] + 1) % len(_PER_TEST_DOMAINS)
    return _PER_TEST_DOMAINS[_next_domain[0]]


@pytest.fixture
def domain_id() -> int:
    """A fresh DDS domain per test, so tests never see each other's nodes."""
    return next_domain_id()


@pytest.fixture
def another_domain_id() -> int:
    """A second fresh domain, for a test that needs two."""
    return next_domain_id()


@pytest.fixture(scope="module")
def module_domain_id() -> int:
    """The domain of a module-scoped fixture's nodes: this worker's own, apart from the
    per-test ones."""
    return _MODULE_DOMAIN


@pytest.fixture(scope="session", autouse=True)
def _own_state_home(tmp_path_factory: pytest.TempPathFactory) -> None:
    """A demo started without --state-dir keeps its state (latched e-stop, audit log) under
    $XDG_STATE_HOME: this session's own (each xdist worker has its own temporary directory),
    never the user's ~/.local/state nor another worker's."""
    os.environ["XDG_STATE_HOME"] = str(tmp_path_factory.mktemp("xdg-state"))


def _refuse_the_source_tree() -> None:
    """Under RCAN_RTPS_TEST_INSTALLED (scripts/python310.sh), the tests are of the installed
    wheel: a rcan_rtps imported from src/ (PYTHONPATH, an editable install) would test the
    tree instead, on whatever it happens to import."""
    if not os.environ.get("RCAN_RTPS_TEST_INSTALLED"):
        return
    spec = importlib.util.find_spec("rcan_rtps")
    origin = Path(spec.origin).resolve() if spec is not None and spec.origin else None
    site = {Path(sysconfig.get_path(k)).resolve() for k in ("purelib", "platlib")}
    if origin is None or not site.intersection(origin.parents):
        raise pytest.UsageError(f"RCAN_RTPS_TEST_INSTALLED is set but rcan_rtps comes from "
                                f"{origin or 'nowhere'}, not from {sys.executable}'s "
                                "site-packages (an installed wheel)")


def pytest_configure(config: pytest.Config) -> None:
    _refuse_the_source_tree()
    # An error asyncio logs (an exception never retrieved, a task destroyed pending) fails the
    # run: tests/asyncio_log_guard.py.
    config.pluginmanager.register(AsyncioLogGuard(config), "rcan-asyncio-log-guard")
    # Whatever starts a DDS participant without naming a domain joins this worker's own, not
    # domain 0 shared with every other worker.
    os.environ["ROS_DOMAIN_ID"] = str(_DEFAULT_DOMAIN)
    # Outside a private network namespace (a run by hand without scripts/netns), every
    # participant of ours and of the rclpy peers stays on loopback: none reaches a network.
    if not os.environ.get("RCAN_RTPS_IN_NETNS"):
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


_SHM_BEFORE = "_rcan_rtps_shm_before"


def pytest_sessionstart(session: pytest.Session) -> None:
    if not hasattr(session.config, "workerinput"):  # the run's controller, not a worker
        setattr(session.config, _SHM_BEFORE, segments())


def pytest_sessionfinish(session: pytest.Session) -> None:
    before = getattr(session.config, _SHM_BEFORE, None)
    if before is not None:  # after every worker ended: their killed peers' segments
        removed = sweep(before)
        if removed:
            print(f"\nremoved {len(removed)} Fast DDS shared-memory files that killed "
                  "rclpy peers left in /dev/shm")
