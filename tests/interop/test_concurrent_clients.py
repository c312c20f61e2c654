"""Clients in different processes calling one rclpy (Fast DDS) server at the same moment.

A Fast DDS server writes every reply to every client's reply reader, naming the request only
in the RTPS inline QoS (related sample identity), which the cyclonedds API cannot read; before
the client read it from Cyclone's packet capture (rtps_capture.py), processes calling one
Fast DDS server at the same moment swapped replies (most of the 150 calls of 6 processes x 25
sequential calls). Against an rclpy server on Cyclone DDS (its replies carry the client's id
in-band) the same load must be exact too. The same with a CPU load generator running:
test_rpc_identity.py. Sequential calls and
fresh clients are exact on both (test_zero_loss.py). Weighed and refused: reading the request
topic to count outstanding requests (that reader would look like a server to every ROS tool).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from oracle.client import RMWS, RclpyOracle

from tests.interop.cpu_load import burning_cpus
from tests.interop.echo_callers import run_callers

PROCESSES = 6
CALLS_EACH = 25
CALLER = Path(__file__).with_name("concurrent_caller.py")


@pytest.mark.parametrize("oracle_rmw", RMWS)
def test_processes_calling_at_once_never_swap_or_lose_replies(
        echo_server: RclpyOracle, domain_id: int, jazzy_share: Path) -> None:
    _call_at_once(echo_server, domain_id, jazzy_share)


@pytest.mark.parametrize("oracle_rmw", RMWS)
def test_processes_calling_at_once_under_cpu_load(
        echo_server: RclpyOracle, domain_id: int, jazzy_share: Path) -> None:
    with burning_cpus():
        _call_at_once(echo_server, domain_id, jazzy_share)


def _call_at_once(oracle: RclpyOracle, domain_id: int, jazzy_share: Path) -> None:
    tallies = run_callers(CALLER, PROCESSES, CALLS_EACH, domain_id, jazzy_share, timeout=120)
    lost = sum(len(t["lost"]) for t in tallies)
    wrong = [w for t in tallies for w in t["wrong"]]
    print(f"{PROCESSES} processes x {CALLS_EACH} calls: {len(wrong)} misattributed, {lost} lost")
    assert (lost, wrong) == (0, []), \
        f"of {PROCESSES * CALLS_EACH} calls: {lost} lost, misattributed {wrong}"
    served = oracle.call("service_requests", name="/echo")
    assert sorted(served) == sorted(f"p{n}:{i}" for n in range(PROCESSES)
                                    for i in range(CALLS_EACH))
