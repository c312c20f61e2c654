"""What a hostile or broken peer on the ROS 2 graph can write, and the bridge's answer.

Each peer here is real DDS: an rclpy node (the oracle), or a participant of our own writing
well-formed CDR with values no well-behaved node sends (Cyclone checks the CDR itself, so
malformed bytes never reach Python: what gets through is well-formed CDR with bad values).
The bridge must not crash, lose the other samples, show what it cannot read as fine, or
stop stopping.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import re
import struct
import subprocess
import sys
import tracemalloc
import uuid
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest
from oracle.client import OracleEnv, RclpyOracle
from waiting import eventually, take

from rcan_rtps.bridge.commanders import MAX_NODE_NAME, foreign_publishers
from rcan_rtps.bridge.faults import UNLISTED
from rcan_rtps.ros import qos, raw_cdr
from rcan_rtps.ros.actions import ActionClient, ActionServer, GoalState, ServerGoal
from rcan_rtps.ros.graph import (
    INFO_BYTES_TAKE,
    MAX_INFO_BYTES,
    MAX_INFO_NAME,
    MAX_NODE_FQN,
    MAX_UNKNOWN_INFO_BYTES,
    MAX_UNKNOWN_INFOS,
    RosGraph,
)
from rcan_rtps.ros.handshake import participant_prefix, peers_know_our_readers
from rcan_rtps.ros.info_inbox import INFO_GID, WAITING_INFOS
from rcan_rtps.ros.participant import DISCOVERY_TOPIC, DISCOVERY_TYPE, RosNode

from .bridge_rig import VIEWER, Rig, bridge_config, close_rig, make_rig

FIB = "test_msgs/action/Fibonacci"
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"
TWIST = "geometry_msgs/msg/Twist"


def tracebacks(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.exc_info or r.levelno >= logging.ERROR]


@pytest.fixture
def hostile(domain_id: int, jazzy_share: Path) -> Iterator[RosNode]:
    with RosNode("hostile", "/robot1", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as node:
        yield node


@pytest.fixture
async def victim(domain_id: int, jazzy_share: Path) -> AsyncIterator[RosNode]:
    with RosNode("victim", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as node:
        yield node


@pytest.fixture
def fib_server(jazzy_oracle: OracleEnv, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_oracle, "fib_server", "/", domain_id=domain_id) as agent:
        agent.call("action_server", name="/fib", mode="slow")
        yield agent


@pytest.fixture
async def rig(tmp_path: Path, jazzy_oracle: OracleEnv, domain_id: int) -> AsyncIterator[Rig]:
    r = await make_rig(bridge_config(tmp_path, domain_id), jazzy_oracle, domain_id)
    yield r
    await close_rig(r)


def not_utf8(codec: Any, value: dict[str, Any], marker: bytes) -> bytes:
    """`value`'s CDR with `marker` (ASCII, in one of its strings) made invalid UTF-8."""
    data = bytes(codec.encode_value(value))
    assert data.count(marker) == 1
    return data.replace(marker, b"\xff" * len(marker))


async def still_stops(rig: Rig) -> None:
    """After whatever the graph did: an e-stop latches and a zero Twist reaches rclpy."""
    await rig.oracle.acall("subscribe", topic="/robot1/cmd_vel", type=TWIST)
    assert await rig.oracle.acall("wait_matched", topic="/robot1/cmd_vel") >= 1
    estop = await rig.command(VIEWER, {"action": "estop"})
    assert estop.http_status == 200 and rig.governor.latch.latched
    await take(rig.oracle, "/robot1/cmd_vel",
               until=lambda got: any(t["linear"]["x"] == 0.0 for t in got))


# -- the graph -------------------------------------------------------------------------
async def test_bad_discovery_info_does_not_stop_a_goal_cancel(
        fib_server: RclpyOracle, victim: RosNode, hostile: RosNode,
        caplog: pytest.LogCaptureFixture) -> None:
    """Services and actions read ros_discovery_info before each call: a node name that is
    not UTF-8 failed that read (UnicodeDecodeError), so a stop could not cancel a goal
    while a peer wrote such samples, and the good samples read with it were lost."""
    client = ActionClient(victim, "/fib", FIB)
    goal = await client.send_goal({"order": 40}, timeout=20)
    async for _ in goal.feedback(timeout=20):
        break  # running
    info = not_utf8(hostile.codecs.of(DISCOVERY_TYPE), {
        "gid": {"data": hostile.participant.guid.bytes},
        "node_entities_info_seq": [{"node_namespace": "/", "node_name": "evil_node"}]},
        b"_node")
    raw_cdr.write(hostile._info_writer, info)
    await asyncio.sleep(0.5)  # in the victim's reader, unread
    assert await client.cancel_all(timeout=10, server_wide=True) >= 1
    assert (await goal.result(timeout=30)).state is GoalState.CANCELED
    graph = RosGraph(victim)
    await graph.settle(0.5)
    assert ("/", "fib_server") in graph.nodes()
    assert ("/", "evil\ufffd\ufffd\ufffd\ufffd\ufffd") in graph.nodes()
    assert not tracebacks(caplog)


async def test_a_node_name_past_its_bound_is_cut_in_the_other_publishers(
        victim: RosNode, hostile: RosNode) -> None:
    """ros_discovery_info bounds a node's name to 256 characters; a peer writing 100,000
    (well-formed CDR, the bound not kept) named its cmd_vel writer so in STATUS's list, its
    faults' messages, the log and the audit: it is cut to MAX_NODE_NAME."""
    publisher = hostile.create_publisher("/robot1/cmd_vel", TWIST)
    data = bytes(hostile.codecs.of(DISCOVERY_TYPE).encode_value({
        "gid": {"data": hostile.participant.guid.bytes},
        "node_entities_info_seq": [{"node_namespace": "/", "node_name": "Q" * 256,
                                    "writer_gid_seq": [{"data": publisher.writer.guid.bytes}]}]}))
    at_bound = struct.pack("<I", 257) + b"Q" * 256 + b"\0"  # its length, chars, NUL
    assert data.count(at_bound) == 1
    data = data.replace(at_bound, struct.pack("<I", 100_001) + b"n" * 100_000 + b"\0")
    graph = RosGraph(victim)

    def named() -> list[str]:
        raw_cdr.write(hostile._info_writer, data)
        graph.refresh()
        found = foreign_publishers(graph.publishers_on({"/robot1/cmd_vel"}),
                                   victim.participant.guid.bytes)
        return [p.node for p in found.values() if p.node and p.node.startswith("/nnn")]

    (name,) = await eventually(named, timeout=20)
    assert len(name) <= MAX_NODE_NAME


async def test_node_names_past_their_bound_are_cut_in_every_view_of_the_graph(
        victim: RosNode, hostile: RosNode) -> None:
    """A peer's ros_discovery_info naming a node with a 100,000-character namespace and name
    (the IDL's bound, 256, not kept: cyclonedds' reader does not check it) reached `node
    list`, `node info` and `topic info` as is: the graph cuts each where it reads them."""
    publisher = hostile.create_publisher("/robot1/chatter", "std_msgs/msg/String")
    data = bytes(hostile.codecs.of(DISCOVERY_TYPE).encode_value({
        "gid": {"data": hostile.participant.guid.bytes},
        "node_entities_info_seq": [{"node_namespace": "/" + "S" * 255, "node_name": "Q" * 256,
                                    "writer_gid_seq": [{"data": publisher.writer.guid.bytes}]}]}))
    for char, huge in ((b"S", 100_000), (b"Q", 100_000)):
        at_bound = struct.pack("<I", 257) + (b"/" if char == b"S" else b"") + \
            char * (255 if char == b"S" else 256) + b"\0"
        assert data.count(at_bound) == 1
        data = data.replace(at_bound, struct.pack("<I", huge + 1) + b"n" * huge + b"\0")
    graph = RosGraph(victim)

    def hostile_nodes() -> list[tuple[str, str]]:
        raw_cdr.write(hostile._info_writer, data)
        graph.refresh()
        return [(ns, name) for ns, name in graph.nodes() if name.startswith("nnn")]

    [(namespace, name)] = await eventually(hostile_nodes, timeout=20)
    assert len(namespace) <= MAX_INFO_NAME and len(name) <= MAX_INFO_NAME
    assert namespace.startswith("nnn") and "(+99744 chars)" in name
    [chatter] = [e for e in graph.topic_endpoints("/robot1/chatter")
                 if e.participant_gid == hostile.participant.guid.bytes]
    assert (chatter.node_namespace, chatter.node_name) == (namespace, name)
    longest = max(len(e.node_name) + len(e.node_namespace) for e in graph.endpoints())
    assert longest <= MAX_NODE_FQN


# -- actions ---------------------------------------------------------------------------
async def test_a_foreign_status_writer_is_ignored(
        fib_server: RclpyOracle, victim: RosNode, hostile: RosNode,
        caplog: pytest.LogCaptureFixture) -> None:
    """A second writer on an action's status topic: a status value action_msgs does not
    define (it raised in the event loop: a traceback, and the array's later entries
    unread), and thousands of other goal ids (each kept for good)."""
    client = ActionClient(victim, "/fib", FIB)
    status = hostile.create_publisher("/fib/_action/status", "action_msgs/msg/GoalStatusArray",
                                      qos.ACTION_STATUS)
    goal = await client.send_goal({"order": 6}, timeout=20)
    await status.wait_for_subscribers(1, timeout=10)
    ours = {"goal_info": {"goal_id": {"uuid": goal.goal_id}}, "status": 50}
    for _ in range(3):
        status.publish({"status_list": [ours, *(
            {"goal_info": {"goal_id": {"uuid": uuid.uuid4().bytes}}, "status": 2}
            for _ in range(2000))]})
    outcome = await goal.result(timeout=30)
    assert outcome.state is GoalState.SUCCEEDED
    assert client.goals_tracked == 1  # ours alone: none of the foreign ids is kept
    assert not tracebacks(caplog)


class _BrokenResults(ActionServer):
    """An action server whose result replies name a status no goal ends with."""

    status = 50

    async def _on_get_result(self, request: Any) -> Any:
        reply = await super()._on_get_result(request)
        reply.status = self.status
        return reply


@pytest.mark.parametrize("status", [50, int(GoalState.EXECUTING)])
async def test_a_result_naming_no_end_keeps_the_end_the_status_showed(
        victim: RosNode, hostile: RosNode, status: int) -> None:
    """The result is asked for once the status topic showed the goal's end; a reply with
    a value action_msgs does not define raised ValueError out of `result()` (the bridge's
    goal watcher died, the goal shown as running for good), one naming a running state
    ended the goal as running."""
    async def execute(goal: ServerGoal) -> dict[str, Any]:
        return {"sequence": [0, 1, 1]}

    server = _BrokenResults(hostile, "/fib", FIB, execute)
    server.status = status
    try:
        client = ActionClient(victim, "/fib", FIB)
        goal = await client.send_goal({"order": 2}, timeout=20)
        outcome = await goal.result(timeout=20)
        assert outcome.state is GoalState.SUCCEEDED
        assert f"status {status}" in outcome.detail
        assert outcome.result is not None and list(outcome.result.sequence) == [0, 1, 1]
    finally:
        await server.close()


# -- telemetry → STATUS -----------------------------------------------------------------
async def test_a_diagnostic_level_outside_the_enum_is_a_fault(rig: Rig) -> None:
    """DiagnosticStatus levels are 0-3; any other level was read as OK, so it cleared the
    component's ERROR and STATUS showed the robot fine."""
    await rig.oracle.acall("publisher", topic="/robot1/diagnostics", type=DIAGNOSTICS)
    await rig.telemetry.subscriptions[2].wait_for_publishers(1, timeout=15)
    assert await rig.oracle.acall("wait_subscribers", topic="/robot1/diagnostics") >= 1

    async def send(level: int, message: str) -> None:
        await rig.oracle.acall("publish", topic="/robot1/diagnostics", type=DIAGNOSTICS,
                               value={"status": [{"level": level, "name": "motor",
                                                  "message": message}]}, count=2)

    async def send_until(level: int, message: str, seen: Callable[[], bool]) -> None:
        # Sent again until seen: a Fast DDS writer's first samples can miss a Cyclone reader
        # that matched it in the same moment (ros/handshake.py); diagnostics repeat anyway.
        async def sent_and_seen() -> bool:
            await send(level, message)
            return seen()
        await eventually(sent_and_seen, interval=0.5)

    await send_until(2, "overheat", lambda: rig.telemetry.status(pending_auth=0).state == "fault")
    await send_until(7, "what is this", lambda: any(
        "what is this" in f.message for f in rig.telemetry.status(pending_auth=0).faults))
    status = rig.telemetry.status(pending_auth=0)
    assert status.state == "fault" and status.faults[0].level == "ERROR"
    assert "what is this" in status.faults[0].message and "7" in status.faults[0].message
    await send_until(0, "ok", lambda: not rig.telemetry.status(pending_auth=0).faults)


async def test_strings_that_are_not_utf8_are_read_as_rclpy_reads_them(
        rig: Rig, hostile: RosNode, caplog: pytest.LogCaptureFixture) -> None:
    """A diagnostic whose text is not UTF-8 (a Latin-1 `°C` from a driver) was dropped as
    undecodable, so the robot's ERROR never showed; rclpy reads such bytes as U+FFFD."""
    diagnostics = hostile.create_publisher("/robot1/diagnostics", DIAGNOSTICS, qos.DEFAULT)
    await diagnostics.wait_for_subscribers(1, timeout=10)
    diagnostics.publish_cdr(not_utf8(diagnostics.codec, {"status": [
        {"level": 2, "name": "motor", "message": "overheat: 95 DEGC"}]}, b"DEG"))
    await eventually(lambda: rig.telemetry.status(pending_auth=0).state == "fault")
    assert rig.telemetry.status(pending_auth=0).faults[0].message == \
        "overheat: 95 \ufffd\ufffd\ufffdC"
    assert not tracebacks(caplog)
    await still_stops(rig)


async def test_a_flood_of_diagnostic_components_is_bounded_and_stays_a_fault(
        rig: Rig, hostile: RosNode) -> None:
    """Unique component names each stayed in the fault table for good: 4 s of them made a
    4.7 MB STATUS. At most 256 are listed, an ERROR before any WARN, and one ERROR says how
    many are not, so nobody reads "fine"."""
    diagnostics = hostile.create_publisher("/robot1/diagnostics", DIAGNOSTICS,
                                           qos.DEFAULT.with_(depth=100))
    await diagnostics.wait_for_subscribers(1, timeout=10)
    diagnostics.publish({"status": [{"level": 2, "name": "motor", "message": "overheat"}]})
    for batch in range(5):
        diagnostics.publish({"status": [
            {"level": 1, "name": f"flood/{batch}/{i}", "message": "m" * 2000}
            for i in range(400)]})
    await eventually(lambda: any(
        f.name == UNLISTED for f in rig.telemetry.status(pending_auth=0).faults))
    status = rig.telemetry.status(pending_auth=0)
    # At most 2000 warnings and an error (best effort: a large sample may be lost).
    assert re.match(r"\d+ more", status.faults[-1].message), status.faults[-1]
    assert status.state == "fault"
    assert len(status.faults) == 257
    assert any(f.name == "motor" and f.level == "ERROR" for f in status.faults)
    assert all(len(f.message) <= 512 for f in status.faults)
    assert len(msgspec.json.encode(status)) < 200_000


async def test_a_huge_joint_state_is_cut_in_status(rig: Rig) -> None:
    """A JointState's size is bounded only by its sender, and STATUS copied it whole."""
    await rig.oracle.acall("publisher", topic="/robot1/joint_states",
                           type="sensor_msgs/msg/JointState")
    await rig.telemetry.subscriptions[1].wait_for_publishers(1, timeout=15)
    n = 5000
    await rig.oracle.acall("publish", topic="/robot1/joint_states",
                           type="sensor_msgs/msg/JointState", count=2, value={
                               "name": [f"joint_{i}" for i in range(n)],
                               "position": [float(i) for i in range(n)]})
    await eventually(lambda: rig.telemetry.status(pending_auth=0).telemetry.joints)
    joints = rig.telemetry.status(pending_auth=0).telemetry.joints
    assert joints is not None and joints.count == n
    assert joints.names[:2] == ["joint_0", "joint_1"] and len(joints.names) == 64
    assert joints.positions == [float(i) for i in range(64)]


async def test_a_velocity_that_is_not_a_number_is_not_idle(rig: Rig, hostile: RosNode) -> None:
    """Odometry with a NaN velocity showed `idle` (NaN compares false with everything):
    a motion the bridge cannot read is not stillness."""
    odom = hostile.create_publisher("/robot1/odom", "nav_msgs/msg/Odometry", qos.DEFAULT)
    await odom.wait_for_subscribers(1, timeout=10)
    odom.publish({"twist": {"twist": {"linear": {"x": math.nan}}}})
    await eventually(lambda: rig.telemetry.status(pending_auth=0).ros.connected)
    assert rig.telemetry.status(pending_auth=0).state == "moving"
    odom.publish({"twist": {"twist": {"linear": {"x": 0.0}}}})
    await eventually(lambda: rig.telemetry.status(pending_auth=0).state == "idle")


# -- any topic -------------------------------------------------------------------------
async def test_a_flood_of_undecodable_samples_is_logged_once(
        victim: RosNode, hostile: RosNode, caplog: pytest.LogCaptureFixture) -> None:
    """Well-formed samples the codec refuses (XCDR2 encapsulation: Cyclone passes it on)
    were each logged: a peer sending them fast filled the bridge's log."""
    caplog.set_level(logging.WARNING, logger="rcan_rtps.ros.readers")
    deep = qos.DEFAULT.with_(depth=1000)  # every sample kept: none lost to history
    sub = victim.create_subscription("/flood", TWIST, deep, maxsize=1000)
    pub = hostile.create_publisher("/flood", TWIST, deep)
    await pub.wait_for_subscribers(1, timeout=10)
    xcdr2 = b"\x00\x07\x00\x00" + bytes(48)
    for _ in range(300):
        pub.publish_cdr(xcdr2)
    pub.publish({"linear": {"x": 0.5}})
    assert (await asyncio.wait_for(sub.get(), 10)).linear.x == 0.5
    assert sub._watch.bad_samples == 300
    warnings = [r for r in caplog.records if r.name == "rcan_rtps.ros.readers"]
    assert len(warnings) == 1


async def test_a_node_that_left_is_not_listed(victim: RosNode, domain_id: int) -> None:
    """ros_discovery_info is keyless: a participant's last sample stayed behind after it
    left (while any other participant remained), so its nodes were listed for good."""
    graph = RosGraph(victim)
    with RosNode("stayer", "/", domain_id=domain_id):
        with RosNode("leaver", "/", domain_id=domain_id):
            await eventually(lambda: (graph.refresh(), ("/", "leaver") in graph.nodes())[1])
        await eventually(lambda: (graph.refresh(), ("/", "leaver") not in graph.nodes())[1])
        assert ("/", "stayer") in graph.nodes()


async def test_made_up_participants_in_discovery_info_name_no_node(
        victim: RosNode, hostile: RosNode) -> None:
    """ros_discovery_info entries naming a gid no live participant has were kept for good
    and listed by nodes(); now they are never listed, and only so many are kept."""
    graph = RosGraph(victim)
    await matched_by_graph(hostile)
    codec = hostile.codecs.of(DISCOVERY_TYPE)
    for i in range(400):
        raw_cdr.write(hostile._info_writer, bytes(codec.encode_value({
            "gid": {"data": uuid.uuid4().bytes},
            "node_entities_info_seq": [{"node_namespace": "/", "node_name": f"ghost_{i}"}]})))
    hostile.announce()  # its own, real info last
    await eventually(lambda: (graph.refresh(), ("/robot1", "hostile") in graph.nodes())[1])
    await asyncio.sleep(0.5)
    graph.refresh()
    assert not [n for n in graph.nodes() if n[1].startswith("ghost_")]
    assert ("/", "victim") in graph.nodes()
    assert len(graph._node_infos) <= MAX_UNKNOWN_INFOS + 2


async def matched_by_graph(peer: RosNode) -> None:
    """Waits until the peer's ros_discovery_info writer matched the graph's reader: before,
    a write overwrites the last one in the writer's latched history of one (a test writing
    several lost all but the last on a busy machine)."""
    await eventually(
        lambda: peer._info_writer.get_publication_matched_status().current_count >= 1)


async def test_a_flood_of_made_up_gids_does_not_push_out_an_honest_nodes_info(
        victim: RosNode, hostile: RosNode, domain_id: int, jazzy_share: Path) -> None:
    """A node writes its ros_discovery_info once (again only when its endpoints change), and
    the graph keeps at most WAITING_INFOS infos waiting for a refresh. Past that the oldest
    went: a peer writing more made-up gids than that between two refreshes (~40,000 a
    second measured from another process) dropped the honest info for good, and the node
    was never listed. Then the writer with the most waiting lost its own oldest — but a
    flood of one info per writer tied every writer, the honest one first. Now the
    participant whose writers have the most waiting loses its own oldest: here a flood of
    one made-up gid per writer, WAITING_INFOS + 64 writers of one participant."""
    graph = RosGraph(victim)
    await matched_by_graph(hostile)
    await victim.delivered()  # the hostile node's own info is waiting for a refresh
    count = WAITING_INFOS + 64
    with RosNode("flooder", "/", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as flooder:
        floods = [flooder.create_writer(DISCOVERY_TOPIC, DISCOVERY_TYPE, qos.DISCOVERY_INFO)
                  for _ in range(count)]
        await eventually(lambda: all(w.get_publication_matched_status().current_count >= 1
                                     for w in floods), timeout=60)
        codec = flooder.codecs.of(DISCOVERY_TYPE)
        empty = bytearray(codec.encode_value({"gid": {"data": bytes(16)},
                                              "node_entities_info_seq": []}))
        for n, flood in enumerate(floods):
            empty[INFO_GID] = uuid.uuid4().bytes
            raw_cdr.write(flood, bytes(empty))
            if n % 256 == 255:
                await victim.delivered()  # (the reader keeps 1,000: never more than 256)
        await victim.delivered()
        assert graph._inbox.dropped >= count - WAITING_INFOS  # the bound was crossed
        await eventually(
            lambda: (graph.refresh(), ("/robot1", "hostile") in graph.nodes())[1], timeout=5)
    graph.close()


async def test_waiting_for_a_peer_keeps_only_the_peers_it_waits_for(
        victim: RosNode, hostile: RosNode) -> None:
    """While a client waits for a server's participant to confirm our readers
    (`peers_know_our_readers`, up to the caller's timeout), any peer may write infos of
    made-up gids: each one's gid was kept until the wait ended (~100,000 entries, 10 MB, in
    5 s of a flood from another process). Only the peers waited for are kept now. The
    hostile peer here announces no info of its own until the flood is written."""
    flood = hostile.create_writer(DISCOVERY_TOPIC, DISCOVERY_TYPE, qos.DISCOVERY_INFO)
    hostile.__dict__.pop("_info_writer").__del__()  # (announce() does nothing from here on)
    peer = participant_prefix(hostile.participant.guid.bytes)
    codec = hostile.codecs.of(DISCOVERY_TYPE)
    empty = bytearray(codec.encode_value({"gid": {"data": bytes(16)},
                                          "node_entities_info_seq": []}))
    count = 10_000
    tracemalloc.start()
    try:
        waiting = asyncio.create_task(peers_know_our_readers(victim, {peer}, timeout=60.0))
        await eventually(lambda: flood.get_publication_matched_status().current_count >= 1)
        for _ in range(count // 250):
            for _ in range(250):
                empty[INFO_GID] = uuid.uuid4().bytes
                raw_cdr.write(flood, bytes(empty))
            await victim.delivered()
        empty[INFO_GID] = hostile.participant.guid.bytes[:16]
        raw_cdr.write(flood, bytes(empty))
        confirmed = await waiting
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert confirmed == {peer}
    assert peak < 20 * count, f"{peak / count:.0f} bytes traced per made-up gid"


async def write_acked(writer: Any, data: bytes) -> None:
    """Writes a sample and waits until the matched readers have it: the next write to a
    latched writer of depth 1 (a node's info writer) may otherwise replace it unsent. Under
    -n 2, a 2.6 MB info written just before the peer's own was never read (review 52)."""
    raw_cdr.write(writer, data)
    assert await asyncio.to_thread(writer.wait_for_acks, 60 * 10**9)


def _info(codec: Any, gid: bytes, name: str, endpoints: int) -> bytes:
    """A ros_discovery_info sample naming one node with `endpoints` made-up endpoint gids."""
    gids = [{"data": uuid.uuid4().bytes} for _ in range(endpoints)]
    return bytes(codec.encode_value({"gid": {"data": gid}, "node_entities_info_seq": [
        {"node_namespace": "/", "node_name": name, "writer_gid_seq": gids}]}))


async def test_a_discovery_info_past_the_size_bound_is_dropped_undecoded(
        victim: RosNode, hostile: RosNode, caplog: pytest.LogCaptureFixture) -> None:
    """The IDL bounds no sequence of an info: a peer's sample of 160,000 endpoint gids
    (2.6 MB) was decoded and kept while the peer lived (~4 times its size in objects); now
    it is dropped undecoded with a warning, and the peer's next, honest info is read."""
    graph = RosGraph(victim)
    await matched_by_graph(hostile)
    codec = hostile.codecs.of(DISCOVERY_TYPE)
    huge = _info(codec, hostile.participant.guid.bytes, "huge", 160_000)
    assert len(huge) > MAX_INFO_BYTES
    await write_acked(hostile._info_writer, huge)
    await victim.delivered()  # (acknowledged: in our reader; now handed over to the graph)
    hostile.announce()  # its own, real info after it
    await eventually(lambda: (graph.refresh(), ("/robot1", "hostile") in graph.nodes())[1])
    assert graph.large_infos == 1
    assert ("/", "huge") not in graph.nodes()
    assert [r.getMessage() for r in caplog.records if "larger than" in r.getMessage()]
    assert not tracebacks(caplog)


async def test_a_flood_of_discovery_infos_past_the_size_bound_is_not_held(
        victim: RosNode, domain_id: int, jazzy_share: Path) -> None:
    """Any peer may write ros_discovery_info samples of any size, and the graph's reader keeps
    up to 1,000: taken only by a refresh, they waited inside Cyclone until the next one (200
    samples of 4.8 MB grew a process by 920 MB, red team 32; a process that never refreshed
    held them for good). The node's reader thread now takes each as it arrives and keeps
    none past the size bound. A peer in another process writes 60 such samples, each
    acknowledged by our reader before the next, while nothing here refreshes: this
    process's resident memory must not grow by more than a few samples' worth (it grew by
    ~4.6 MB a sample before)."""
    graph = RosGraph(victim)
    graph.refresh()
    flood, size = 60, 4_800_000
    before = 0

    def ready() -> None:
        nonlocal before
        before = _resident_bytes()

    try:
        await _flood(flood, size, domain_id, jazzy_share, on_ready=ready)
        grown = _resident_bytes() - before
        await eventually(lambda: (graph.refresh(), graph.large_infos == flood)[1])
    finally:
        graph.close()
    assert grown < 8 * size, f"grew by {grown / size:.1f} samples' worth"


async def test_a_sample_past_the_nodes_size_bound_is_dropped_as_it_arrives(
        domain_id: int, jazzy_share: Path) -> None:
    """Any peer may write a sample of any size to a topic we read, and Cyclone reassembled it
    whole before any code of ours could look at it (a 50 MB info peaked a process at +100 MB).
    A node's `max_sample_bytes` (the bridge's `ros2.max_sample_bytes`, 256 MiB by default)
    is Cyclone's MaxSampleSize: larger samples are dropped as they arrive. With 8 MiB, a 4 MB
    info still reaches the graph (counted past the info bound), a 20 MB one never does, and
    the process's peak memory does not grow by it."""
    with RosNode("bounded", "/", domain_id=domain_id, distro="jazzy", idl_paths=[jazzy_share],
                 max_sample_bytes=8 << 20) as node:
        graph = RosGraph(node)
        try:
            await _flood(1, 4_000_000, domain_id, jazzy_share)
            await eventually(lambda: (graph.refresh(), graph.large_infos == 1)[1])
            with contextlib.suppress(OSError):  # (the peak from here on: Linux ≥ 4.0)
                Path("/proc/self/clear_refs").write_text("5")
            before = _resident_bytes()
            await _flood(1, 20_000_000, domain_id, jazzy_share)
            await asyncio.sleep(1.0)  # (had it been taken, it would be in the graph's inbox)
            peak = _resident_bytes("VmHWM:")
            graph.refresh()
            assert graph.large_infos == 1
        finally:
            graph.close()
    assert peak - before < 20_000_000, f"peak grew by {(peak - before) >> 20} MiB"


async def _flood(count: int, size: int, domain_id: int, share: Path,
                 on_ready: Callable[[], None] = lambda: None) -> None:
    """Runs info_flooder.py: `count` infos of `size` bytes, each acknowledged (or dropped);
    `on_ready()` once it is matched, before it writes."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    flooder = subprocess.Popen(
        [sys.executable, str(Path(__file__).with_name("info_flooder.py")), str(count),
         str(size), str(domain_id), str(share)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert flooder.stdout is not None and flooder.stdin is not None
        assert await asyncio.to_thread(flooder.stdout.readline) == "ready\n"
        on_ready()
        flooder.stdin.write("go\n")
        flooder.stdin.flush()
        assert await asyncio.wait_for(asyncio.to_thread(flooder.stdout.readline), 300) \
            == "done\n"
    finally:
        flooder.kill()
        flooder.wait()


def _resident_bytes(field: str = "VmRSS:") -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field):
                return int(line.split()[1]) * 1024
    raise AssertionError(f"no {field} in /proc/self/status")


async def test_infos_of_made_up_participants_share_a_byte_budget(
        victim: RosNode, hostile: RosNode) -> None:
    """The 256 infos kept for participants not (yet) discovered could each be up to the
    size bound (~0.5 GB of objects): they also share MAX_UNKNOWN_INFO_BYTES, the oldest
    going first."""
    graph = RosGraph(victim)
    await matched_by_graph(hostile)
    codec = hostile.codecs.of(DISCOVERY_TYPE)
    samples = [_info(codec, uuid.uuid4().bytes, f"ghost_{i}", 90_000) for i in range(8)]
    for data in samples:
        await write_acked(hostile._info_writer, data)
    await victim.delivered()  # (acknowledged: in our reader; now handed over to the graph)
    hostile.announce()
    # (each refresh decodes ~INFO_BYTES_TAKE: until one has taken all, the last included)
    await eventually(lambda: graph.refresh() and ("/robot1", "hostile") in graph.nodes())
    kept = [gid for gid in graph._node_infos if gid not in graph._alive]
    assert 0 < len(kept) <= MAX_UNKNOWN_INFO_BYTES // len(samples[0]) < len(samples)
    newest = bytes(samples[-1][4:20])  # the gid, after the 4-byte CDR header
    assert newest in kept


async def test_discovery_infos_dropped_at_every_refresh_are_logged_at_a_bounded_rate(
        victim: RosNode, hostile: RosNode, caplog: pytest.LogCaptureFixture) -> None:
    """A ros_discovery_info sample past the size bound (or one that does not decode) was
    logged by each refresh that took one; services, actions and the bridge's polls refresh
    often, so a peer writing one now and then filled the log as fast as we refreshed."""
    caplog.set_level(logging.WARNING, logger="rcan_rtps.ros.graph")
    graph = RosGraph(victim)
    huge = _info(hostile.codecs.of(DISCOVERY_TYPE), uuid.uuid4().bytes, "huge", 160_000)
    for n in range(1, 5):
        raw_cdr.write(hostile._info_writer, huge)
        await eventually(lambda n=n: (graph.refresh(), graph.large_infos == n)[1])
    assert len([r for r in caplog.records if "larger than" in r.getMessage()]) == 1


async def test_a_discovery_info_past_the_size_bound_leaves_no_stale_nodes(
        victim: RosNode, hostile: RosNode, caplog: pytest.LogCaptureFixture) -> None:
    """A participant's info past the size bound is dropped undecoded, and the warning says
    its nodes are not shown; but the info it replaced stayed, so the nodes the participant
    named before (and may no longer have) were listed as its nodes."""
    graph = RosGraph(victim)
    await eventually(lambda: (graph.refresh(), ("/robot1", "hostile") in graph.nodes())[1])
    codec = hostile.codecs.of(DISCOVERY_TYPE)
    huge = _info(codec, hostile.participant.guid.bytes, "huge", 160_000)
    raw_cdr.write(hostile._info_writer, huge)
    await eventually(lambda: (graph.refresh(), graph.large_infos == 1)[1])
    assert ("/robot1", "hostile") not in graph.nodes() and ("/", "huge") not in graph.nodes()
    assert ("/", "victim") in graph.nodes()
    hostile.announce()  # its next info, within the bound: listed again
    await eventually(lambda: (graph.refresh(), ("/robot1", "hostile") in graph.nodes())[1])


async def test_a_view_names_endpoints_without_walking_every_info(
        victim: RosNode, hostile: RosNode, domain_id: int) -> None:
    """Each view (`endpoints()`, which services and actions call before each call, a stop's
    goal cancel included) built a table of every gid every live info names to name a few
    endpoints: ~550 ms a call with eight peers each announcing 120,000 made-up gids within
    MAX_INFO_BYTES (red team 32). Infos are indexed once, when read; a view's peak of traced
    memory (what it allocates) must not grow with the infos' gids."""
    graph = RosGraph(victim)
    codec = hostile.codecs.of(DISCOVERY_TYPE)
    with RosNode("second", "/", domain_id=domain_id) as second:
        for peer in (hostile, second):
            raw_cdr.write(peer._info_writer, _info(codec, peer.participant.guid.bytes,
                                                   "crowded", 100_000))
        await eventually(lambda: (graph.refresh(),
                                  ("/", "crowded") in graph.nodes_sharing_a_name())[1])
        tracemalloc.start()
        try:
            graph.endpoints()
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    assert peak < 1_000_000, f"{peak} bytes allocated by one view"


async def test_a_refresh_decodes_so_many_discovery_info_bytes_at_a_time(
        victim: RosNode, hostile: RosNode) -> None:
    """Decoding an info within MAX_INFO_BYTES costs ~150 ms of Python a MiB of gids, on the
    caller's loop, and a peer may write one as often as it likes: a refresh decoded every one
    waiting (eight here, ~2 s; a peer writing ten a second held the loop for good). It stops
    past INFO_BYTES_TAKE and says it is behind; the next refreshes take the rest."""
    graph = RosGraph(victim)
    graph.refresh()
    writer = hostile.create_writer(DISCOVERY_TOPIC, DISCOVERY_TYPE,
                                   qos.DISCOVERY_INFO.with_(depth=8))
    await eventually(lambda: writer.get_publication_matched_status().current_count >= 1)
    codec = hostile.codecs.of(DISCOVERY_TYPE)
    samples = [_info(codec, uuid.uuid4().bytes, f"big_{i}", 100_000) for i in range(8)]
    assert INFO_BYTES_TAKE // 2 < len(samples[0]) <= INFO_BYTES_TAKE
    for data in samples:
        raw_cdr.write(writer, data)
    assert await asyncio.to_thread(writer.wait_for_acks, 60 * 10**9)  # all in our reader
    await asyncio.sleep(0.5)  # acknowledged may still be on its way into the reader
    def big() -> int:  # infos of made-up participants decoded and kept
        return len([gid for gid in graph._info_sizes if gid not in graph._alive])

    assert graph.refresh() is False
    assert big() == 2  # the sample that crossed half the budget, and the one that passed it
    await eventually(graph.refresh)  # the rest, refresh after refresh
    assert big() == MAX_UNKNOWN_INFO_BYTES // len(samples[0])


async def test_waiting_for_a_peer_does_not_decode_its_latched_history(
        victim: RosNode, hostile: RosNode) -> None:
    """Before a call, a client waits until the server's participant has matched its readers
    (`peers_know_our_readers`): a fresh ros_discovery_info reader hears that participant's
    latched info. It took up to 1,000 waiting samples at once through cyclonedds' own decoder,
    so a peer keeping a deep latched history of large infos made every such wait decode
    all of them (24 here, ~2.5 MB each). Each is now taken as it arrives by the node's
    reader thread, only its gid kept: the wait's peak of traced memory stays within a few
    samples, and the peer is still confirmed."""
    flood = 24
    writer = hostile.create_writer(DISCOVERY_TOPIC, DISCOVERY_TYPE,
                                   qos.DISCOVERY_INFO.with_(depth=flood))
    huge = _info(hostile.codecs.of(DISCOVERY_TYPE), hostile.participant.guid.bytes, "huge",
                 150_000)
    for _ in range(flood):  # (kept by the writer for late readers: transient-local)
        raw_cdr.write(writer, huge)
    peer = participant_prefix(hostile.participant.guid.bytes)
    tracemalloc.start()
    try:
        confirmed = await peers_know_our_readers(victim, {peer}, timeout=30.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert confirmed == {peer}
    assert peak < 4 * len(huge), f"{peak / len(huge):.1f} samples' worth held"
