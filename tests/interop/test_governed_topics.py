"""The CLI's sending commands refuse where a bridge governs the robot (`cli/_governed.py`).

`rcan-rtps run` marks the endpoints the robot obeys (velocity, trajectories, the e-stop's, its
action clients) with its robot's id in USER_DATA; `topic pub`, `bag play`, `service call` and
`action send_goal` on one of those topics would command the robot past the bridge's roles,
limits, approvals, audit and e-stop, so they refuse unless `--ungoverned`. Against a real
`run --sim` (its own robot a real ROS 2 node) and a real rclpy subscriber on the marked topic.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from cyclonedds.idl import make_idl_struct
from waiting import eventually, eventually_sync

from rcan_rtps.cli._governed import GovernorGuard
from rcan_rtps.ros import graph as graph_mod
from rcan_rtps.ros.bag import BagWriter
from rcan_rtps.ros.errors import WireError
from rcan_rtps.ros.names import mangle_topic
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.serialization import serialize
from rcan_rtps.ros.typesys.store import TypeStore
from tests.interop.test_demo import Demo, _run_demo

TWIST = "geometry_msgs/msg/Twist"
STRING = "std_msgs/msg/String"
CLI_TIMEOUT = 60


@pytest.fixture
def demo(tmp_path: Path, domain_id: int) -> Iterator[Demo]:
    yield from _run_demo(tmp_path, domain_id, "--state-dir", str(tmp_path / "state"))


def cli(demo: Demo, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "ROS_DOMAIN_ID": str(demo.domain_id),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}  # as the demo keeps to loopback
    return subprocess.run([sys.executable, "-m", "rcan_rtps", *args], env=env, text=True,
                          capture_output=True, timeout=CLI_TIMEOUT)


def status(demo: Demo) -> dict[str, Any]:
    request = urllib.request.Request(demo.url + "/api/status",
                                     headers={"Authorization": f"Bearer {demo.user}"})
    with urllib.request.urlopen(request, timeout=10) as reply:
        body: dict[str, Any] = json.loads(reply.read())
    return body


def refused(done: subprocess.CompletedProcess[str], demo: Demo, name: str) -> None:
    ruri = status(demo)["ruri"]
    assert done.returncode == 1, (done.stdout, done.stderr)
    assert f"{name} is governed: the rcan-rtps bridge of {ruri}" in done.stderr, done.stderr
    assert "--ungoverned" in done.stderr
    assert "Traceback" not in done.stderr


def test_topic_pub_on_the_bridges_velocity_topic_is_refused(demo: Demo) -> None:
    done = cli(demo, "topic", "pub", "/robot1/cmd_vel", TWIST, "{linear: {x: 0.5}}", "--once")
    refused(done, demo, "/robot1/cmd_vel")
    assert "publishing #" not in done.stdout  # nothing was sent
    # Another topic is no one's to govern.
    other = cli(demo, "topic", "pub", "/robot1/chatter", STRING, "{data: hi}", "--once",
                "-w", "0")
    assert other.returncode == 0 and "publishing #1" in other.stdout, other.stderr


def test_ungoverned_sends_and_the_bridge_lists_the_sender(demo: Demo) -> None:
    env = {**os.environ, "ROS_DOMAIN_ID": str(demo.domain_id),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}  # as the demo keeps to loopback
    proc = subprocess.Popen(
        [sys.executable, "-m", "rcan_rtps", "topic", "pub", "/robot1/cmd_vel", TWIST,
         "{}", "--times", "100", "--rate", "20", "--ungoverned"],
        env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        def listed() -> bool:
            return any(f["topic"] == "/robot1/cmd_vel" and not f["expected"]
                       for f in status(demo)["foreign_publishers"])
        eventually_sync(listed, timeout=30, what="the ungoverned sender in STATUS")
        out, err = proc.communicate(timeout=CLI_TIMEOUT)  # zero twists, 5 s of them
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert "publishing #100" in out, err
    assert "warning: /robot1/cmd_vel is governed by" in err and "ungoverned" in err, err


def test_action_send_goal_and_its_services_are_refused(demo: Demo) -> None:
    """The bridge's navigate client is seen from the start (its status reader), before its
    first goal makes the goal writers."""
    done = cli(demo, "action", "send_goal", "/robot1/navigate_to_pose",
               "nav2_msgs/action/NavigateToPose", "{pose: {pose: {position: {x: 1.0}}}}",
               "--timeout", "20")
    refused(done, demo, "/robot1/navigate_to_pose")
    assert "Sending goal" not in done.stdout
    cancel = cli(demo, "service", "call", "/robot1/navigate_to_pose/_action/cancel_goal",
                 "action_msgs/srv/CancelGoal", "{}", "--timeout", "20")
    assert cancel.returncode == 1, cancel.stderr
    assert "/robot1/navigate_to_pose is governed" in cancel.stderr, cancel.stderr


def _bag(where: Path, topic: str, type_name: str, values: dict[str, Any]) -> Path:
    writer = BagWriter(where, TypeStore(distro="jazzy"), flush_period=60)
    writer.add_topic(topic, type_name, [])
    for i in range(20):
        writer.write(topic, 1_000_000_000 + i * 50_000_000, serialize(type_name, values))
    writer.close()
    return where


def test_bag_play_onto_a_governed_topic_is_refused(demo: Demo, tmp_path: Path) -> None:
    bag = _bag(tmp_path / "drive", "/robot1/cmd_vel", TWIST, {"linear": {"x": 1.0}})
    refused(cli(demo, "bag", "play", str(bag)), demo, "/robot1/cmd_vel")
    # remapped away from the robot, it plays
    done = cli(demo, "bag", "play", str(bag), "-m", "/robot1/cmd_vel:=/replay/cmd_vel")
    assert done.returncode == 0, done.stderr


def test_nothing_moved_the_robot_while_refusing(demo: Demo) -> None:
    """The refused commands sent nothing: the robot stays at rest where it started."""
    def at_rest() -> dict[str, Any] | None:
        body = status(demo)
        return body if body["ros"]["connected"] and body["telemetry"]["position"] else None
    before = eventually_sync(at_rest, timeout=20, what="the robot's position")["telemetry"]
    for _ in range(3):
        cli(demo, "topic", "pub", "/robot1/cmd_vel", TWIST, "{linear: {x: 1.0}}", "--times",
            "5", "--rate", "20")
    time.sleep(0.5)
    after = status(demo)["telemetry"]
    assert after["position"] == before["position"], (before, after)


def test_an_arm_trajectory_topic_is_governed_before_the_first_arm_command(demo: Demo) -> None:
    """Red team 24: the bridge made its trajectory writer on first use (an idle bridge builds
    no JointTrajectory), so an idle bridge's arm topic carried no mark, and `topic pub` there
    drove the arm past the bridge until the bridge had itself sent a trajectory."""
    topic = "/robot1/joint_trajectory_controller/joint_trajectory"
    done = cli(demo, "topic", "pub", topic, "trajectory_msgs/msg/JointTrajectory", "{}",
               "--once", "-w", "0")
    refused(done, demo, topic)
    assert "publishing #" not in done.stdout


# std_msgs/String as a plain DDS peer writes it (no rmw, no typehash).
_PeerString = make_idl_struct("String_", "std_msgs::msg::dds_::String_", {"data": str})


def test_a_peers_mark_is_shown_bounded_and_escaped(domain_id: int) -> None:
    """Red team 24: the governor's name is a peer's USER_DATA, of any length and bytes. A
    60 KB mark came out whole in the error's one line; it is cut (with its length said), what
    does not print escaped, bytes that are no UTF-8 replaced — and still refused."""
    from cyclonedds.core import Policy
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.pub import DataWriter
    from cyclonedds.qos import Qos
    from cyclonedds.topic import Topic

    mark = b"governed_by=\x1b]0;x" + b"A" * 60_000 + b";"  # `;` ends the value: "\x1b]0"
    long_mark = b"governed_by=\xff\x1b[2J" + b"B" * 60_000 + b";"
    participant = DomainParticipant(domain_id)
    writers = [DataWriter(participant, Topic(participant, f"rt/{name}", _PeerString),
                          qos=Qos(Policy.Userdata(data)))
               for name, data in (("short", mark), ("long", long_mark))]
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    try:
        for name in ("short", "long"):
            done = subprocess.run(
                [sys.executable, "-m", "rcan_rtps", "topic", "pub", f"/{name}", STRING,
                 "{data: hi}", "--once", "-w", "0"],
                env=env, text=True, capture_output=True, timeout=CLI_TIMEOUT)
            assert done.returncode == 1, (done.stdout, done.stderr)
            assert "publishing #" not in done.stdout
            assert f"/{name} is governed" in done.stderr, done.stderr
            assert "\x1b" not in done.stderr  # escaped: `\\x1b`
            assert len(done.stderr) < 1000, len(done.stderr)
        assert "\ufffd\\x1b[2JBBB" in done.stderr and "(60005 characters)" in done.stderr
    finally:
        del writers, participant


def test_a_bridge_that_comes_while_sending_ends_the_sending(tmp_path: Path,
                                                           domain_id: int) -> None:
    """Red team 24: the look while sending (every LOOK_PERIOD) had no test of its own — a
    `topic pub --rate` already sending when `run` starts stops at the bridge's mark."""
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}  # as the demo keeps to loopback
    proc = subprocess.Popen(
        [sys.executable, "-m", "rcan_rtps", "topic", "pub", "/robot1/cmd_vel", TWIST, "{}",
         "--rate", "10", "-w", "0"],
        env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    demo = _run_demo(tmp_path, domain_id, "--state-dir", str(tmp_path / "state"))
    try:
        assert proc.stdout is not None
        while "publishing #1" not in proc.stdout.readline():  # sending, no governor yet
            assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
        running = next(demo)
        out, err = proc.communicate(timeout=CLI_TIMEOUT)
        refused(subprocess.CompletedProcess(proc.args, proc.returncode, out, err), running,
                "/robot1/cmd_vel")
    finally:
        proc.kill()
        demo.close()  # the bridge stopped as the fixture stops it


async def test_a_governor_behind_unread_discovery_is_still_found(
        domain_id: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """A refresh takes so much discovery at a time (`REFRESH_TAKE`, red team 32): behind a
    large graph or a flood, the bridge's governed writer may not be read within the look
    before the first send (GOVERNOR_LOOK_S), and the command sent past it. The look goes on
    until the graph has read what was waiting. Here a refresh takes 4 samples, and a
    participant's 300 writers come before its governed one."""
    with RosNode("crowd", "/robot1", domain_id=domain_id,
                 governed_by="rcan://registry.local/acme/rover/unit-0001") as crowd, \
            RosNode("cli", "/", domain_id=domain_id) as me:
        for i in range(300):
            crowd.create_publisher(f"/crowd/t{i}", STRING)
        crowd.create_publisher("/robot1/cmd_vel", TWIST, governed=True)  # the last one
        seen = graph_mod.RosGraph(me)  # all of it arrived, before the guard's graph exists
        await eventually(lambda: (seen.refresh(), [e for e in seen.endpoints()
                                                   if e.governed_by])[1], timeout=30)
        seen.close()
        monkeypatch.setattr(graph_mod, "REFRESH_TAKE", 4)
        graph = graph_mod.RosGraph(me)  # its readers hold every endpoint, unread
        guard = GovernorGuard(graph, {mangle_topic("/robot1/cmd_vel"): "/robot1/cmd_vel"},
                              allowed=False)
        with pytest.raises(WireError, match="is governed"):
            await guard.look_before_sending()
        graph.close()


async def test_settle_reads_all_waiting_discovery(domain_id: int,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """`RosGraph.settle` (the CLI's views: `topic list`, `node info`) returned once its time
    was up and every ROS participant had announced its nodes, whatever discovery still waited
    unread: with a refresh taking so much at a time (`REFRESH_TAKE`, 4 here), a large graph
    was listed in part."""
    with RosNode("crowd", "/", domain_id=domain_id) as crowd, \
            RosNode("cli", "/", domain_id=domain_id) as me:
        for i in range(300):
            crowd.create_publisher(f"/crowd/t{i}", STRING)
        seen = graph_mod.RosGraph(me)
        await eventually(lambda: (seen.refresh(), len(_crowd_topics(seen)) == 300)[1],
                         timeout=30)
        seen.close()
        monkeypatch.setattr(graph_mod, "REFRESH_TAKE", 4)
        graph = graph_mod.RosGraph(me)  # its readers hold every endpoint, unread
        await graph.settle(0.0, 30.0)
        assert len(_crowd_topics(graph)) == 300
        graph.close()


def _crowd_topics(graph: graph_mod.RosGraph) -> set[str]:
    return {e.ros_name for e in graph.endpoints() if e.ros_name.startswith("/crowd/")}
