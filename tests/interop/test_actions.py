"""Actions against a real rclpy Jazzy Fibonacci server (on Fast DDS and on
Cyclone DDS). rclpy's client on Cyclone against our server: test_rmw_cyclonedds.py."""

from __future__ import annotations

import asyncio
import logging
import sys
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest
from dropping import DeafCapture
from oracle.client import OracleEnv, RclpyOracle, both_rmws, fibonacci
from waiting import eventually

from rcan_rtps._modules import START_ONLY
from rcan_rtps.ros.actions import ActionClient, GoalState
from rcan_rtps.ros.errors import ServiceTimeout, ServiceUnavailable, ValueFitError, WireError
from rcan_rtps.ros.handshake import ANNOUNCE_TRIES
from rcan_rtps.ros.participant import RosNode

FIB = "test_msgs/action/Fibonacci"


@pytest.fixture
def oracle(jazzy_oracle: OracleEnv, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_oracle, "fib_server", "/", domain_id=domain_id) as agent:
        yield agent


@pytest.fixture
async def node(domain_id: int, jazzy_share: Path) -> AsyncIterator[RosNode]:
    # the oracle's share/ first: rosidl's own test_msgs .idl files (the bundle has ours too)
    with RosNode("rcan_actions", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as n:
        yield n


@both_rmws
async def test_goal_succeeds_with_feedback(oracle: RclpyOracle, node: RosNode) -> None:
    await oracle.acall("action_server", name="/fib")
    client = ActionClient(node, "/fib", FIB)
    goal = await client.send_goal({"order": 6}, timeout=20)
    assert goal.accepted and goal.state is not GoalState.REJECTED
    feedback = [list(f.sequence) async for f in goal.feedback(timeout=20)]
    outcome = await goal.result(timeout=20)
    assert outcome.state is GoalState.SUCCEEDED
    assert outcome.result is not None and list(outcome.result.sequence) == fibonacci(6)
    assert feedback and feedback[-1] == fibonacci(6)
    assert all(f == fibonacci(len(f) - 1) for f in feedback)


@both_rmws
async def test_goal_cancelled_mid_run(oracle: RclpyOracle, node: RosNode) -> None:
    await oracle.acall("action_server", name="/fib", mode="slow")
    client = ActionClient(node, "/fib", FIB)
    goal = await client.send_goal({"order": 40}, timeout=20)
    async for _ in goal.feedback(timeout=20):
        break  # running
    assert await goal.cancel(timeout=10)
    outcome = await goal.result(timeout=30)
    assert outcome.state is GoalState.CANCELED
    assert outcome.result is not None and len(outcome.result.sequence) < 41


@both_rmws
async def test_goal_rejected(oracle: RclpyOracle, node: RosNode) -> None:
    await oracle.acall("action_server", name="/fib", mode="reject")
    client = ActionClient(node, "/fib", FIB)
    goal = await client.send_goal({"order": 3}, timeout=20)
    assert not goal.accepted and goal.state is GoalState.REJECTED
    assert (await goal.result()).state is GoalState.REJECTED


@both_rmws
async def test_goal_aborted(oracle: RclpyOracle, node: RosNode) -> None:
    await oracle.acall("action_server", name="/fib", mode="abort")
    client = ActionClient(node, "/fib", FIB)
    goal = await client.send_goal({"order": 4}, timeout=20)
    outcome = await goal.result(timeout=20)
    assert outcome.state is GoalState.ABORTED
    assert outcome.result is not None and list(outcome.result.sequence) == fibonacci(4)


@both_rmws
async def test_two_goals_in_flight(oracle: RclpyOracle, node: RosNode) -> None:
    await oracle.acall("action_server", name="/fib", mode="slow")
    client = ActionClient(node, "/fib", FIB)
    first, second = await asyncio.gather(client.send_goal({"order": 9}, timeout=20),
                                         client.send_goal({"order": 5}, timeout=20))
    assert first.goal_id != second.goal_id and first.accepted and second.accepted
    assert not first.state.terminal and not second.state.terminal  # both running at once
    one, two = await asyncio.gather(first.result(timeout=30), second.result(timeout=30))
    assert one.result is not None and list(one.result.sequence) == fibonacci(9)
    assert two.result is not None and list(two.result.sequence) == fibonacci(5)


@both_rmws
async def test_our_client_and_an_rclpy_client_share_the_server(
        oracle: RclpyOracle, node: RosNode, jazzy_oracle: OracleEnv, domain_id: int) -> None:
    await oracle.acall("action_server", name="/fib")
    with RclpyOracle(jazzy_oracle, "fib_client", "/", domain_id=domain_id) as other:
        client = ActionClient(node, "/fib", FIB)
        await client.wait_for_server(20)
        for order in (7, 3, 10):  # several rounds, each with both clients' goals in flight
            await other.acall("action_send_goal", name="/fib", key=f"k{order}", order=order + 2)
            ours = await client.send_goal({"order": order}, timeout=20)
            mine = await ours.result(timeout=30)
            theirs = await other.acall("action_goal", key=f"k{order}", timeout=60)
            assert mine.state is GoalState.SUCCEEDED
            assert mine.result is not None and list(mine.result.sequence) == fibonacci(order)
            assert theirs["result"] == {"status": 4, "sequence": fibonacci(order + 2)}


@both_rmws
async def test_server_vanishing_mid_goal_ends_the_goal(jazzy_oracle: OracleEnv, domain_id: int,
                                                      node: RosNode) -> None:
    server = RclpyOracle(jazzy_oracle, "doomed", "/", domain_id=domain_id)
    try:
        await server.acall("action_server", name="/fib", mode="slow")
        client = ActionClient(node, "/fib", FIB)
        goal = await client.send_goal({"order": 200}, timeout=20)
        async for _ in goal.feedback(timeout=20):
            break
    finally:
        server.close()  # the node leaves the graph with the goal still running
    outcome = await goal.result(timeout=30)
    assert outcome.state is GoalState.SERVER_LOST and "left the graph" in outcome.detail


async def test_no_server_is_an_error_within_the_timeout(node: RosNode) -> None:
    client = ActionClient(node, "/nobody", FIB)
    with pytest.raises(ServiceUnavailable, match="/nobody/_action/send_goal"):
        await asyncio.wait_for(client.send_goal({"order": 1}, timeout=1.0), 10)


async def test_malformed_goal_names_the_field(node: RosNode) -> None:
    client = ActionClient(node, "/fib", FIB)
    with pytest.raises(ValueFitError, match=r"^order: 3000000000 is out of range"):
        await client.send_goal({"order": 3_000_000_000}, timeout=1.0)


async def _feedback_renewed(client: ActionClient, times: int) -> None:
    while client.feedback_renewed < times:
        await asyncio.sleep(0.01)


async def _announced_services(client: ActionClient) -> None:
    """The three services' reply readers past their announcement wait (capture not deaf)."""
    for service in (client._goal_side()._send, client._goal_side()._get, client._cancel_srv):
        await service.wait_for_service(15)


async def test_an_action_client_closed_while_it_waits_for_the_announcement_says_so(
        oracle: RclpyOracle, node: RosNode) -> None:
    """Fast DDS: before the first goal the client waits to hear the feedback writer's first
    HEARTBEAT to our reader, making the reader again when it does not come. Closed
    meanwhile, `send_goal` raised the binding's DDSException (the deleted reader's GUID
    asked for) instead of saying the client is closed, and a renewal under way made a
    feedback reader for the closed client."""
    await oracle.acall("action_server", name="/fib")
    for renewed in (0, 1):  # in the first reader's wait, in the second's
        client = ActionClient(node, "/fib", FIB)
        await _announced_services(client)
        real, node.identities = node.identities, DeafCapture(node.identities)
        try:
            goal = asyncio.ensure_future(client.send_goal({"order": 3}, timeout=20))
            await asyncio.wait_for(_feedback_renewed(client, renewed), 15)
            await asyncio.sleep(0.1)
            client.close()
            with pytest.raises(WireError, match="closed"):
                await asyncio.wait_for(goal, 15)
            feedback = client._sending and client._sending._feedback
            assert not feedback or feedback._closed
        finally:
            node.identities = real


async def test_goals_sent_at_once_share_one_announcement_wait(
        oracle: RclpyOracle, node: RosNode) -> None:
    """Fast DDS: each send_goal waited for the feedback writer's announcement on its own,
    so two goals sent at once made the feedback reader again twice as often, and the later
    one's wait went on making it again after the first goal was out: a feedback reader
    replaced with a goal's feedback on its way (the reader is made again only before any
    goal, `_renew_feedback_reader`)."""
    await oracle.acall("action_server", name="/fib", mode="slow")
    client = ActionClient(node, "/fib", FIB)
    await _announced_services(client)
    real, node.identities = node.identities, DeafCapture(node.identities)
    readers_with_a_goal_out: list[object] = []

    async def first() -> object:
        goal = await client.send_goal({"order": 12}, timeout=20)
        readers_with_a_goal_out.append(client._goal_side()._feedback)
        return goal

    async def second() -> object:  # once the first one's wait has made its reader again
        await asyncio.wait_for(_feedback_renewed(client, 2), 15)
        return await client.send_goal({"order": 3}, timeout=20)

    try:
        await asyncio.gather(first(), second())
    finally:
        node.identities = real
        readers_with_a_goal_out.append(client._goal_side()._feedback)
        client.close()
    assert client.feedback_renewed == ANNOUNCE_TRIES - 1
    assert readers_with_a_goal_out[0] is readers_with_a_goal_out[1]


async def test_a_goal_behind_another_s_announcement_wait_ends_at_its_own_deadline(
        oracle: RclpyOracle, node: RosNode) -> None:
    """Fast DDS: goals sent at once share one wait for the feedback writer's announcement,
    bounded by the deadline of the goal that waits for it. Another goal waited for its turn
    past its own deadline, until that wait was over."""
    await oracle.acall("action_server", name="/fib")
    client = ActionClient(node, "/fib", FIB)
    await _announced_services(client)
    real, node.identities = node.identities, DeafCapture(node.identities)
    try:
        first = asyncio.ensure_future(client.send_goal({"order": 3}, timeout=20))
        await asyncio.wait_for(_announcing(client), 15)
        with pytest.raises(ServiceTimeout, match="behind another goal"):
            await asyncio.wait_for(client.send_goal({"order": 3}, timeout=0.2), 15)
        assert not client._goal_side()._feedback_announced and not first.done()  # its wait goes on
        goal = await asyncio.wait_for(first, 30)
    finally:
        node.identities = real
    assert goal.accepted and client.feedback_unannounced == 1
    assert client.feedback_renewed == ANNOUNCE_TRIES - 1
    assert (await goal.result(timeout=20)).state is GoalState.SUCCEEDED
    client.close()


async def _announcing(client: ActionClient) -> None:
    """Until a goal's wait for the feedback writer's announcement is under way."""
    while not client._goal_side()._announce_lock.locked():
        await asyncio.sleep(0.01)


LONG_LIVED_GOALS = 200


@both_rmws
async def test_a_long_lived_client_keeps_a_bounded_number_of_goals(
        oracle: RclpyOracle, node: RosNode, caplog: pytest.LogCaptureFixture) -> None:
    """The bridge keeps one client per server for its whole life: each goal followed to the
    end of its feedback is let go of, so the client's goals do not grow with the goals sent.
    rclpy's status topic lists each ended goal for 15 minutes more: what it says of goals let
    go of is ignored, and quietly."""
    await oracle.acall("action_server", name="/fib_fast", period=0.0)
    client = ActionClient(node, "/fib_fast", FIB)
    tracked = []
    with caplog.at_level(logging.INFO, "rcan_rtps.ros.actions"):
        for _ in range(LONG_LIVED_GOALS):
            goal = await client.send_goal({"order": 2}, timeout=20)
            tracked.append(client.goals_tracked)
            feedback = [list(f.sequence) async for f in goal.feedback(timeout=20)]
            outcome = await goal.result(timeout=20)
            assert outcome.state is GoalState.SUCCEEDED and feedback == [fibonacci(2)]
    assert max(tracked) == 1 and client.goals_tracked == 0, \
        f"goals tracked at each send: {tracked}"
    assert not [r.message for r in caplog.records if r.name == "rcan_rtps.ros.actions"]


@both_rmws
async def test_a_stops_first_cancel_imports_nothing(
        oracle: RclpyOracle, node: RosNode, domain_id: int, jazzy_share: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A bridge lets the IDL parser and the XTypes describer go once started (issue 27): a
    stop's server-wide cancel that is its cancel service's first call, on either mapping,
    still makes that service's endpoints and cancels another client's goal with both
    modules unimportable (as under `pip install -U` beside a running bridge)."""
    await oracle.acall("action_server", name="/fib", mode="slow")
    client = ActionClient(node, "/fib", FIB)  # as a bridge's, made at start
    with RosNode("rcan_other", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as elsewhere:  # RViz, a script
        far = await ActionClient(elsewhere, "/fib", FIB).send_goal({"order": 40}, timeout=20)
        assert far.accepted
        await eventually(client.server_present, timeout=20, what="the server seen")
        assert not client._cancel_srv._pairs  # no endpoint of its cancel service made yet
        for module in START_ONLY:  # (the IDL parser and the XTypes describer among them)
            monkeypatch.setitem(sys.modules, module, None)  # importing it raises ImportError
        assert await client.cancel_all(timeout=20, server_wide=True) == 1
        assert (await far.result(timeout=30)).state is GoalState.CANCELED
