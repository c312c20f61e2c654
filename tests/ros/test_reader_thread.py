"""The node's reader thread (ros/readers.py), which replaced Cyclone listeners: delivery,
callbacks on our thread (never a Cyclone one), close with samples in flight, many
subscriptions on one thread, publishing from a callback, own writer + own reader on one
topic, invalid samples, historical samples and incompatible QoS (both sides).

Every wait below is for an outcome with a generous bound; nothing asserts a duration.
"""

from __future__ import annotations

import asyncio
import re
import threading
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from waiting import eventually

from rcan_rtps.ros import qos
from rcan_rtps.ros.participant import RosNode

STRING = "std_msgs/msg/String"
INT = "std_msgs/msg/Int32"
LATCHED = qos.DEFAULT.with_(depth=1, durability=qos.Durability.TRANSIENT_LOCAL)
DEEP = qos.DEFAULT.with_(depth=5000)  # bursts below must not fall out of a keep-last history


@pytest.fixture
async def nodes(domain_id: int) -> AsyncIterator[tuple[RosNode, RosNode]]:
    a = RosNode("reader_a", "/rt", domain_id=domain_id, localhost=True)
    b = RosNode("writer_b", "/rt", domain_id=domain_id, localhost=True)
    try:
        yield a, b
    finally:
        a.close()
        b.close()


async def loop_caught_up() -> None:
    """Every callback handed to the loop so far has run: call_soon_threadsafe is FIFO."""
    loop = asyncio.get_running_loop()
    done = loop.create_future()
    loop.call_soon_threadsafe(done.set_result, None)
    await done


def reader_threads(node: RosNode) -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == f"dds-read {node.fqn}"]


async def test_async_delivery_in_order(nodes: tuple[RosNode, RosNode]) -> None:
    a, b = nodes
    sub = a.create_subscription("chatter", STRING, DEEP)
    pub = b.create_publisher("chatter", STRING, DEEP)
    await pub.wait_for_subscribers()
    for i in range(100):
        pub.publish({"data": f"m{i}"})
    got = [(await sub.get(timeout=20)).data for _ in range(100)]  # type: ignore[attr-defined]
    assert got == [f"m{i}" for i in range(100)]


async def test_callbacks_run_on_the_nodes_reader_thread(nodes: tuple[RosNode, RosNode]) -> None:
    a, b = nodes
    seen: list[tuple[str, str]] = []
    a.create_subscription("chatter", STRING,
                          callback=lambda m: seen.append((threading.current_thread().name,
                                                          m.data)))  # type: ignore[attr-defined]
    pub = b.create_publisher("chatter", STRING)
    await pub.wait_for_subscribers()
    pub.publish({"data": "hello"})
    await eventually(lambda: bool(seen), timeout=20)
    assert seen == [(f"dds-read {a.fqn}", "hello")]
    assert a.reader_thread.alive() and len(reader_threads(a)) == 1


@pytest.mark.logs_traceback  # (a user's callback raising: its traceback is the user's)
async def test_a_failing_callback_does_not_silence_the_subscription(
        nodes: tuple[RosNode, RosNode]) -> None:
    a, b = nodes
    good: list[int] = []

    def callback(msg: Any) -> None:
        if msg.data % 2:
            raise ValueError("odd")
        good.append(msg.data)

    a.create_subscription("numbers", INT, callback=callback)
    pub = b.create_publisher("numbers", INT)
    await pub.wait_for_subscribers()
    for i in range(10):
        pub.publish({"data": i})
    await eventually(lambda: len(good) == 5, timeout=20)
    assert good == [0, 2, 4, 6, 8]


async def test_invalid_samples_are_skipped(nodes: tuple[RosNode, RosNode]) -> None:
    """A writer leaving makes an invalid (no-data) sample: never delivered."""
    a, b = nodes
    sub = a.create_subscription("numbers", INT)
    writer = b.create_writer("rt/rt/numbers", INT, qos.DEFAULT)
    await sub.wait_for_publishers()
    writer.write(b.values.build(INT, {"data": 7}))
    assert (await sub.get(timeout=20)).data == 7  # type: ignore[attr-defined]
    writer.__del__()  # unregisters: NOT_ALIVE_NO_WRITERS, an invalid sample
    await eventually(lambda: sub.matched_count() == 0, timeout=20)
    with pytest.raises(asyncio.TimeoutError):
        await sub.get(timeout=0.5)


async def test_historical_samples_reach_a_late_subscription(
        nodes: tuple[RosNode, RosNode]) -> None:
    a, b = nodes
    pub = b.create_publisher("latched", STRING, LATCHED)
    pub.publish({"data": "before you came"})
    sub = a.create_subscription("latched", STRING, LATCHED)
    assert (await sub.get(timeout=20)).data == "before you came"  # type: ignore[attr-defined]


async def test_incompatible_qos_is_counted_without_a_listener(
        nodes: tuple[RosNode, RosNode]) -> None:
    a, b = nodes
    b.create_publisher("strict", STRING, qos.SENSOR_DATA)  # best effort
    sub = a.create_subscription("strict", STRING, qos.DEFAULT)  # wants reliable
    await eventually(lambda: sub.incompatible_qos_events >= 1, timeout=20)


async def test_publisher_hears_of_an_incompatible_subscription_without_a_listener(
        nodes: tuple[RosNode, RosNode]) -> None:
    a, b = nodes
    pub = b.create_publisher("strict_pub", STRING, qos.SENSOR_DATA)  # best effort
    a.create_subscription("strict_pub", STRING, qos.DEFAULT)  # wants reliable
    await eventually(lambda: pub.incompatible_qos_events >= 1, timeout=20)
    pub.close()  # leaves the reader thread, which serves the node's other endpoints on
    assert b.reader_thread.alive()


async def test_many_subscriptions_share_one_thread(nodes: tuple[RosNode, RosNode]) -> None:
    a, b = nodes
    n = 40
    got: dict[int, list[int]] = {i: [] for i in range(n)}
    queued = []
    for i in range(n):
        if i % 2:
            a.create_subscription(f"t{i}", INT, callback=lambda m, i=i: got[i].append(m.data))
        else:
            queued.append((i, a.create_subscription(f"t{i}", INT)))
    pubs = [b.create_publisher(f"t{i}", INT) for i in range(n)]
    for pub in pubs:
        await pub.wait_for_subscribers(timeout=30)
    for round_ in range(5):
        for i, pub in enumerate(pubs):
            pub.publish({"data": i * 100 + round_})
    for i, sub in queued:
        got[i] = [(await sub.get(timeout=20)).data for _ in range(5)]  # type: ignore[attr-defined]
    await eventually(lambda: all(len(v) == 5 for v in got.values()), timeout=20)
    assert got == {i: [i * 100 + r for r in range(5)] for i in range(n)}
    assert len(reader_threads(a)) == 1


async def test_publish_from_a_callback(nodes: tuple[RosNode, RosNode]) -> None:
    """A callback (on the reader thread) that writes to topics this same node reads,
    itself included: a ping-pong of 200 messages inside one node, then a relay to b."""
    a, b = nodes
    ping = a.create_publisher("ping", INT)
    relay = a.create_publisher("relay", INT)
    relayed = b.create_subscription("relay", INT)

    def on_ping(msg: Any) -> None:
        if msg.data < 200:
            ping.publish({"data": msg.data + 1})  # the topic being delivered right now
        else:
            relay.publish({"data": msg.data})

    a.create_subscription("ping", INT, callback=on_ping)
    await ping.wait_for_subscribers()
    await relay.wait_for_subscribers()
    ping.publish({"data": 0})
    assert (await relayed.get(timeout=30)).data == 200  # type: ignore[attr-defined]


async def test_own_writer_and_reader_on_one_topic_with_a_second_writer(
        nodes: tuple[RosNode, RosNode]) -> None:
    """The issue-9 shape inside one process: node a writes the topic it reads from the
    event loop while a thread writes it through node b as fast as it can."""
    a, b = nodes
    mine, theirs = 0, 0

    def count(msg: Any) -> None:
        nonlocal mine, theirs
        if msg.data >= 0:
            mine += 1
        else:
            theirs += 1

    a.create_subscription("shared", INT, DEEP, callback=count)
    own = a.create_publisher("shared", INT, DEEP)
    other = b.create_publisher("shared", INT, DEEP)
    await own.wait_for_subscribers()
    await other.wait_for_subscribers()
    stop = threading.Event()

    def flood() -> None:
        while not stop.is_set():
            other.publish({"data": -1})
            time.sleep(0.0005)

    flooder = threading.Thread(target=flood, daemon=True)
    flooder.start()
    try:
        for i in range(2000):
            own.publish({"data": i})
            if i % 50 == 0:
                await asyncio.sleep(0)
    finally:
        stop.set()
        flooder.join(30)
    assert not flooder.is_alive()
    await eventually(lambda: mine == 2000, timeout=20)
    assert theirs > 0


async def test_close_while_samples_arrive(nodes: tuple[RosNode, RosNode]) -> None:
    """After `close()` returns no callback runs, while the other subscriptions of the
    thread go on; a second close is harmless."""
    a, b = nodes
    closed_count: list[int] = []
    kept: list[int] = []
    doomed = a.create_subscription("busy", INT, callback=lambda m: closed_count.append(m.data))
    a.create_subscription("busy", INT, callback=lambda m: kept.append(m.data))
    pub = b.create_publisher("busy", INT)
    await pub.wait_for_subscribers(2)
    stop = threading.Event()

    def flood() -> None:
        i = 0
        while not stop.is_set():
            pub.publish({"data": i})
            i += 1
            time.sleep(0.0005)

    flooder = threading.Thread(target=flood, daemon=True)
    flooder.start()
    try:
        await eventually(lambda: len(closed_count) > 50, timeout=20)
        doomed.close()
        after_close = len(closed_count)
        before = len(kept)
        await eventually(lambda: len(kept) > before + 100, timeout=20)
        assert len(closed_count) == after_close
        doomed.close()
    finally:
        stop.set()
        flooder.join(30)


async def test_node_close_stops_the_thread_with_samples_in_flight(domain_id: int) -> None:
    a = RosNode("closing", "/rt", domain_id=domain_id, localhost=True)
    b = RosNode("flooder", "/rt", domain_id=domain_id, localhost=True)
    try:
        calls: list[int] = []
        a.create_subscription("busy", INT, callback=lambda m: calls.append(m.data))
        queued = a.create_subscription("busy", INT)
        pub = b.create_publisher("busy", INT)
        await pub.wait_for_subscribers(2)
        stop = threading.Event()

        def flood() -> None:
            while not stop.is_set():
                pub.publish({"data": 1})
                time.sleep(0.0005)

        flooder = threading.Thread(target=flood, daemon=True)
        flooder.start()
        try:
            await eventually(lambda: len(calls) > 50, timeout=20)
            thread = reader_threads(a)[0]
            a.close()
            n = len(calls)
            assert not thread.is_alive() and not a.reader_thread.alive()
            # Callbacks run on the reader thread, now gone; samples it handed to the loop
            # before it ended have been dealt with once a later hand-off has run.
            await loop_caught_up()
            assert len(calls) == n  # no callback after close
            while not queued._queue.empty():  # type: ignore[union-attr]
                queued._queue.get_nowait()  # type: ignore[union-attr]
            await loop_caught_up()
            assert queued._queue.empty()  # type: ignore[union-attr]
            a.close()  # idempotent
        finally:
            stop.set()
            flooder.join(30)
    finally:
        a.close()
        b.close()


async def test_a_node_that_only_publishes_shares_one_thread_for_writer_statuses(
        domain_id: int) -> None:
    # Publishers report incompatible subscriptions from the node's one reader thread too.
    with RosNode("talker", "/rt", domain_id=domain_id, localhost=True) as node:
        node.create_publisher("chatter", STRING).publish({"data": "x"})
        node.create_publisher("chatter2", STRING).publish({"data": "y"})
        assert len(reader_threads(node)) == 1


def test_no_python_runs_in_a_cyclone_thread() -> None:
    """The deadlock invariant, as far as source can show it: no Cyclone listener and no
    query-condition filter (both run Python on Cyclone's threads) anywhere in the product."""
    src = Path(__file__).resolve().parents[2] / "src" / "rcan_rtps"
    pattern = re.compile(r"\bListener\s*\(|\blistener\s*=|QueryCondition\s*\(|"
                         r"import .*\b(Listener|QueryCondition)\b|\.wait_async\(")
    offenders = [f"{path.relative_to(src)}:{n}: {line.strip()}"
                 for path in sorted(src.rglob("*.py"))
                 for n, line in enumerate(path.read_text().splitlines(), 1)
                 if pattern.search(line) and not line.lstrip().startswith("#")]
    assert offenders == []


def _dds_matched(pub: Any) -> int:
    return int(pub.writer.get_publication_matched_status().current_count)


async def test_a_publishers_matched_count_follows_subscriptions_coming_and_going(
        nodes: tuple[RosNode, RosNode]) -> None:
    """The count comes from the reader thread, not a DDS call: it must follow every change
    and settle on what DDS says, also for a publisher made after its subscribers."""
    a, b = nodes
    pub = b.create_publisher("/rt/matched", STRING)
    for cycle in range(20):
        count = cycle % 3 + 1
        subs = [a.create_subscription("/rt/matched", STRING) for _ in range(count)]
        await eventually(lambda n=count: pub.matched_count() == n == _dds_matched(pub),
                         what=f"cycle {cycle}: {count} matched")
        late = b.create_publisher(f"/rt/matched_{cycle}", STRING)
        early = a.create_subscription(f"/rt/matched_{cycle}", STRING)
        await eventually(lambda p=late: p.matched_count() == 1, what=f"late publisher {cycle}")
        for sub in [*subs, early]:
            sub.close()
        late.close()
        await eventually(lambda: pub.matched_count() == 0 == _dds_matched(pub),
                         what=f"cycle {cycle}: all left")


async def test_delivered_returns_after_every_sample_held_was_handed_over(
        nodes: tuple[RosNode, RosNode]) -> None:
    """Issue 27: a goal's end must not be concluded while its feedback is still on the way
    from the reader thread (actions.py). Samples delivered in-process are in the reader when
    `publish` returns; a slow callback keeps the thread busy with them meanwhile."""
    a, b = nodes
    loop = asyncio.get_running_loop()
    got: list[str] = []

    def slow_hop(m: Any) -> None:
        time.sleep(0.001)
        loop.call_soon_threadsafe(got.append, m.data)

    a.create_subscription("chatter", STRING, DEEP, callback=slow_hop)
    pub = b.create_publisher("chatter", STRING, DEEP)
    await pub.wait_for_subscribers()
    for rounds in range(20):
        for i in range(20):
            pub.publish({"data": f"{rounds}.{i}"})
        await a.delivered()
        assert got[-1:] == [f"{rounds}.19"], f"round {rounds}: {got[-3:]}"


async def test_delivered_returns_on_a_node_without_readers_or_closed(domain_id: int) -> None:
    node = RosNode("no_readers", "/rt", domain_id=domain_id, localhost=True)
    await node.delivered()  # no reader thread: nothing to wait for
    node.create_subscription("chatter", STRING)
    node.close()
    await node.delivered()
