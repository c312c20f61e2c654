"""Reading the related sample identity of a Fast DDS server's replies (docs/design/rpc-identity.md).

Several processes call one rclpy echo server on rmw_fastrtps at the same moment; each reads,
from Cyclone's own packet capture, the request identity every reply names in its inline QoS
(identity_caller.py). Every reply a process receives must be identified: its own replies as
its own and echoing the right request, the copies of other processes' replies as foreign. A
call waits for the reply naming its own request only, so no process may lose or swap one.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from oracle.client import RclpyOracle

from tests.interop.cpu_load import burning_cpus
from tests.interop.echo_callers import run_callers

CALLER = Path(__file__).with_name("identity_caller.py")


def _run_callers(processes: int, calls: int, domain_id: int, share: Path) -> list[dict]:
    return run_callers(CALLER, processes, calls, domain_id, share, timeout=180)


def _check(tallies: list[dict], processes: int, calls: int) -> None:
    counts = {kind: sum(t["tally"].get(kind, 0) for t in tallies)
              for kind in ("ours", "foreign", "mixed", "unknown")}
    lost = sum(len(t["lost"]) for t in tallies)
    renewed, unannounced = (sum(t[k] for t in tallies) for k in ("renewed", "unannounced"))
    losses = {f"p{n}": (t["lost"], t["lost_in_capture"]) for n, t in enumerate(tallies)
              if t["lost"]}
    print(f"{processes} processes x {calls} calls: {counts}, lost {lost} {losses} (calls, of "
          f"them reached our socket); {renewed} reply readers made again, "
          f"{unannounced} processes called unannounced")
    # A reader the server's writer was not heard announcing itself to can lose its first
    # reply as history (handshake.py, 3.): the only loss allowed, and only to those.
    excused = [t["lost"] for t in tallies if t["unannounced"] and t["lost"] == [1]]
    assert counts["ours"] == processes * calls - len(excused), (counts, lost, unannounced)
    assert (counts["mixed"], counts["unknown"], lost) == (0, 0, len(excused)), counts


@pytest.mark.parametrize("processes", [4, 6])
def test_every_reply_of_a_fast_dds_server_names_its_request(
        echo_server: RclpyOracle, domain_id: int, jazzy_share: Path, processes: int) -> None:
    calls = 25
    _check(_run_callers(processes, calls, domain_id, jazzy_share), processes, calls)


def test_every_reply_is_identified_under_cpu_load(
        echo_server: RclpyOracle, domain_id: int, jazzy_share: Path) -> None:
    processes, calls = 4, 50
    with burning_cpus():
        tallies = _run_callers(processes, calls, domain_id, jazzy_share)
    _check(tallies, processes, calls)
