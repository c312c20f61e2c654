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

Without a readable identity (the capture off here; DDS-Security in practice) a reply is taken
only while the caller is the service's only client in the graph: with others calling, the
processes swapped 140 of 150 replies before; now such a call fails with AmbiguousReply, and a
lone caller still gets every answer.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from pathlib import Path

import pytest
from oracle.client import RMWS, RclpyOracle

from rcan_rtps.ros import services
from rcan_rtps.ros.errors import AmbiguousReply
from rcan_rtps.ros.graph import Direction
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.services import ServiceClient, shared_graph
from tests.interop.cpu_load import burning_cpus
from tests.interop.echo_callers import run_callers
from tests.waiting import eventually

PROCESSES = 6
CALLS_EACH = 25
CALLER = Path(__file__).with_name("concurrent_caller.py")
ECHO = "test_msgs/srv/BasicTypes"


@pytest.mark.parametrize("oracle_rmw", RMWS)
def test_processes_calling_at_once_never_swap_or_lose_replies(
        echo_server: RclpyOracle, domain_id: int, jazzy_share: Path) -> None:
    _call_at_once(echo_server, domain_id, jazzy_share)


@pytest.mark.parametrize("oracle_rmw", RMWS)
def test_processes_calling_at_once_under_cpu_load(
        echo_server: RclpyOracle, domain_id: int, jazzy_share: Path) -> None:
    with burning_cpus():
        _call_at_once(echo_server, domain_id, jazzy_share)


@pytest.mark.parametrize("oracle_rmw", RMWS)
def test_without_request_identity_no_reply_is_taken_for_another(
        echo_server: RclpyOracle, domain_id: int, jazzy_share: Path,
        monkeypatch: pytest.MonkeyPatch, oracle_rmw: str) -> None:
    monkeypatch.setenv("RCAN_RTPS_RPC_IDENTITY", "off")
    ambiguous = _call_at_once(echo_server, domain_id, jazzy_share, ambiguous_ok=True)
    if oracle_rmw == "fastrtps":  # its replies reach every client: most are unsure
        assert ambiguous > 0
    else:  # rmw_cyclonedds names the client in the reply itself
        assert ambiguous == 0


@pytest.mark.parametrize("oracle_rmw", RMWS)
def test_without_request_identity_a_lone_client_gets_every_answer(
        echo_server: RclpyOracle, domain_id: int, jazzy_share: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RCAN_RTPS_RPC_IDENTITY", "off")
    assert _call_at_once(echo_server, domain_id, jazzy_share, processes=1) == 0


def _call_at_once(oracle: RclpyOracle, domain_id: int, jazzy_share: Path, *,
                  processes: int = PROCESSES, ambiguous_ok: bool = False) -> int:
    """Runs the callers; asserts nothing lost or wrong; returns how many were ambiguous."""
    tallies = run_callers(CALLER, processes, CALLS_EACH, domain_id, jazzy_share, timeout=120)
    lost = sum(len(t["lost"]) for t in tallies)
    wrong = [w for t in tallies for w in t["wrong"]]
    ambiguous = sum(len(t["ambiguous"]) for t in tallies)
    identity = os.environ.get("RCAN_RTPS_RPC_IDENTITY", "on")
    print(f"{processes} processes x {CALLS_EACH} calls (identity capture {identity}): "
          f"{len(wrong)} misattributed, {lost} lost, {ambiguous} refused as ambiguous")
    assert (lost, wrong) == (0, []), \
        f"of {processes * CALLS_EACH} calls: {lost} lost, misattributed {wrong}"
    assert ambiguous_ok or ambiguous == 0
    served = oracle.call("service_requests", name="/echo")
    assert sorted(served) == sorted(f"p{n}:{i}" for n in range(processes)
                                    for i in range(CALLS_EACH))
    return ambiguous


async def test_a_client_that_left_keeps_unnamed_replies_ambiguous_a_while(
        echo_server: RclpyOracle, domain_id: int, jazzy_share: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Without a readable identity, the other clients' being gone is not enough: one that
    left may have left a request unanswered (it gave up on it), and the server's reply to it
    still comes to us. A clean-clone CI under load took such a reply as the answer to its own
    request (1 of 150, 'p3:24 got p0:24': p0's last call refused as ambiguous, p0 gone, p3's
    next call answered by p0's reply). So a reply without identity is ambiguous until the
    others have been gone QUIET_AFTER_CLIENT_LEFT_S; after that, taken again. (oracle_rmw is
    fastrtps, the default: replies without an in-band header.)"""
    monkeypatch.setenv("RCAN_RTPS_RPC_IDENTITY", "off")
    with RosNode("caller", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as node:
        client = ServiceClient(node, "/echo", ECHO)
        await client.wait_for_service(timeout=30)
        assert await _echoed(client, "alone") == "alone"  # never saw another: answered

        with RosNode("other", "/", domain_id=domain_id, distro="jazzy",
                     idl_paths=[jazzy_share]) as other_node:
            other = ServiceClient(other_node, "/echo", ECHO)
            await other.wait_for_service(timeout=30)
            with contextlib.suppress(AmbiguousReply):
                await _echoed(other, "its")  # its endpoints made
            await eventually(lambda: _clients_seen(node) == 2, timeout=30,
                             what="the other client in the graph")
            with pytest.raises(AmbiguousReply):
                await _echoed(client, "beside")
            other.close()
        await eventually(lambda: _clients_seen(node) == 1, timeout=30,
                         what="the other client gone from the graph")
        with pytest.raises(AmbiguousReply):  # before the fix: answered
            await _echoed(client, "just after")
        monkeypatch.setattr(services, "QUIET_AFTER_CLIENT_LEFT_S", 0.5)
        await asyncio.sleep(0.6)
        assert await _echoed(client, "later") == "later"
        client.close()


async def _echoed(client: ServiceClient, text: str) -> str:
    reply = await client.call({"string_value": text}, timeout=15)
    return str(reply.string_value)


def _clients_seen(node: RosNode) -> int:
    """Request writers on /echo in `node`'s graph: clients (ours included)."""
    graph = shared_graph(node)
    graph.refresh()
    return len(graph.gids_on("rq/echoRequest", Direction.PUBLISHER))
