"""Issue 12: no reply and no first feedback lost, calling real rclpy Jazzy servers (on Fast DDS
and on Cyclone DDS) from fresh clients, over and over.

A fresh client is the worst case: its endpoints are as new as discovery can be when the
request goes out. Every call is sequential (a Fast DDS server's replies reach every client's
reader, see services.py), and every reply must echo its own request.
"""

from __future__ import annotations

import asyncio
import logging
import os
import subprocess
import sys
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from contextlib import AbstractContextManager, closing, contextmanager
from pathlib import Path
from typing import Any, TypeVar

import pytest
from dropping import DeafCapture, small_buffers
from oracle.client import OracleEnv, RclpyOracle, both_rmws, fibonacci

from rcan_rtps.ros import action_goals, qos, readers, services
from rcan_rtps.ros.actions import ActionClient, GoalState
from rcan_rtps.ros.errors import ActionError, ServiceTimeout
from rcan_rtps.ros.handshake import matched_writers
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.rtps_capture import SampleIdentity
from rcan_rtps.ros.services import ServiceClient

from .cpu_load import burning_cpus

ECHO = "test_msgs/srv/BasicTypes"
FIB = "test_msgs/action/Fibonacci"
# Counts can be raised to hunt rarer losses: RCAN_RTPS_ZERO_LOSS_SCALE=5
SCALE = float(os.environ.get("RCAN_RTPS_ZERO_LOSS_SCALE", "1"))
CALLS_PER_CLIENT = int(200 * SCALE)  # fresh ServiceClient each, one node
CALLS_PER_NODE = int(25 * SCALE)  # fresh RosNode (participant) each
GOALS = int(100 * SCALE)  # fresh ActionClient each, one node
GOALS_PER_NODE = int(15 * SCALE)  # fresh RosNode each
LOADED_GOALS = int(100 * SCALE)  # fresh ActionClient each, the CPU busy
# Fresh ServiceClient each, our buffer smaller still and a stream to it: drops are frequent.
ANNOUNCED_CALLS = int(100 * SCALE)
ANNOUNCED_GOALS = int(40 * SCALE)
# At most, until a first feedback's repair comes after its goal's end: 1 goal in ~20 on a busy
# 2-core machine (10 to 35 goals in five runs), so 60 missed it about once in twenty runs (a
# clean-clone CI at e01f629); 200 goals miss it about once in 30 000 and cost ~2 min only then.
OWED_GOALS = 200
LATE_FEEDBACKS = 3  # first feedbacks handed over after their goal's end, to show it
TINY_RCVBUF = "1kB"
NOISE = "/zero_loss_noise"  # a camera's worth of traffic to our socket: 1 kB messages ...
NOISE_HZ = 3000.0  # ... as fast as the oracle's Python thread can send them
# With that many drops a reply's repair can miss a 3 s HEARTBEAT or two: lost means not in 10 s.
ANNOUNCED_TIMEOUT = 10.0
# A first feedback's wait: its goal's repair window and the longest a repair the capture shows
# owed is waited for (a Fast DDS server's: 7 + 30 s), with margin for a busy host.
WHOLE_WINDOW = max(action_goals.REPAIR_S.values()) + max(action_goals.OWED_REPAIR_S.values()) + 8
CLI_CALLS = int(20 * SCALE)  # fresh `rcan-rtps service call` processes
REPLY_TIMEOUT = 5.0


@pytest.fixture
def oracle(jazzy_oracle: OracleEnv, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_oracle, "zero_loss", "/", domain_id=domain_id) as agent:
        agent.call("echo_server", name="/echo")
        agent.call("action_server", name="/fib", period=0.01)
        yield agent


@pytest.fixture
async def node(domain_id: int, jazzy_share: Path) -> AsyncIterator[RosNode]:
    with RosNode("zero_loss_client", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as n:
        yield n


@pytest.fixture
async def noisy_node(oracle: RclpyOracle, domain_id: int, jazzy_share: Path,
                     monkeypatch: pytest.MonkeyPatch) -> AsyncIterator[RosNode]:
    """A node whose socket drops datagrams often: a 1 kB receive buffer, and a stream of
    1 kB messages from the oracle to it."""
    small_buffers(monkeypatch, TINY_RCVBUF)
    with RosNode("zero_loss_noisy", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as n:
        await oracle.acall("publisher", topic=NOISE, type="std_msgs/msg/String", qos="sensor")
        n.create_subscription(NOISE, "std_msgs/msg/String", qos.SENSOR_DATA,
                              callback=lambda message: None)
        await oracle.acall("publish_periodic", topic=NOISE, type="std_msgs/msg/String",
                           value={"data": "x" * 1000}, rate=NOISE_HZ)
        try:
            yield n
        finally:
            await oracle.acall("stop_periodic", topic=NOISE)


Client = TypeVar("Client", ServiceClient, ActionClient)
Fresh = Callable[[int], AbstractContextManager[Client]]  # the i-th call's new client


def on_node(node: RosNode, make: Callable[[RosNode], Client]) -> Fresh[Client]:
    """A new client on `node` per call, closed after it."""
    return lambda i: closing(make(node))


def on_fresh_node(prefix: str, domain_id: int, share: Path,
                  make: Callable[[RosNode], Client]) -> Fresh[Client]:
    """A new node (DDS participant) per call, with a new client on it."""
    @contextmanager
    def fresh(i: int) -> Iterator[Client]:
        with RosNode(f"{prefix}_{i}", "/", domain_id=domain_id, distro="jazzy",
                     idl_paths=[share]) as node, closing(make(node)) as client:
            yield client
    return fresh


async def each_fresh(count: int, fresh: Fresh[Client],
                     use: Callable[[Client, int], Awaitable[None]]) -> None:
    """`count` sequential calls, each from the new client `fresh` gives."""
    for i in range(count):
        with fresh(i) as client:
            await use(client, i)


def echo_client(node: RosNode) -> ServiceClient:
    return ServiceClient(node, "/echo", ECHO)


def fib_client(node: RosNode) -> ActionClient:
    return ActionClient(node, "/fib", FIB)


def burst_client(node: RosNode) -> ActionClient:
    return ActionClient(node, "/fib_burst", FIB)


def request_of(i: int) -> dict[str, object]:
    return {"string_value": f"call {i}", "int64_value": i, "uint32_value": 7 * i}


class Tally:
    """Outcomes of repeated calls: lost (timed out) and misattributed (another's reply)."""

    def __init__(self, timeout: float = REPLY_TIMEOUT) -> None:
        self.timeout = timeout
        self.lost: list[int] = []
        self.wrong: list[tuple[int, str]] = []
        self.slow: list[int] = []  # answered, but only after a repair (over a second)

    async def call(self, client: ServiceClient, i: int) -> None:
        start = time.monotonic()
        try:
            reply = await client.call(request_of(i), timeout=self.timeout)
        except ServiceTimeout:
            self.lost.append(i)
            return
        if time.monotonic() - start > 1.0:
            self.slow.append(i)
        if (reply.string_value, reply.int64_value, reply.uint32_value) != \
                (f"call {i}", i, 7 * i):
            self.wrong.append((i, reply.string_value))

    def assert_clean(self, total: int) -> None:
        assert (self.lost, self.wrong) == ([], []), \
            f"of {total} calls: {len(self.lost)} lost {self.lost}, " \
            f"{len(self.wrong)} misattributed {self.wrong}"


@both_rmws
async def test_fresh_service_clients_lose_no_reply(oracle: RclpyOracle, node: RosNode) -> None:
    tally = Tally()
    await each_fresh(CALLS_PER_CLIENT, on_node(node, echo_client), tally.call)
    tally.assert_clean(CALLS_PER_CLIENT)
    served = await oracle.acall("service_requests", name="/echo")
    assert served == [f"call {i}" for i in range(CALLS_PER_CLIENT)]


@both_rmws
async def test_fresh_nodes_lose_no_reply(oracle: RclpyOracle, domain_id: int,
                                         jazzy_share: Path) -> None:
    tally = Tally()
    fresh = on_fresh_node("zero_loss", domain_id, jazzy_share, echo_client)
    await each_fresh(CALLS_PER_NODE, fresh, tally.call)
    tally.assert_clean(CALLS_PER_NODE)


class GoalTally:
    """Outcomes of repeated goals: first feedback missing, wrong result."""

    def __init__(self, order: Callable[[int], int] = lambda i: 2 + i % 4,
                 feedback_timeout: float = 10.0) -> None:
        self.order = order  # by default the result tells one goal from the next
        self.feedback_timeout = feedback_timeout
        self.dropped: int | None = 0  # at our DDS sockets while the goals ran (None: unknown)
        self.no_first_feedback: list[int] = []
        self.wrong: list[tuple[int, object]] = []

    async def run(self, client: ActionClient, i: int) -> None:
        order = self.order(i)
        drops = client.node.udp_drops()
        try:
            await self._run(client, i, order)
        finally:
            now = client.node.udp_drops()
            if drops is None or now is None or self.dropped is None:
                self.dropped = None
            else:
                self.dropped += now - drops

    async def _run(self, client: ActionClient, i: int, order: int) -> None:
        goal = await client.send_goal({"order": order}, timeout=10)
        assert goal.accepted, f"goal {i} not accepted"
        first = await _first_feedback(goal, self.feedback_timeout)
        outcome = await goal.result(timeout=10)
        if first != fibonacci(2):  # the server's first feedback is [0, 1, 1]
            self.no_first_feedback.append(i)
        if outcome.state is not GoalState.SUCCEEDED or outcome.result is None or \
                list(outcome.result.sequence) != fibonacci(order):
            self.wrong.append((i, outcome))

    def assert_clean(self, total: int) -> None:
        dropped = "unknown" if self.dropped is None else self.dropped
        assert (self.no_first_feedback, self.wrong) == ([], []), \
            f"of {total} goals: first feedback lost for {self.no_first_feedback}, " \
            f"wrong results {self.wrong}; datagrams dropped at our sockets meanwhile: {dropped}"


async def _first_feedback(goal: object, timeout: float = 10.0) -> list[int] | None:
    async for feedback in goal.feedback(timeout=timeout):  # type: ignore[attr-defined]
        return list(feedback.sequence)
    return None


@both_rmws
async def test_fresh_action_clients_get_every_first_feedback(oracle: RclpyOracle,
                                                             node: RosNode) -> None:
    tally = GoalTally()
    await each_fresh(GOALS, on_node(node, fib_client), tally.run)
    tally.assert_clean(GOALS)


@both_rmws
async def test_every_first_feedback_under_cpu_load(oracle: RclpyOracle, node: RosNode) -> None:
    """Issue 27: under load the goal's terminal status could be handed over before the
    feedback sent ahead of it, and `feedback()` ended empty. Order 2 and no pause: one feedback,
    then at once the end: both come in one wake-up of our reader thread as often as can be."""
    await oracle.acall("action_server", name="/fib_burst", period=0.0)
    tally = GoalTally(order=lambda i: 2)
    with burning_cpus() as burners:
        await each_fresh(LOADED_GOALS, on_node(node, burst_client), tally.run)
    print(f"{oracle.rmw}, {burners} CPU burners: {LOADED_GOALS} goals, "
          f"{len(tally.no_first_feedback)} first feedbacks lost, {len(tally.wrong)} wrong results")
    tally.assert_clean(LOADED_GOALS)


@both_rmws
async def test_fresh_nodes_get_every_first_feedback(oracle: RclpyOracle, domain_id: int,
                                                    jazzy_share: Path) -> None:
    tally = GoalTally()
    fresh = on_fresh_node("zero_loss_goal", domain_id, jazzy_share, fib_client)
    await each_fresh(GOALS_PER_NODE, fresh, tally.run)
    tally.assert_clean(GOALS_PER_NODE)


@both_rmws
async def test_a_reply_is_not_lost_when_the_servers_first_heartbeat_was_dropped(
        oracle: RclpyOracle, noisy_node: RosNode, caplog: pytest.LogCaptureFixture) -> None:
    """A Fast DDS reply writer announces itself to a new reader with one GAP+HEARTBEAT. When
    our socket dropped it, the next one came with the reply, ahead of its DATA, and Cyclone
    took it as the reader's start: the reply was dropped as history and ACKed, lost for good
    (docs/design/zero-loss.md). The client waits to hear that HEARTBEAT before its first
    request, and makes its reader again when it does not come; when it gave up (four readers
    unheard), the reply's DATA still reached our socket, and the call takes it from the
    packet capture. No reply may be lost."""
    drops = noisy_node.udp_drops()
    assert drops is not None, "the kernel's drop counts are needed (Linux /proc)"
    caplog.set_level(logging.DEBUG, logger="rcan_rtps.ros.services")
    calls, renewed, unannounced, from_capture = Tally(ANNOUNCED_TIMEOUT), 0, 0, 0
    with burning_cpus() as burners:
        for i in range(ANNOUNCED_CALLS):
            with closing(echo_client(noisy_node)) as client:
                pair = await client.wait_for_service(REPLY_TIMEOUT)
                await calls.call(client, i)
                renewed += pair.renewed
                unannounced += pair.unannounced
                from_capture += pair.from_capture
    dropped = (noisy_node.udp_drops() or 0) - drops
    print(f"{oracle.rmw}, {burners} CPU burners, {TINY_RCVBUF} receive buffer, {NOISE_HZ:.0f} Hz "
          f"to it: {ANNOUNCED_CALLS} calls from fresh clients, {dropped} datagrams dropped at "
          f"our sockets, {len(calls.lost)} replies lost, {len(calls.slow)} sent again (over 1 s), "
          f"{renewed} reply readers made again, {unannounced} requests sent unannounced, "
          f"{from_capture} replies taken from the packet capture")
    for record in caplog.records:
        if "goes out without it" in record.getMessage():
            print(record.getMessage())
    assert dropped > 0, "no datagram was dropped at our sockets: nothing was shown"
    calls.assert_clean(ANNOUNCED_CALLS)


@pytest.mark.parametrize("oracle_rmw", ["fastrtps"])
async def test_a_reply_our_reader_never_delivers_is_taken_from_the_capture(
        oracle: RclpyOracle, node: RosNode) -> None:
    """A reply Cyclone dropped as history never reaches our reader, though its DATA reached
    our socket: the call takes it from the packet capture — its own reply, never the one to
    another client's request that reaches the same reader meanwhile (a Fast DDS server sends
    every reply to every client's reader). Our reader is made deaf here: nothing it takes
    is delivered."""
    with closing(echo_client(node)) as ours, closing(echo_client(node)) as other:
        pair = await ours.wait_for_service(REPLY_TIMEOUT)
        await other.wait_for_service(REPLY_TIMEOUT)
        node.unwatch(pair.watch)
        theirs = asyncio.create_task(other.call(request_of(1), timeout=REPLY_TIMEOUT))
        for i in (2, 3):
            reply = await ours.call(request_of(i), timeout=ANNOUNCED_TIMEOUT)
            assert (reply.string_value, reply.int64_value) == (f"call {i}", i)
        assert (await theirs).string_value == "call 1"
        assert pair.from_capture == 2


@pytest.mark.parametrize("oracle_rmw", ["fastrtps"])
async def test_a_fragmented_reply_our_reader_never_delivers_is_put_together_from_the_capture(
        oracle: RclpyOracle, node: RosNode) -> None:
    """The same, for a reply Fast DDS sends in DATA_FRAGs (a 200 kB string): its pieces are
    put together from the capture, and the call gets it whole; the capture then holds
    nothing."""
    with closing(echo_client(node)) as ours:
        pair = await ours.wait_for_service(REPLY_TIMEOUT)
        node.unwatch(pair.watch)
        big = "".join(f"{i:07d}" for i in range(200_000 // 7))
        reply = await ours.call({"string_value": big, "int64_value": 5},
                                timeout=ANNOUNCED_TIMEOUT)
        assert (reply.string_value, reply.int64_value) == (big, 5)
        assert pair.from_capture == 1
        assert node.identities is not None and node.identities._replies.held == 0


@pytest.mark.parametrize("oracle_rmw", ["fastrtps"])
async def test_a_call_cancelled_or_timed_out_while_its_reply_waits_in_the_capture(
        oracle: RclpyOracle, node: RosNode) -> None:
    """A call cancelled while its reply waits in the capture for its turn, or timed out, leaves
    nothing expected or kept behind, and its reply never reaches the next call."""
    capture = node.identities
    assert capture is not None
    with closing(echo_client(node)) as ours:
        pair = await ours.wait_for_service(REPLY_TIMEOUT)
        node.unwatch(pair.watch)
        call = asyncio.create_task(ours.call(request_of(1), timeout=ANNOUNCED_TIMEOUT))
        for _ in range(500):  # (at most 5 s)
            if capture.captured_reply(SampleIdentity(pair.writer_guid, 1)) is not None:
                break
            await asyncio.sleep(0.01)
        else:
            pytest.fail("the reply never reached the capture")
        # past the first look: the call has found it and gives the reader its turn
        await asyncio.sleep(services.CAPTURE_REPLY_AFTER + services.CAPTURE_SETTLE / 4)
        call.cancel()
        with pytest.raises(asyncio.CancelledError):
            await call
        assert (dict(capture._replies._expected), capture._replies.held) == ({}, 0)
        with pytest.raises(ServiceTimeout):
            await ours.call(request_of(2), timeout=0.1)
        assert (dict(capture._replies._expected), capture._replies.held) == ({}, 0)
        reply = await ours.call(request_of(3), timeout=ANNOUNCED_TIMEOUT)
        assert (reply.string_value, reply.int64_value) == ("call 3", 3)
        assert pair.from_capture == 1


@both_rmws
async def test_a_first_feedback_is_not_lost_when_the_feedback_writer_s_first_heartbeat_was_dropped(
        oracle: RclpyOracle, noisy_node: RosNode) -> None:
    """The same announcement, for an action's feedback: a fresh client's feedback reader hears
    the Fast DDS feedback writer's first HEARTBEAT before its first goal, or is made again;
    when it gave up (four readers unheard), or Cyclone dropped the first feedback as history
    all the same, its DATA still reached our socket, and the goal takes it from the packet
    capture."""
    await oracle.acall("action_server", name="/fib_burst", period=0.0)
    # (the repair window after the goal's end, REPAIR_S, within the wait for feedback)
    tally = GoalTally(order=lambda i: 2, feedback_timeout=WHOLE_WINDOW)
    renewed = unannounced = from_capture = waited = 0

    async def run(client: ActionClient, i: int) -> None:
        nonlocal renewed, unannounced, from_capture, waited
        try:
            await tally.run(client, i)
        finally:
            renewed += client.feedback_renewed
            unannounced += client.feedback_unannounced
            from_capture += client.feedback_from_capture
            waited += client.repairs_waited

    with burning_cpus() as burners:
        await each_fresh(ANNOUNCED_GOALS, on_node(noisy_node, burst_client), run)
    print(f"{oracle.rmw}, {burners} CPU burners, {TINY_RCVBUF} receive buffer, {NOISE_HZ:.0f} Hz "
          f"to it: {ANNOUNCED_GOALS} goals from fresh clients, {tally.dropped} datagrams dropped "
          f"at our sockets, {len(tally.no_first_feedback)} first feedbacks lost, "
          f"{len(tally.wrong)} wrong results, {renewed} feedback readers made again, "
          f"{unannounced} clients sent goals unannounced, {from_capture} feedbacks taken from "
          f"the packet capture, {waited} windows kept open for a repair still owed")
    assert tally.dropped, "no datagram was dropped at our sockets: nothing was shown"
    assert tally.wrong == [], f"wrong results: {tally.wrong}"
    # Without the wait 18 % of first feedbacks were lost here (7 of 40 expected). With it, the
    # capture, our reader asking again every 100 ms and the window kept open while the
    # capture shows the repair owed (a goal whose writer's HEARTBEATs were all dropped at our
    # socket for 10.9 s after its end was lost before; docs/design/zero-loss.md, "Heartbeats
    # dropped for the whole window"), what is left is a client that gave up hearing its
    # writer's announcement: a HEARTBEAT dropped ahead of the feedback's DATA can make Cyclone
    # take that feedback as history. None lost beyond those.
    assert len(tally.no_first_feedback) <= unannounced, \
        f"of {ANNOUNCED_GOALS} goals, first feedback lost for {tally.no_first_feedback}, with " \
        f"{unannounced} clients sending goals unannounced"


@pytest.mark.parametrize("oracle_rmw", ["fastrtps"])
async def test_a_first_feedback_repaired_after_the_window_still_comes(
        oracle: RclpyOracle, noisy_node: RosNode, monkeypatch: pytest.MonkeyPatch) -> None:
    """A first feedback dropped at our socket comes again only after a HEARTBEAT of its
    writer reaches our socket (a Fast DDS writer's come every 3 s), which the noise may drop
    too, past any fixed window: the window stays open while the packet capture shows the
    repair owed. Here the window is 0, so every repair after the goal's end is one the capture
    kept it open for; goals go out until one was (at most OWED_GOALS)."""
    monkeypatch.setattr(action_goals, "REPAIR_S", dict.fromkeys(action_goals.REPAIR_S, 0.0))
    await oracle.acall("action_server", name="/fib_burst", period=0.0)
    tally, waited, unannounced = GoalTally(order=lambda i: 2, feedback_timeout=WHOLE_WINDOW), 0, 0
    with burning_cpus():
        for i in range(OWED_GOALS):
            with closing(burst_client(noisy_node)) as client:
                await tally.run(client, i)
                waited += getattr(client, "repairs_waited", 0)
                unannounced += client.feedback_unannounced
            if waited or len(tally.no_first_feedback) > unannounced:
                break
    print(f"{i + 1} goals, {waited} windows kept open for a repair owed, "
          f"{len(tally.no_first_feedback)} first feedbacks lost, {unannounced} unannounced")
    assert len(tally.no_first_feedback) <= unannounced, \
        f"first feedback lost for {tally.no_first_feedback} ({unannounced} unannounced)"
    assert waited, f"no repair came after the end of {OWED_GOALS} goals: nothing was shown"


def slow_feedback_hand_over(monkeypatch: pytest.MonkeyPatch, delay: float) -> None:
    """The node's reader thread sleeps `delay` before it takes from a feedback reader that
    has samples: a busy host's late hand-over, every time."""
    service = readers.ReaderThread._service_reader

    def late(self: readers.ReaderThread, watch: Any) -> None:
        if "feedback" in watch.label and watch.condition.triggered:
            time.sleep(delay)
        service(self, watch)
    monkeypatch.setattr(readers.ReaderThread, "_service_reader", late)


@pytest.mark.parametrize("oracle_rmw", ["fastrtps"])
async def test_a_repair_taken_as_the_window_closes_is_still_handed_over(
        oracle: RclpyOracle, noisy_node: RosNode, monkeypatch: pytest.MonkeyPatch) -> None:
    """The packet capture shows a repaired feedback taken (our reader's ACKNACK after it) as
    soon as Cyclone has it; the reader thread hands it to the goal later. A window closed once
    the capture showed nothing owed lost it (2 of 900 goals in the noisy conditions, 10 of 450
    with a 50 ms late hand-over). Here every hand-over of feedback is 600 ms late (past two of
    the looks at the capture, OWED_POLL apart) and the window 0: goals go out until three first
    feedbacks came after their goal's end (at most OWED_GOALS), and each must come."""
    monkeypatch.setattr(action_goals, "REPAIR_S", dict.fromkeys(action_goals.REPAIR_S, 0.0))
    slow_feedback_hand_over(monkeypatch, 0.6)
    await oracle.acall("action_server", name="/fib_burst", period=0.0)
    lost, late, unannounced = [], 0, 0
    with burning_cpus():
        for i in range(OWED_GOALS):
            with closing(burst_client(noisy_node)) as client:
                goal = await client.send_goal({"order": 2}, timeout=10)
                first = await _first_feedback(goal, timeout=WHOLE_WINDOW)
                assert (await goal.result(timeout=10)).state is GoalState.SUCCEEDED
                unannounced += client.feedback_unannounced
            if first != fibonacci(2):
                lost.append(i)
            elif goal.end_settled.is_set():  # it came after the goal's end had settled
                late += 1
            if late >= LATE_FEEDBACKS or len(lost) > unannounced:
                break
    print(f"{i + 1} goals, {late} first feedbacks handed over after the end, "
          f"{len(lost)} lost, {unannounced} unannounced")
    assert len(lost) <= unannounced, f"first feedback lost for {lost} ({unannounced} unannounced)"
    assert late >= LATE_FEEDBACKS, \
        f"{late} first feedbacks came after the end of {OWED_GOALS} goals: too few to show it"


def status_shows_only(client: ActionClient, shown: Callable[[Any], bool]) -> None:
    """Our client's status topic shows only the statuses `shown` keeps: the others dropped at
    our socket, as a whole window of the status writer's samples and HEARTBEATs was under the
    noise (docs/design/zero-loss.md, "The goal's status late")."""
    sender = client._goal_side()  # (made by wait_for_server: it takes the status)
    take = sender.on_status

    def on_status(array: Any) -> None:
        array.status_list = [s for s in array.status_list if shown(s)]
        take(array)
    sender.on_status = on_status  # type: ignore[method-assign]


def never_listing(client: ActionClient) -> None:
    status_shows_only(client, lambda status: False)


# s a late status's goal waits for its result: 1 s more than `action_goals.LAST_ASK_S`, so the
# result is asked for before the wait runs out
LATE_STATUS_WAIT = 6.0
# the status topic lists the goal, but never shows it ended
NOT_ENDED = lambda status: not GoalState(int(status.status)).terminal  # noqa: E731


@both_rmws
@pytest.mark.parametrize("shown", [lambda status: False, NOT_ENDED], ids=["unlisted", "unended"])
async def test_a_goal_whose_status_is_late_is_accepted_and_ended_by_replies_tied_to_it(
        oracle: RclpyOracle, node: RosNode, shown: Callable[[Any], bool]) -> None:
    """A send_goal reply tied to our request (the Cyclone mapping's header; the related
    sample identity the capture reads for Fast DDS) is ours: the goal is accepted without its
    listing on the status topic; its result, asked for at once when the listing is late, or
    before the wait for its end runs out (LAST_ASK_S), tells its end. Before, an unlisted Fast
    DDS goal failed ("never appeared on its status topic") and the others' results waited for
    the status topic's end in vain ("goal still ACCEPTED")."""
    with closing(fib_client(node)) as client:
        await client.wait_for_server(REPLY_TIMEOUT)
        status_shows_only(client, shown)
        goal = await client.send_goal({"order": 3}, timeout=REPLY_TIMEOUT)
        assert goal.accepted
        outcome = await goal.result(timeout=LATE_STATUS_WAIT)
        assert outcome.state is GoalState.SUCCEEDED and outcome.result is not None
        assert list(outcome.result.sequence) == fibonacci(3)
        assert goal.state is GoalState.SUCCEEDED


@pytest.mark.parametrize("oracle_rmw", ["fastrtps"])
async def test_without_the_capture_a_goal_never_listed_is_not_taken_as_accepted(
        oracle: RclpyOracle, domain_id: int, jazzy_share: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Fails closed: a Fast DDS reply whose identity cannot be read may be another client's,
    so "accepted" still needs the status topic to list the goal."""
    monkeypatch.setenv("RCAN_RTPS_RPC_IDENTITY", "off")
    with RosNode("zero_loss_untied", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as untied, closing(fib_client(untied)) as client:
        await client.wait_for_server(REPLY_TIMEOUT)
        never_listing(client)
        with pytest.raises(ActionError, match="never appeared on its status topic"):
            await client.send_goal({"order": 3}, timeout=2.5)


@pytest.mark.parametrize("oracle_rmw", ["fastrtps"])
async def test_a_feedback_our_reader_never_delivers_is_taken_from_the_capture(
        oracle: RclpyOracle, node: RosNode) -> None:
    """A feedback Cyclone dropped as history never reaches our reader, though its DATA reached
    our socket: the goal takes it from the packet capture, in the order the server sent it —
    its own feedback, never that of another client's goal, which reaches the same reader
    meanwhile. Our reader is made deaf here (what it takes is held back); its copies, handed
    over late, are not yielded again."""
    await oracle.acall("action_server", name="/fib_burst", period=0.0)
    with closing(burst_client(node)) as ours, closing(burst_client(node)) as other:
        await ours.wait_for_server(REPLY_TIMEOUT)
        await other.wait_for_server(REPLY_TIMEOUT)
        held: list[Any] = []
        sender = ours._goal_side()  # (made by wait_for_server: it takes the feedback)
        deliver, sender._on_feedback = sender._on_feedback, held.append  # type: ignore[method-assign]
        theirs = await other.send_goal({"order": 6}, timeout=10)
        goal = await ours.send_goal({"order": 3}, timeout=10)
        feedback = goal.feedback(timeout=30)
        got = [await anext(feedback)]
        assert any(bytes(m.goal_id.uuid) == goal.goal_id for m in held), "the reader took none"
        for message in held:  # the reader's own copies, late
            deliver(message)
        got += [f async for f in feedback]
        assert [list(f.sequence) for f in got] == [fibonacci(2), fibonacci(3)]
        assert ours.feedback_from_capture == 2
        assert len([f async for f in theirs.feedback(timeout=30)]) == 5
        assert node.identities is not None and node.identities._replies.held == 0


@pytest.mark.parametrize("oracle_rmw", ["fastrtps"])
async def test_a_first_feedback_our_reader_dropped_comes_before_the_next(
        oracle: RclpyOracle, node: RosNode) -> None:
    """Cyclone drops as history what came before the HEARTBEAT it takes as a fresh reader's
    start, and delivers what comes after: the goal's first feedback missing, the next ones
    there. The first is taken from the capture and yielded first. (Here our reader's first
    feedback sample is held back for good.)"""
    await oracle.acall("action_server", name="/fib_burst", period=0.0)
    with closing(burst_client(node)) as ours:
        await ours.wait_for_server(REPLY_TIMEOUT)
        sender = ours._goal_side()  # (made by wait_for_server: it takes the feedback)
        deliver, dropped = sender._on_feedback, []

        def drop_the_first(message: Any) -> None:
            if dropped:
                deliver(message)
            else:
                dropped.append(message)
        sender._on_feedback = drop_the_first  # type: ignore[method-assign]
        goal = await ours.send_goal({"order": 4}, timeout=10)
        got = [list(f.sequence) async for f in goal.feedback(timeout=30)]
        assert [list(m.feedback.sequence) for m in dropped] == [fibonacci(2)]
        assert got == [fibonacci(2), fibonacci(3), fibonacci(4)]
        assert ours.feedback_from_capture == 1


@both_rmws
def test_fresh_cli_calls_lose_no_reply(oracle: RclpyOracle, domain_id: int,
                                       jazzy_share: Path) -> None:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    lost: list[tuple[int, str]] = []
    for i in range(CLI_CALLS):
        done = subprocess.run(
            [sys.executable, "-m", "rcan_rtps", "--idl-path", str(jazzy_share), "service",
             "call", "/echo", ECHO, f"{{string_value: cli {i}, int64_value: {i}}}",
             "--timeout", str(REPLY_TIMEOUT)],
            capture_output=True, text=True, env=env, timeout=60)
        if done.returncode != 0 or f"string_value: cli {i}\n" not in done.stdout:
            lost.append((i, done.stderr.strip()[-200:]))
    assert lost == [], f"of {CLI_CALLS} CLI calls, {len(lost)} failed: {lost}"


# A Cyclone writer's first HEARTBEAT to our new feedback reader made late: the server's writers
# send a HEARTBEAT at most once a second (the heartbeat timer a busy server runs late), and
# our reader's pre-emptive ACKNACK, which would ask for one sooner, is put off past the goal.
SERVER_LATE_HEARTBEAT = ('<Internal><HeartbeatInterval min="5 ms" minsched="1 s" max="8 s">'
                         '1 s</HeartbeatInterval></Internal>')
OUR_LATE_ACKNACK = '<Internal><PreEmptiveAckDelay>2 s</PreEmptiveAckDelay></Internal>'
HEARTBEAT_TIMERS_LAPSE = 1.3  # s: past the server's heartbeat interval
LATE_SYNC_GOALS = int(6 * SCALE)
FEEDBACK = "/fib_burst/_action/feedback"
FEEDBACK_TYPE = "test_msgs/action/Fibonacci_FeedbackMessage"


def cyclone_guid(guid: bytes) -> str:
    """A GUID as Cyclone's trace writes it (four 32-bit words in hex)."""
    return ":".join(f"{int.from_bytes(guid[i:i + 4], 'big'):x}" for i in range(0, 16, 4))


@pytest.mark.parametrize("oracle_rmw", ["cyclonedds"])
async def test_no_first_feedback_reaches_a_reader_that_has_not_heard_its_cyclone_writer(
        jazzy_oracle: OracleEnv, domain_id: int, jazzy_share: Path, tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Cyclone drops a Cyclone writer's DATA while it has seen no HEARTBEAT of that writer
    since a reliable reader of ours matched it ("no heartbeat seen yet", `ddsi_receive.c`);
    the sample comes again only once the writer has heard our NACK, on a busy machine after
    the goal's end, when feedback() had ended (docs/design/zero-loss.md). The writer sends
    that HEARTBEAT when it matches our reader, from its timer, no sooner than its heartbeat
    interval allows: here another process's reader of the feedback topic matched just before
    ours, so it comes a second late, and the first feedback is written before it. Our client
    now hears it in the packet capture before the first goal goes out, or makes its reader
    again. Cyclone's trace of our process tells whether it dropped a feedback."""
    trace = tmp_path / "cyclone.trace"
    monkeypatch.setenv("CYCLONEDDS_URI", f"<Tracing><Category>trace</Category><OutputFile>"
                       f"{trace}</OutputFile></Tracing>{OUR_LATE_ACKNACK}")
    env = {"CYCLONEDDS_URI": SERVER_LATE_HEARTBEAT}
    tally, renewed, writers = GoalTally(order=lambda i: 2), 0, set()
    with RclpyOracle(jazzy_oracle, "late_heartbeat", "/", domain_id=domain_id,
                     env=env) as server, \
            RclpyOracle(jazzy_oracle, "other_reader", "/", domain_id=domain_id,
                        env=env) as other, \
            RosNode("late_heartbeat_client", "/", domain_id=domain_id, distro="jazzy",
                    idl_paths=[jazzy_share]) as node:
        await server.acall("action_server", name="/fib_burst", period=0.0)
        for i in range(LATE_SYNC_GOALS):
            await asyncio.sleep(HEARTBEAT_TIMERS_LAPSE)  # the handshake's writers answer at once
            await other.acall("subscribe", topic=FEEDBACK, type=FEEDBACK_TYPE)
            await other.acall("wait_matched", topic=FEEDBACK)
            with closing(burst_client(node)) as client:
                try:
                    await tally.run(client, i)
                finally:
                    renewed += client.feedback_renewed
                    feedback = client._sending and client._sending._feedback
                    if feedback:
                        writers |= set(matched_writers(feedback.reader).values())
            await other.acall("unsubscribe", topic=FEEDBACK)
    names = {cyclone_guid(w) for w in writers}
    dropped = [line for line in trace.read_text(errors="replace").splitlines()
               if "no heartbeat seen yet" in line and any(f"DATA({n} " in line for n in names)]
    print(f"{LATE_SYNC_GOALS} goals, feedback writer's first HEARTBEAT late: "
          f"{len(dropped)} feedback samples dropped by Cyclone, "
          f"{len(tally.no_first_feedback)} first feedbacks lost, {renewed} readers made again")
    assert names, "no feedback writer was matched"
    assert dropped == [], f"Cyclone dropped feedback before a HEARTBEAT: {dropped}"
    tally.assert_clean(LATE_SYNC_GOALS)
    # The writer's HEARTBEAT did come late: the client heard none within ANNOUNCE_WAIT.
    assert renewed > 0, "every feedback writer's HEARTBEAT came at once: nothing was shown"


@both_rmws
async def test_a_goal_sent_before_the_sync_was_heard_waits_for_its_feedback_to_be_repaired(
        oracle: RclpyOracle, node: RosNode, monkeypatch: pytest.MonkeyPatch) -> None:
    """Where no HEARTBEAT of a Cyclone feedback writer could be heard before the first goal
    (no packet capture, or none heard after ANNOUNCE_TRIES readers), a first feedback may have
    been dropped for want of one, and comes only once the writer has repaired it: feedback()
    of a goal none of whose feedback has come by its end then waits the repair time after
    it, as after a datagram dropped at our socket, until the server leaves. A goal whose
    feedback came does not: the reader takes a writer's samples in order, so its first
    feedback came too (every fresh client waited 2 s more without a capture: macOS,
    RCAN_RTPS_RPC_IDENTITY=off). A Fast DDS writer's samples are taken before any
    HEARTBEAT: no such wait. (The repair time is made long, so that waiting it out shows.)"""
    monkeypatch.setattr(action_goals, "REPAIR_S", dict.fromkeys(action_goals.REPAIR_S, 600.0))
    await oracle.acall("action_server", name="/fib_burst", period=0.0)
    client = await deaf_burst_client(node)
    assert client.feedback_unannounced == 1  # nothing heard after ANNOUNCE_TRIES readers
    # A Fast DDS writer's samples are taken before any HEARTBEAT: nothing to wait for.
    assert client.feedback_in_sync() is (oracle.rmw == "fastrtps")
    # Order 2: one feedback, before the end; it comes, and feedback() ends with the goal.
    fed = await client.send_goal({"order": 2}, timeout=20)
    assert fed._unsynced is (oracle.rmw == "cyclonedds")
    got = [list(f.sequence) async for f in _within(fed.feedback(), 60)]
    assert got[:1] == [fibonacci(2)]
    if oracle.rmw == "fastrtps":  # (whether it waits then depends on drops at our socket)
        client.close()
        return
    # A Cyclone writer's sample taken: in sync. Another fresh client, still unsynced, whose
    # goal of order 1 has no feedback: it waits the repair time for what may be on its way.
    client.close()
    client = await deaf_burst_client(node)
    unfed = await client.send_goal({"order": 1}, timeout=20)
    assert unfed._unsynced
    following = asyncio.create_task(_drain(unfed.feedback()))
    assert (await unfed.result(timeout=20)).state is GoalState.SUCCEEDED
    await node.delivered()
    await asyncio.sleep(0.5)  # feedback() has looked at the goal's end
    assert not following.done()
    client.close()  # (as the server leaving does: nothing more can come)
    with pytest.raises(ActionError):
        await asyncio.wait_for(following, 30)


async def deaf_burst_client(node: RosNode) -> ActionClient:
    """A fresh client of /fib_burst, ready, whose wait heard no feedback writer's HEARTBEAT
    (its capture deaf to them while it waited: it made its reader again and gave up)."""
    real, node.identities = node.identities, DeafCapture(node.identities)
    try:
        client = burst_client(node)
        await client.wait_for_server(20)
    finally:
        node.identities = real
    return client


async def _within(feedback: AsyncIterator[Any], timeout: float) -> AsyncIterator[Any]:
    """`feedback`'s items, failing when it has not ended within `timeout` (loop time)."""
    deadline = asyncio.get_running_loop().time() + timeout
    while True:
        try:
            yield await asyncio.wait_for(anext(feedback),
                                         deadline - asyncio.get_running_loop().time())
        except StopAsyncIteration:
            return


async def _drain(feedback: AsyncIterator[object]) -> None:
    async for _ in feedback:
        pass


@pytest.mark.parametrize("oracle_rmw", ["cyclonedds"])
async def test_a_restarted_cyclone_server_s_feedback_writer_is_not_taken_for_in_sync(
        jazzy_oracle: OracleEnv, domain_id: int, jazzy_share: Path) -> None:
    """A long-lived client (the bridge's) heard its server's feedback writer and took its
    feedback; the server restarts (nav2 brought up again): its new feedback writer starts
    out of sync with our reader like any (handshake.py, 4.), and was neither heard nor has
    our reader taken anything from it. feedback_in_sync() said True (one flag for the client's
    life), so the new server's first goal would not wait for a dropped first feedback to be
    repaired. It is in sync once a sample of that writer was taken."""
    with RosNode("restart_client", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as node, closing(burst_client(node)) as client:
        for run in ("first", "second"):
            with RclpyOracle(jazzy_oracle, f"{run}_server", "/", domain_id=domain_id) as server:
                await server.acall("action_server", name="/fib_burst", period=0.0)
                await client.wait_for_server(20)
                feedback = client._goal_side()._feedback
                assert feedback is not None
                while len(matched_writers(feedback.reader)) != 1:  # the old one gone
                    await asyncio.sleep(0.05)
                if run == "second":
                    assert not client.feedback_in_sync(), "a writer never heard nor taken from"
                goal = await client.send_goal({"order": 2}, timeout=20)
                got = [list(f.sequence) async for f in goal.feedback(timeout=30)]
                assert got[:1] == [fibonacci(2)]
                assert client.feedback_in_sync()
            while client.server_present():
                await asyncio.sleep(0.05)


@pytest.mark.parametrize("oracle_rmw", ["fastrtps"])
async def test_a_goal_s_looks_in_the_capture_are_off_the_event_loop(
        oracle: RclpyOracle, node: RosNode, monkeypatch: pytest.MonkeyPatch) -> None:
    """A goal looks in the packet capture for its feedback at its first feedback
    (`feedback_before`) and, when none came, at its end (`captured_feedback`, which reads the
    capture to its end every time): each look may parse up to MISS_BUDGET bytes (250-440 ms
    of small datagrams, bench/capture_lag.py), so each is made in a worker thread, as a late
    reply's is, never on the event loop a stop needs."""
    await oracle.acall("action_server", name="/fib_burst", period=0.0)
    capture = node.identities
    assert capture is not None
    looked_on: dict[str, list[int]] = {"feedback_before": [], "captured_feedback": []}
    for name, threads in looked_on.items():
        monkeypatch.setattr(capture, name, _noting_thread(getattr(capture, name), threads))
    with closing(burst_client(node)) as ours:
        fed = await ours.send_goal({"order": 4}, timeout=10)  # feedback: the first one's look
        assert len([f async for f in fed.feedback(timeout=30)]) == 3
        bare = await ours.send_goal({"order": 1}, timeout=10)  # none: the look at its end
        assert [f async for f in bare.feedback(timeout=30)] == []
    assert all(looked_on.values()), f"not looked: {looked_on}"
    on_loop = {k: v.count(threading.get_ident()) for k, v in looked_on.items()}
    assert on_loop == {"feedback_before": 0, "captured_feedback": 0}, \
        f"looks on the event loop: {on_loop} of {looked_on}"
    assert capture._replies.held == 0


def _noting_thread(look: Callable[..., Any], threads: list[int]) -> Callable[..., Any]:
    def noted(*args: Any) -> Any:
        threads.append(threading.get_ident())
        return look(*args)
    return noted
