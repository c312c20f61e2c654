"""A peer on the ROS graph listing our goals on an action's status topic with states the
server never gave them (red team 31): a buggy or hostile node writing GoalStatusArray, or a
second action server of the same name, which gets every goal request too and lists the
goals with its own states. Any process on a ROS domain may write any topic; the status
topic names goals by id, and the ids are on the send_goal request topic for anyone to read.

What the bridge must keep: a goal's end is the end its server reports, and a goal whose
send gave up is cancelled whenever its server lists it running, whatever else was listed.
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

from rcan_rtps.ros import qos
from rcan_rtps.ros.action_goals import ClientGoal
from rcan_rtps.ros.action_server import ActionServer, ServerGoal
from rcan_rtps.ros.actions import STATUS_TYPE, ActionClient, GoalState
from rcan_rtps.ros.errors import WireError
from rcan_rtps.ros.participant import RosNode, RosPublisher

from .test_goal_accepted_late import GOAL, slow_server_and_tracker

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


def listing(goal_id: bytes, state: GoalState) -> dict[str, object]:
    return {"status_list": [{"goal_info": {"goal_id": {"uuid": goal_id}},
                             "status": int(state)}]}


def list_until_heard(status: RosPublisher, goal: ClientGoal, claimed: GoalState
                     ) -> Awaitable[object]:
    """Lists `goal` in `claimed` until our client has it so: whatever its status reader
    keeps, a listing that came with the server's own in one take of the reader thread is
    not lost (the last test below is about that)."""
    def heard() -> bool:
        if goal.state is not claimed:
            status.publish(listing(goal.goal_id, claimed))
        return goal.state is claimed
    return eventually(heard, what=lambda: f"the listing heard (goal {goal.state.name})")


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
        status = hostile.create_publisher("/fib/_action/status", STATUS_TYPE,
                                          qos.ACTION_STATUS)
        client = ActionClient(node, "/fib", FIB)
        try:
            await client.wait_for_server(20.0)
            await status.wait_for_subscribers(1, timeout=10)
            goal = await client.send_goal({"order": 30}, timeout=20)  # runs ~3 s
            assert goal.accepted
            await list_until_heard(status, goal, claimed)
            outcome = await goal.result(timeout=25)
            assert outcome.state is GoalState.ABORTED, outcome
            assert outcome.result is not None and list(outcome.result.sequence) == fibonacci(30)
        finally:
            client.close()
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

        def listed_until_settled() -> bool:  # (settled: listed ended, or canceling)
            if goal in tracker.client.unsettled_late():
                status.publish(listing(goal, claimed))
                return False
            return True
        await eventually(listed_until_settled, timeout=20, what="the listing heard")
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
