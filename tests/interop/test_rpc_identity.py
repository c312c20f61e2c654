"""Reading the related sample identity of a Fast DDS server's replies (docs/design/rpc-identity.md).

Several processes call one rclpy echo server on rmw_fastrtps at the same moment; each reads,
from Cyclone's own packet capture, the request identity every reply names in its inline QoS
(identity_caller.py). Every reply a process receives must be identified: its own replies as
its own and echoing the right request, the copies of other processes' replies as foreign. A
call waits for the reply naming its own request only, so no process may lose or swap one.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from oracle.client import OracleEnv, RclpyOracle

from tests.interop.cpu_load import burning_cpus

CALLER = Path(__file__).with_name("identity_caller.py")


@pytest.fixture
def oracle(jazzy_oracle: OracleEnv, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_oracle, "echo_host", "/", domain_id=domain_id) as agent:
        agent.call("echo_server", name="/echo")
        yield agent


def _run_callers(processes: int, calls: int, domain_id: int, share: Path) -> list[dict]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    callers = [subprocess.Popen(
        [sys.executable, str(CALLER), f"p{n}", str(calls), str(domain_id), str(share)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
        for n in range(processes)]
    try:
        for caller in callers:  # all matched before anyone calls
            assert caller.stdout is not None and caller.stdout.readline().strip() == "ready"
        for caller in callers:
            assert caller.stdin is not None
            caller.stdin.write("go\n")
            caller.stdin.flush()
        return [json.loads(caller.communicate(timeout=180)[0].splitlines()[-1])
                for caller in callers]
    finally:
        for caller in callers:
            caller.kill()


def _check(tallies: list[dict], processes: int, calls: int) -> None:
    counts = {kind: sum(t["tally"].get(kind, 0) for t in tallies)
              for kind in ("ours", "foreign", "mixed", "unknown")}
    lost = sum(len(t["lost"]) for t in tallies)
    print(f"{processes} processes x {calls} calls: {counts}, lost {lost}")
    assert counts["ours"] == processes * calls, counts
    assert (counts["mixed"], counts["unknown"], lost) == (0, 0, 0), counts


@pytest.mark.parametrize("processes", [4, 6])
def test_every_reply_of_a_fast_dds_server_names_its_request(
        oracle: RclpyOracle, domain_id: int, jazzy_share: Path, processes: int) -> None:
    calls = 25
    _check(_run_callers(processes, calls, domain_id, jazzy_share), processes, calls)


def test_every_reply_is_identified_under_cpu_load(
        oracle: RclpyOracle, domain_id: int, jazzy_share: Path) -> None:
    processes, calls = 4, 50
    with burning_cpus():
        tallies = _run_callers(processes, calls, domain_id, jazzy_share)
    _check(tallies, processes, calls)
