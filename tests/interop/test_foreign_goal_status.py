"""A peer on the ROS graph listing our goals on an action's status topic with states the
server never gave them (red team 31): a buggy or hostile node writing GoalStatusArray, or a
second action server of the same name, which gets every goal request too and lists the
goals with its own states. Any process on a ROS domain may write any topic; the status
topic names goals by id, and the ids are on the send_goal request topic for anyone to read.

What the bridge must keep: a goal's status is what its server lists — the participant
that answered its send_goal, or, before that is known, one serving the action — and another
writer's listing of it counts for nothing: it does not end the goal, keep it from a stop's
cancel, count it accepted, or give a goal whose send gave up a made-up end.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import uuid
from collections.abc import AsyncIterator, Awaitable, Iterator
from pathlib import Path
from typing import Any

import pytest
from oracle.client import OracleEnv, RclpyOracle, both_rmws, fibonacci
from waiting import eventually

from rcan_rtps.ros import action_goals, qos
from rcan_rtps.ros.action_goals import LateGoal
from rcan_rtps.ros.action_server import ActionServer, ServerGoal
from rcan_rtps.ros.actions import STATUS_TYPE, ActionClient, GoalState
from rcan_rtps.ros.errors import WireError
from rcan_rtps.ros.participant import RosNode, RosPublisher

from .bridge_rig import NAV
from .test_goal_accepted_late import GOAL, SlowServer, slow_server_and_tracker

FIB = "test_msgs/action/Fibonacci"


@pytest.fixture
def node(domain_id: int, jazzy_share: Path) -> Iterator[RosNode]:
    with RosNode("rcan_client", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as made:
        yield made


@pytest.fixture
def hostile(domain_id: int, jazzy_share: Path) -> Iterator[RosNode]:
    with RosNode("hostile", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as made:
        yield made


@contextlib.asynccontextmanager
async def client_and_forger(node: RosNode, hostile: RosNode
                            ) -> AsyncIterator[tuple[ActionClient, RosPublisher]]:
    """Our client of /fib, matched with its server, and a writer of another node on its
    status topic, matched with our client (closed after)."""
    status = hostile.create_publisher("/fib/_action/status", STATUS_TYPE, qos.ACTION_STATUS)
    client = ActionClient(node, "/fib", FIB)
    try:
        await client.wait_for_server(20.0)
        await status.wait_for_subscribers(1, timeout=10)
        yield client, status
    finally:
        client.close()


def listing(goal_id: bytes, state: GoalState) -> dict[str, object]:
    return {"status_list": [{"goal_info": {"goal_id": {"uuid": goal_id}},
                             "status": int(state)}]}


def list_until_ignored(status: RosPublisher, client: ActionClient, goal_id: bytes,
                       claimed: GoalState) -> Awaitable[object]:
    """Lists `goal_id` in `claimed` until our client has counted another writer's listing
    of its goals (ignored): whatever its status reader keeps, a listing that came with the
    server's own in one take of the reader thread is not lost
    (`test_another_writer_s_listing_does_not_replace_the_server_s_listing_unread`)."""
    def heard() -> bool:
        if client.foreign_listings == 0:
            status.publish(listing(goal_id, claimed))
        return client.foreign_listings > 0
    return eventually(heard, what="the listing heard (and ignored)")


async def list_once(status: RosPublisher, node: RosNode, goal_id: bytes,
                    claimed: GoalState) -> None:
    """Lists `goal_id` in `claimed` once, and returns when our reader has acknowledged it
    and the node has handed it to the client (its only reader on the topic)."""
    status.publish(listing(goal_id, claimed))
    assert await status.acknowledged(10)
    await node.delivered()


@both_rmws
@pytest.mark.parametrize("claimed", [GoalState.SUCCEEDED, GoalState.CANCELED])
async def test_an_end_another_writer_lists_does_not_hide_the_end_the_server_reports(
        jazzy_oracle: OracleEnv, domain_id: int, node: RosNode, hostile: RosNode,
        claimed: GoalState) -> None:
    """Another writer lists our running goal ended (succeeded, canceled); the server then
    aborts it. The result is asked for once the status topic showed an end, and with a
    Fast DDS server a reply was taken only if it named that end: the server's own reply,
    tied to our request by its related sample identity, naming ABORTED, was refused as
    another client's, asked for again every 5 s and refused each time until the result's
    timeout (the bridge showed the goal running for its hour, then `unknown`): the end the
    server reported was never shown. A reply tied to our request is ours, as with the
    Cyclone mapping (which never asked)."""
    with RclpyOracle(jazzy_oracle, "fib_server", "/", domain_id=domain_id) as server:
        await server.acall("action_server", name="/fib", mode="abort", period=0.1)
        async with client_and_forger(node, hostile) as (client, status):
            try:
                goal = await client.send_goal({"order": 30}, timeout=20)  # runs ~3 s
                assert goal.accepted
                await list_until_ignored(status, client, goal.goal_id, claimed)
                outcome = await goal.result(timeout=25)
                assert outcome.state is GoalState.ABORTED, outcome
                assert outcome.result is not None and list(outcome.result.sequence) == fibonacci(30)
            finally:
                await server.acall("ping")
        assert uuid.UUID(bytes=goal.goal_id)


@pytest.mark.parametrize("claimed", [GoalState.CANCELED, GoalState.CANCELING])
async def test_a_foreign_listing_does_not_end_the_take_back_of_a_given_up_goal(
        domain_id: int, claimed: GoalState) -> None:
    """A goal whose send gave up (the server busy) is cancelled whenever its server lists it
    running. Another writer listed it canceled (or canceling) first: the watch took that
    as the goal's end (or the server canceling it), stopped cancelling and let go of it;
    the server, accepting it a moment later, listed it running, and it ran on with nothing
    to cancel it but a stop."""
    async with slow_server_and_tracker(domain_id) as (server, tracker), \
            _hostile_node(domain_id) as hostile:
        status = hostile.create_publisher("/robot1/navigate_to_pose/_action/status",
                                          STATUS_TYPE, qos.ACTION_STATUS)
        await status.wait_for_subscribers(1, timeout=10)
        with pytest.raises(WireError):
            await tracker.send(GOAL, timeout=1.0, message_id="m-given-up")
        [goal] = server.sent
        await eventually(lambda: goal in server.cancels, what="the cancel at once")

        await list_until_ignored(status, tracker.client, goal, claimed)
        assert goal in tracker.client.unsettled_late()  # (not settled by that listing)
        server.release.set()  # the busy server gets to it: accepted, listed running
        await eventually(lambda: server.ended.get(goal) == "canceled", timeout=30,
                         what=lambda: f"the goal cancelled (now {server.ended.get(goal)})")


@contextlib.asynccontextmanager
async def _hostile_node(domain_id: int) -> AsyncIterator[RosNode]:
    with RosNode("hostile", "/robot1", domain_id=domain_id) as made:
        yield made


async def test_another_writer_s_listing_does_not_replace_the_server_s_listing_unread(
        domain_id: int, node: RosNode, hostile: RosNode, jazzy_share: Path) -> None:
    """The status topic is keyless, and its readers kept one sample (action_status_default,
    depth 1): a listing of another writer (a second server of the name, any node) that came
    before our reader thread took the server's listing of our goal's end replaced it, and
    the end was never seen (the server writes a goal's status only when it changes): a
    bridge showed the goal running until its result's timeout, an hour. Here the reader
    thread is held in another subscription's callback while both listings arrive."""
    release = asyncio.Event()

    async def execute(goal: ServerGoal) -> dict[str, Any]:
        await release.wait()
        return {"sequence": [0, 1, 1]}

    held, holding = threading.Event(), threading.Event()

    def hold(_: Any) -> None:  # on the node's reader thread
        holding.set()
        held.wait(30)

    with RosNode("fib_robot", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as robot:
        server = ActionServer(robot, "/fib", FIB, execute)
        client = ActionClient(node, "/fib", FIB)
        status = hostile.create_publisher("/fib/_action/status", STATUS_TYPE,
                                          qos.ACTION_STATUS)
        node.create_subscription("/hold", "std_msgs/msg/String", callback=hold)
        holder = hostile.create_publisher("/hold", "std_msgs/msg/String")
        try:
            goal = await client.send_goal({"order": 2}, timeout=20)
            await eventually(lambda: goal.state is GoalState.EXECUTING, what="executing")
            await holder.wait_for_subscribers(1, timeout=10)
            await status.wait_for_subscribers(1, timeout=10)
            holder.publish({"data": "hold"})
            await eventually(holding.is_set, what="the reader thread held")
            release.set()  # the server lists the goal succeeded ...
            await eventually(lambda: server._status.acknowledged(10), what="its listing in")
            status.publish({"status_list": []})  # ... and another writer lists nothing
            assert await status.acknowledged(10)
            held.set()
            assert await asyncio.wait_for(goal.ended(), 20) is GoalState.SUCCEEDED
        finally:
            held.set()
            client.close()
            await server.close()


@both_rmws
@pytest.mark.parametrize("claimed", [GoalState.SUCCEEDED, GoalState.ABORTED])
async def test_a_running_goal_another_writer_lists_ended_runs_on_and_a_stop_cancels_it(
        jazzy_oracle: OracleEnv, domain_id: int, node: RosNode, hostile: RosNode,
        claimed: GoalState) -> None:
    """Another writer lists our running goal ended. The client took it: `ended()` returned
    the made-up end, and a stop's cancel of the client's open goals (`cancel_all`: the
    bridge's stop path) skipped it as ended — the server ran it on. Only the server that
    answered the send_goal lists our goal now."""
    with RclpyOracle(jazzy_oracle, "fib_server", "/", domain_id=domain_id) as server:
        await server.acall("action_server", name="/fib", mode="slow")  # 0.2 s a step
        async with client_and_forger(node, hostile) as (client, status):
            try:
                goal = await client.send_goal({"order": 400}, timeout=20)  # runs ~80 s
                assert goal.accepted
                await eventually(lambda: goal.state is GoalState.EXECUTING, timeout=20,
                                 what=lambda: f"executing (now {goal.state.name})")
                ending = asyncio.create_task(goal.ended())
                await list_once(status, node, goal.goal_id, claimed)
                assert goal.state is GoalState.EXECUTING
                assert client.foreign_listings >= 1
                assert await client.cancel_all(10) == 1  # the stop path: it is still open
                assert await asyncio.wait_for(ending, 30) is GoalState.CANCELED
                outcome = await goal.result(timeout=30)
                assert outcome.state is GoalState.CANCELED, outcome  # the server's own end
                assert outcome.result is not None and len(outcome.result.sequence) < 400
            finally:
                await server.acall("ping")


@both_rmws
async def test_another_writer_s_listing_does_not_count_an_unanswered_goal_accepted(
        jazzy_oracle: OracleEnv, domain_id: int, node: RosNode, hostile: RosNode) -> None:
    """A goal whose send_goal reply does not come (a busy server) counted accepted when the
    status topic listed it: any writer's listing did, and the send returned a goal the
    server had not accepted. Only a participant serving the action counts now: the send
    gives up (and its goal is taken back should the server accept it late)."""
    with RclpyOracle(jazzy_oracle, "fib_server", "/", domain_id=domain_id) as server:
        # answers each goal request 4 s late
        await server.acall("action_server", name="/fib", mode="slow", accept_after=4.0)
        async with client_and_forger(node, hostile) as (client, status):
            try:
                goal_id = uuid.uuid4().bytes
                sending = asyncio.create_task(
                    client.send_goal({"order": 400}, timeout=1.5, goal_id=goal_id))
                while not sending.done():
                    await list_once(status, node, goal_id, GoalState.ACCEPTED)
                    await asyncio.sleep(0.1)
                with pytest.raises(WireError, match="no reply within the timeout"):
                    await sending
                assert client.foreign_listings >= 1
            finally:
                await server.acall("ping")


async def test_another_writer_s_listing_gives_no_given_up_goal_a_made_up_end(
        domain_id: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """A goal whose send gave up, which its (busy) server never accepted, listed succeeded
    by another writer during its watch: the client told of it as a late goal that the
    server had accepted and ended succeeded (a bridge audits it: GOAL_FINISHED, a made-up
    end of a goal that never ran). The server's participant lists nothing: nothing told."""
    monkeypatch.setattr(action_goals, "LATE_WATCH_S", 0.5)  # the watch: the send's 1.0 s
    told: list[LateGoal] = []
    with RosNode("nav_robot", "/robot1", domain_id=domain_id) as robot_node, \
            RosNode("rcan_client", "/", domain_id=domain_id) as node, \
            RosNode("hostile", "/robot1", domain_id=domain_id) as hostile:
        server = SlowServer(robot_node)  # in this process, as the client is
        client = ActionClient(node, "/robot1/navigate_to_pose", NAV)
        client.on_late_goal = told.append
        status = hostile.create_publisher("/robot1/navigate_to_pose/_action/status",
                                          STATUS_TYPE, qos.ACTION_STATUS)
        try:
            await client.wait_for_server(20.0)
            await status.wait_for_subscribers(1, timeout=10)
            with pytest.raises(WireError):
                await client.send_goal(GOAL, timeout=1.0)
            [goal] = server.sent
            assert client.watching_late(goal)
            await list_once(status, node, goal, GoalState.SUCCEEDED)
            await eventually(lambda: not client.watching_late(goal), timeout=20,
                             what="the watch's end")
            assert told == []
            assert client.foreign_listings >= 1
        finally:
            client.close()
            server.release.set()
            await server.close()


async def test_a_goal_whose_server_restarted_ends_lost(
        domain_id: int, node: RosNode, jazzy_share: Path) -> None:
    """The server restarts: a new participant serves the action before the old one has
    left (its goals are gone with it). A status writer was matched throughout, so the goal
    waited for an end nobody would list, until its result's timeout; it ends lost now (only
    its server's participant lists it)."""
    async def forever(goal: ServerGoal) -> dict[str, Any]:
        await asyncio.Event().wait()
        return {}

    client = ActionClient(node, "/fib", FIB)
    try:
        with RosNode("fib_robot", "/", domain_id=domain_id, distro="jazzy",
                     idl_paths=[jazzy_share]) as old_robot:
            old = ActionServer(old_robot, "/fib", FIB, forever)
            goal = await client.send_goal({"order": 2}, timeout=20)
            await eventually(lambda: goal.state is GoalState.EXECUTING, what="executing")
            new_robot = RosNode("fib_robot", "/", domain_id=domain_id, distro="jazzy",
                                idl_paths=[jazzy_share])
            new = ActionServer(new_robot, "/fib", FIB, forever)
            await client._status.wait_for_publishers(2, timeout=10)
            await old.close()
        try:
            assert await asyncio.wait_for(goal.ended(), 20) is GoalState.SERVER_LOST
            assert client.server_present()  # (the new server is there)
        finally:
            await new.close()
            new_robot.close()
    finally:
        client.close()


async def test_another_writer_s_listing_does_not_make_a_rejected_goal_accepted(
        jazzy_oracle: OracleEnv, domain_id: int, jazzy_share: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A Fast DDS server with the packet capture off: its send_goal reply cannot be tied to
    our request, and the status topic decides (`_confirm`): 'rejected' is ours only if the
    goal is not listed within REJECT_GRACE. Another writer listing it had a goal the
    server rejected counted accepted. Only a participant serving the action counts now."""
    monkeypatch.setenv("RCAN_RTPS_RPC_IDENTITY", "off")  # (before the domain's first node)
    with RclpyOracle(jazzy_oracle, "fib_server", "/", domain_id=domain_id) as server, \
            RosNode("rcan_client", "/", domain_id=domain_id, distro="jazzy",
                    idl_paths=[jazzy_share]) as node, \
            RosNode("hostile", "/", domain_id=domain_id, distro="jazzy",
                    idl_paths=[jazzy_share]) as hostile:
        assert node.identities is None
        await server.acall("action_server", name="/fib", mode="reject")
        async with client_and_forger(node, hostile) as (client, status):
            try:
                goal_id = uuid.uuid4().bytes
                sending = asyncio.create_task(
                    client.send_goal({"order": 5}, timeout=10, goal_id=goal_id))
                while not sending.done():
                    await list_once(status, node, goal_id, GoalState.ACCEPTED)
                goal = await sending
                assert (goal.accepted, goal.state) == (False, GoalState.REJECTED)
                assert client.foreign_listings >= 1
            finally:
                await server.acall("ping")


class _SlowResults(ActionServer):
    """Answers get_result a moment after the goal's end (another server answers first)."""

    async def _on_get_result(self, request: Any) -> Any:
        reply = await super()._on_get_result(request)
        await asyncio.sleep(0.3)
        return reply


async def test_of_two_servers_of_the_name_the_one_that_answered_the_goal_lists_it(
        domain_id: int, node: RosNode, jazzy_share: Path) -> None:
    """Two servers of one name (ours, in this process): both get the goal request. The one
    whose reply the client took has the goal; the other, slower to accept, runs it too and
    aborts it at once. Its listing ended the goal here (ABORTED) while the first still ran
    it; and its get_result reply, first in (the request reaches every server), was taken
    for the goal's result. Only the first one's listing and result count now."""
    release, second_may_accept = asyncio.Event(), asyncio.Event()

    async def until_released(goal: ServerGoal) -> dict[str, Any]:
        await release.wait()
        return {"sequence": [0, 1, 1]}

    async def at_once_aborted(goal: ServerGoal) -> dict[str, Any]:
        goal.abort()
        return {}

    async def later(_: Any) -> bool:
        await second_may_accept.wait()
        return True

    with RosNode("fib_robot", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as first_robot, \
            RosNode("fib_robot_2", "/", domain_id=domain_id, distro="jazzy",
                    idl_paths=[jazzy_share]) as second_robot:
        first = _SlowResults(first_robot, "/fib", FIB, until_released)
        second = ActionServer(second_robot, "/fib", FIB, at_once_aborted, accept=later)
        client = ActionClient(node, "/fib", FIB)
        try:
            await client.wait_for_server(20.0)
            await client._status.wait_for_publishers(2, timeout=10)
            goal = await client.send_goal({"order": 2}, timeout=20)  # the first's reply
            await eventually(lambda: goal.state is GoalState.EXECUTING, what="executing")
            second_may_accept.set()
            await eventually(lambda: getattr(second._goals.get(goal.goal_id), "state", None)
                             is GoalState.ABORTED, what="the second server's goal aborted")
            await eventually(lambda: second._status.acknowledged(10),
                             what="its listing in")
            await node.delivered()
            assert goal.state is GoalState.EXECUTING
            assert client.foreign_listings >= 1
            release.set()
            assert await asyncio.wait_for(goal.ended(), 20) is GoalState.SUCCEEDED
            outcome = await goal.result(timeout=20)
            assert outcome.state is GoalState.SUCCEEDED, outcome
            assert outcome.result is not None and list(outcome.result.sequence) == [0, 1, 1]
        finally:
            release.set()
            second_may_accept.set()
            client.close()
            await first.close()
            await second.close()
