"""Red team 23 on the quiet period after a client left (services.QUIET_AFTER_CLIENT_LEFT_S).

Without a readable reply identity, a reply is taken as ours only while no other client of
the service is there and none left less than the quiet period ago: one that left may have
left a request unanswered, and the server's reply to it still reaches every reply reader.
The client judged "left" by what it saw at its own calls: a client that came and went
between two of our calls (our client idle meanwhile) was never seen, so it had never
"left", and its late reply was taken as the answer to our next request."""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path

import pytest
from oracle.client import OracleEnv, RclpyOracle

from rcan_rtps.ros.errors import AmbiguousReply, ServiceTimeout
from rcan_rtps.ros.graph import Direction
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.services import ServiceClient, shared_graph
from tests.waiting import eventually

SET_BOOL = "std_srvs/srv/SetBool"
SERVED_IN_S = 3.0  # the server's time per request: a client giving up sooner leaves it


@pytest.fixture
def slow_server(jazzy_oracle: OracleEnv, domain_id: int) -> RclpyOracle:
    """An rclpy node (Fast DDS, the default oracle_rmw) answering /slow (SetBool: `success`
    echoes `data`, so whose reply it is shows) SERVED_IN_S after each request."""
    with RclpyOracle(jazzy_oracle, "slow_host", "/", domain_id=domain_id) as agent:
        agent.call("service_server", name="/slow", type=SET_BOOL, delay=SERVED_IN_S)
        yield agent


async def test_a_client_come_and_gone_between_our_calls_keeps_replies_ambiguous(
        slow_server: RclpyOracle, domain_id: int, jazzy_share: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Another client comes, asks, gives up before the answer and leaves, all while ours
    makes no call (our graph sees it come and go)."""
    await _trial(domain_id, jazzy_share, monkeypatch, ours_looks=True)


async def test_a_client_our_graph_never_saw_alive_keeps_replies_ambiguous(
        slow_server: RclpyOracle, domain_id: int, jazzy_share: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """As above, with nothing of ours looking at the graph while the other client is there:
    the discovery reader keeps one sample an endpoint, and its last one, its disposal, names
    no topic. The graph never saw it alive, yet it left a request behind all the same."""
    await _trial(domain_id, jazzy_share, monkeypatch, ours_looks=False)


async def _trial(domain_id: int, jazzy_share: Path, monkeypatch: pytest.MonkeyPatch, *,
                 ours_looks: bool) -> None:
    """Our client answered alone; another client's request left unanswered at the server
    (`ours_looks`: our graph refreshed while that client is there); then our next call must
    not take the server's reply to it (data False) as ours: ambiguous, or our own answer."""
    monkeypatch.setenv("RCAN_RTPS_RPC_IDENTITY", "off")
    with RosNode("caller", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as node:
        client = ServiceClient(node, "/slow", SET_BOOL)
        await client.wait_for_service(timeout=30)
        assert (await client.call({"data": True}, timeout=20)).success  # alone: answered
        with RosNode("other", "/", domain_id=domain_id, distro="jazzy",
                     idl_paths=[jazzy_share]) as other_node:
            other = ServiceClient(other_node, "/slow", SET_BOOL)
            await other.wait_for_service(timeout=30)
            watched = node if ours_looks else other_node  # the other's view leaves ours be
            await eventually(lambda: _clients_seen(watched) == 2, timeout=30,
                             what="both clients in a graph")
            with contextlib.suppress(ServiceTimeout, AmbiguousReply):
                await other.call({"data": False}, timeout=0.5)
            other.close()
        if ours_looks:
            await eventually(lambda: _clients_seen(node) == 1, timeout=30,
                             what="the other client gone from our graph")
        else:
            await asyncio.sleep(1.0)  # its disposal on its way (the server answers at 3 s)
        try:
            reply = await client.call({"data": True}, timeout=20)
        except AmbiguousReply:
            pass  # the fix: the other left just now
        else:
            assert reply.success, f"took the other client's reply as ours: {reply.message}"
        client.close()
        await asyncio.sleep(0)


def _clients_seen(node: RosNode) -> int:
    graph = shared_graph(node)
    graph.refresh()
    return len(graph.gids_on("rq/slowRequest", Direction.PUBLISHER))
