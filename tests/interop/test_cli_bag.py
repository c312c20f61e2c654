"""`rcan-rtps bag record|play|info` against a real rclpy Jazzy graph; bags checked with the
MCAP library's own ROS 2 decoder and written by rosbags."""

from __future__ import annotations

import os
import selectors
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from oracle.client import RclpyOracle

from .bounded_cli import error_line, run_bounded

# Arrival gaps at the rclpy node carry both processes' scheduling delays: beside the parallel
# phase's workers a message could arrive 0.3 s late (gaps 729/10 ms for 450/100 recorded), so
# the tests that compare them run in the serial phase (scripts/pytest_phases.sh).
PACED = pytest.mark.serial
# `play` waits for the graph's subscriptions to match its writers, but the Fast DDS reader
# learns of our writer on its own schedule; as with ros2 bag play, a start delay covers that
# on a loaded machine.
PLAY_DELAY = "1.0"


def cli(domain_id: int, *args: str, timeout: float = 90) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    return subprocess.run([sys.executable, "-m", "rcan_rtps", *args], capture_output=True,
                          text=True, env=env, timeout=timeout)


def cli_start(domain_id: int, *args: str) -> subprocess.Popen[str]:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    return subprocess.Popen([sys.executable, "-m", "rcan_rtps", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


def wait_for_lines(proc: subprocess.Popen[str], wanted: set[str], timeout: float) -> list[str]:
    assert proc.stdout is not None
    seen: list[str] = []
    line = "-"
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        deadline = time.monotonic() + timeout
        while wanted - set(seen) and time.monotonic() < deadline:
            if sel.select(0.2):
                line = proc.stdout.readline()
                if not line:
                    break
                seen.append(line.strip())
    if wanted - set(seen) and (not line or proc.poll() is not None):  # ended: say how
        _, err = proc.communicate(timeout=10)
        raise AssertionError(f"exited {proc.returncode} before {wanted - set(seen)}; "
                             f"got {seen}; stderr: {err}")
    assert not wanted - set(seen), f"missing {wanted - set(seen)}; got {seen}"
    return seen


@pytest.fixture
def oracle(jazzy_python: Path, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_python, "bag_peer", "/", domain_id=domain_id) as agent:
        yield agent


def take_all(oracle: RclpyOracle, topic: str, count: int, timeout: float = 20) -> list[Any]:
    got: list[Any] = []
    deadline = time.monotonic() + timeout
    while len(got) < count and time.monotonic() < deadline:
        got += oracle.call("take", topic=topic)
        time.sleep(0.1)
    return got


def assert_paced_like(written_ns: list[int], recorded_ns: list[int], rate: float = 1.0) -> None:
    """Played over the recorded time, not dumped at once: the writer's source timestamps
    (when `play` wrote each message, whatever delayed its delivery) are in order and span at
    least half the recorded span at `rate`. `play` keeps its schedule from its start, so a
    stall before its first write shortens the span by that much; half leaves room for it on
    a busy machine. When each message is due is checked without a clock in
    tests/cli/test_bag_playback.py; absolute timing belongs to a benchmark, not here."""
    assert len(written_ns) == len(recorded_ns)
    assert written_ns == sorted(written_ns)
    recorded_span = (recorded_ns[-1] - recorded_ns[0]) / rate
    assert written_ns[-1] - written_ns[0] >= recorded_span / 2, (written_ns, recorded_ns)


def read_bag(path: Path) -> tuple[Any, dict[str, list[tuple[int, Any]]]]:
    (mcap_file,) = path.glob("*.mcap")
    with mcap_file.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        messages: dict[str, list[tuple[int, Any]]] = {}
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            messages.setdefault(channel.topic, []).append((message.log_time, decoded))
        header = reader.get_header()
    return (header, summary), messages


@PACED
def test_record_reads_back_with_the_mcap_library_and_plays_with_its_timing(
        oracle: RclpyOracle, domain_id: int, tmp_path: Path, jazzy_share: Path) -> None:
    oracle.call("publisher", topic="/rec/chatter", type="std_msgs/msg/String")
    oracle.call("publisher", topic="/rec/pose", type="geometry_msgs/msg/PoseStamped",
                qos="sensor")
    bag = tmp_path / "recorded"
    recorder = cli_start(domain_id, "bag", "record", "/rec/chatter", "/rec/pose",
                         "-o", str(bag))
    try:
        try:
            wait_for_lines(recorder, {"Subscribed to topic '/rec/chatter'",
                                      "Subscribed to topic '/rec/pose'"}, timeout=30)
        except AssertionError as missing:  # (once in CI: /rec/pose's publisher unseen)
            seen = cli(domain_id, "topic", "info", "-v", "/rec/pose", timeout=30)
            raise AssertionError(f"{missing}; a fresh participant's `topic info -v "
                                 f"/rec/pose`: {seen.stdout}{seen.stderr}") from None
        time.sleep(1.0)  # the subscriptions' DDS match with Fast DDS
        for i, gap in enumerate([0.1, 0.3, 0.2, 0.4, 0.1]):
            oracle.call("publish", topic="/rec/chatter", type="std_msgs/msg/String",
                        value={"data": f"hello {i}"}, count=1, period=gap)
        oracle.call("publish", topic="/rec/pose", type="geometry_msgs/msg/PoseStamped",
                    value={"header": {"frame_id": "map", "stamp": {"sec": 7}},
                           "pose": {"position": {"x": 1.5}, "orientation": {"w": 1.0}}},
                    count=3, period=0.1)
        time.sleep(0.5)
        recorder.send_signal(signal.SIGINT)
        _, err = recorder.communicate(timeout=30)
        assert recorder.returncode == 0, err
    finally:
        if recorder.poll() is None:
            recorder.kill()

    assert sorted(p.name for p in bag.iterdir()) == ["metadata.yaml", "recorded_0.mcap"]
    (header, summary), messages = read_bag(bag)
    assert header.profile == "ros2"
    schemas = {s.name: s for s in summary.schemas.values()}
    assert {s.encoding for s in schemas.values()} == {"ros2msg"}
    assert schemas["std_msgs/msg/String"].data.decode() == "string data\n"
    pose_def = schemas["geometry_msgs/msg/PoseStamped"].data.decode()
    assert "\nMSG: std_msgs/Header\n" in pose_def and "\nMSG: builtin_interfaces/Time\n" in pose_def
    channels = {c.topic: c for c in summary.channels.values()}
    rclpy_hash = oracle.call("publishers_info", topic="/rec/chatter")[0]["type_hash"]
    assert channels["/rec/chatter"].message_encoding == "cdr"
    assert channels["/rec/chatter"].metadata["topic_type_hash"] == rclpy_hash
    offered = yaml.safe_load(channels["/rec/pose"].metadata["offered_qos_profiles"])
    assert offered[0]["reliability"] == "best_effort"

    assert [m.data for _, m in messages["/rec/chatter"]] == [f"hello {i}" for i in range(5)]
    pose = messages["/rec/pose"][0][1]
    assert pose.header.frame_id == "map" and pose.header.stamp.sec == 7
    assert pose.pose.position.x == 1.5 and len(messages["/rec/pose"]) == 3

    info = cli(domain_id, "bag", "info", str(bag))
    assert info.returncode == 0, info.stderr
    lines = info.stdout.splitlines()
    assert "Files:             recorded_0.mcap" in lines
    assert "Storage id:        mcap" in lines and "Messages:          8" in lines
    assert ("Topic information: Topic: /rec/chatter | Type: std_msgs/msg/String | Count: 5 | "
            "Serialization Format: cdr") in lines

    oracle.call("subscribe_timed", topic="/rec/chatter", type="std_msgs/msg/String",
                field="data", clock="source")
    played = cli(domain_id, "bag", "play", str(bag), "--topics", "/rec/chatter",
                 "-d", PLAY_DELAY)
    assert played.returncode == 0, played.stderr
    got = take_all(oracle, "/rec/chatter", 5)
    assert [value for _, value in got] == [f"hello {i}" for i in range(5)]
    assert_paced_like([arrived for arrived, _ in got],
                       [t for t, _ in messages["/rec/chatter"]])


def write_rosbags_bag(path: Path, offsets: list[float]) -> list[int]:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    twist = store.types["geometry_msgs/msg/Twist"]
    vector = store.types["geometry_msgs/msg/Vector3"]
    start = time.time_ns()
    stamps = [start + round(s * 1e9) for s in offsets]
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/played/cmd_vel", twist.__msgtype__, typestore=store)
        for i, stamp in enumerate(stamps):
            msg = twist(linear=vector(x=float(i), y=0.0, z=0.0),
                        angular=vector(x=0.0, y=0.0, z=0.5))
            writer.write(conn, stamp, store.serialize_cdr(msg, twist.__msgtype__))
    return stamps


@PACED
def test_a_bag_written_by_rosbags_plays_to_rclpy(oracle: RclpyOracle, domain_id: int,
                                                 tmp_path: Path) -> None:
    bag = tmp_path / "from_rosbags"
    stamps = write_rosbags_bag(bag, [0.0, 0.25, 0.35, 0.8, 0.9, 1.3])
    info = cli(domain_id, "bag", "info", str(bag))
    assert info.returncode == 0, info.stderr
    assert "Messages:          6" in info.stdout.splitlines()
    assert "Duration:          1.300000000s" in info.stdout.splitlines()

    oracle.call("subscribe_timed", topic="/played/cmd_vel", type="geometry_msgs/msg/Twist",
                field="linear.x", clock="source")
    played = cli(domain_id, "bag", "play", str(bag), "-d", PLAY_DELAY)
    assert played.returncode == 0, played.stderr
    got = take_all(oracle, "/played/cmd_vel", 6)
    assert [value for _, value in got] == [float(i) for i in range(6)]
    assert_paced_like([arrived for arrived, _ in got], stamps)

    doubled = cli(domain_id, "bag", "play", str(bag), "--rate", "2", "-d", PLAY_DELAY)
    assert doubled.returncode == 0, doubled.stderr
    twice_as_fast = take_all(oracle, "/played/cmd_vel", 6)
    assert [value for _, value in twice_as_fast] == [float(i) for i in range(6)]
    assert_paced_like([written for written, _ in twice_as_fast], stamps, rate=2.0)


def _wait_until_counted(bag: Path, count: int, timeout: float = 20.0) -> None:
    """Until a recording's metadata.yaml counts `count` messages (or `timeout` passed: the
    test's own checks then say what is missing)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        meta = yaml.safe_load((bag / "metadata.yaml").read_text())
        if meta["rosbag2_bagfile_information"]["message_count"] == count:
            return
        time.sleep(0.1)


def test_a_recorder_killed_after_2_s_leaves_a_bag_mcap_and_rosbags_read(
        oracle: RclpyOracle, domain_id: int, tmp_path: Path) -> None:
    """SIGKILL, no clean exit: the bag holds what was recorded until the last flush (at most
    a second before), mcap's sequential reader reads it as it is, and after `bag reindex`
    rosbags reads it as a complete bag."""
    from mcap.exceptions import EndOfFile
    from mcap.reader import NonSeekingReader
    from rosbags.highlevel import AnyReader

    oracle.call("publisher", topic="/crash/chatter", type="std_msgs/msg/String")
    bag = tmp_path / "killed"
    started = time.monotonic()
    recorder = cli_start(domain_id, "bag", "record", "/crash/chatter", "-o", str(bag))
    try:
        wait_for_lines(recorder, {"Subscribed to topic '/crash/chatter'"}, timeout=30)
        oracle.call("wait_subscribers", topic="/crash/chatter")
        time.sleep(0.5)  # the subscription's DDS match with Fast DDS, as above
        oracle.call("publish", topic="/crash/chatter", type="std_msgs/msg/String",
                    value={"data": "before the kill"}, count=5, period=0.05)
        time.sleep(max(0.0, 2.0 - (time.monotonic() - started)))
        _wait_until_counted(bag, 5)  # what metadata.yaml counts is in the file
        recorder.send_signal(signal.SIGKILL)
        recorder.communicate(timeout=30)
    finally:
        if recorder.poll() is None:
            recorder.kill()
    assert recorder.returncode == -signal.SIGKILL

    (mcap_file,) = bag.glob("*.mcap")
    seen = []
    # no summary, no footer: the recorder never closed it
    with mcap_file.open("rb") as stream, pytest.raises(EndOfFile):
        for _, channel, message in NonSeekingReader(stream).iter_messages(log_time_order=False):
            seen.append((channel.topic, message.data))
    assert len(seen) == 5 and {topic for topic, _ in seen} == {"/crash/chatter"}

    info = cli(domain_id, "bag", "info", str(bag))
    assert info.returncode == 1 and "Traceback" not in info.stderr
    assert "bag reindex" in info.stderr

    rebuilt = cli(domain_id, "bag", "reindex", str(bag))
    assert rebuilt.returncode == 0, rebuilt.stderr
    assert f"Reindexed '{mcap_file}': 5 messages" in rebuilt.stdout
    with AnyReader([bag]) as reader:
        assert [c.topic for c in reader.connections] == ["/crash/chatter"]
        got = [reader.deserialize(raw, conn.msgtype).data for conn, _, raw in reader.messages()]
    assert got == ["before the kill"] * 5
    info = cli(domain_id, "bag", "info", str(bag))
    assert info.returncode == 0, info.stderr
    assert "Messages:          5" in info.stdout.splitlines()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=lambda s: s.name)
def test_a_recorder_ended_by_a_signal_closes_a_complete_bag(
        oracle: RclpyOracle, domain_id: int, tmp_path: Path, sig: signal.Signals) -> None:
    """SIGTERM (a supervisor) or SIGHUP (its terminal or ssh session closed) ends `record`
    as Ctrl-C does: the bag closed, complete, read by `bag info` and the mcap library with no
    `bag reindex`. SIGHUP used to kill the recorder, leaving a bag without its summary."""
    oracle.call("publisher", topic="/hup/chatter", type="std_msgs/msg/String")
    bag = tmp_path / "ended"
    recorder = cli_start(domain_id, "bag", "record", "/hup/chatter", "-o", str(bag))
    try:
        wait_for_lines(recorder, {"Subscribed to topic '/hup/chatter'"}, timeout=30)
        oracle.call("wait_subscribers", topic="/hup/chatter")
        time.sleep(0.5)  # the subscription's DDS match with Fast DDS, as above
        oracle.call("publish", topic="/hup/chatter", type="std_msgs/msg/String",
                    value={"data": "before the signal"}, count=3, period=0.05)
        _wait_until_counted(bag, 3)  # until the recorder has them
        recorder.send_signal(sig)
        _, err = recorder.communicate(timeout=30)
    finally:
        if recorder.poll() is None:
            recorder.kill()
    assert recorder.returncode == 0, (recorder.returncode, err)
    info = cli(domain_id, "bag", "info", str(bag))
    assert info.returncode == 0, info.stderr
    assert "Topic: /hup/chatter | Type: std_msgs/msg/String | Count: 3 |" in info.stdout
    _, messages = read_bag(bag)
    assert [m.data for _, m in messages["/hup/chatter"]] == ["before the signal"] * 3


def test_a_message_dds_refuses_is_played_past_and_told_in_one_line(
        oracle: RclpyOracle, domain_id: int, tmp_path: Path) -> None:
    """A bag's string whose CDR claims 2^31 bytes in 4 (red team 22): Cyclone refuses it
    (BAD_PARAMETER), which tracebacked `play`; now the messages around it are played and one
    line at the end says what was not."""
    from rcan_rtps.ros.bag import BagWriter
    from rcan_rtps.ros.serialization import serialize
    from rcan_rtps.ros.typesys.store import TypeStore

    bag = tmp_path / "lying"
    writer = BagWriter(bag, TypeStore(distro="jazzy"), flush_period=60)
    writer.add_topic("/lying/chatter", "std_msgs/msg/String", [])
    lie = b"\x00\x01\x00\x00" + (2**31).to_bytes(4, "little")
    for i, data in enumerate([serialize("std_msgs/msg/String", {"data": "before"}), lie,
                              serialize("std_msgs/msg/String", {"data": "after"})]):
        writer.write("/lying/chatter", 1_000_000_000 + i * 10_000_000, data)
    writer.close()

    oracle.call("subscribe", topic="/lying/chatter", type="std_msgs/msg/String")
    played = cli(domain_id, "bag", "play", str(bag), "-d", PLAY_DELAY)
    assert played.returncode == 1 and "Traceback" not in played.stderr, played.stderr
    (line,) = played.stderr.strip().splitlines()
    assert line.startswith(f"rcan-rtps: error: 1 message(s) of '{bag}' were not published")
    assert "'/lying/chatter' at 1.010000000" in line
    assert [m["data"] for m in take_all(oracle, "/lying/chatter", 2)] == ["before", "after"]


def test_a_message_past_the_sample_size_bound_is_played_past_and_told_in_one_line(
        oracle: RclpyOracle, domain_id: int, tmp_path: Path) -> None:
    """Cyclone sends no sample past the domain's `max_sample_bytes`: its write failed with a
    bare DDSException ("Non specific error"), a traceback out of `play`. Now it is
    SampleTooLarge, saying so, and played past like any message DDS refuses."""
    from rcan_rtps.ros.bag import BagWriter
    from rcan_rtps.ros.serialization import serialize
    from rcan_rtps.ros.typesys.store import TypeStore

    bag = tmp_path / "huge"
    writer = BagWriter(bag, TypeStore(distro="jazzy"), flush_period=60)
    writer.add_topic("/huge/chatter", "std_msgs/msg/String", [])
    for i, text in enumerate(["before", "x" * (2 << 20), "after"]):
        writer.write("/huge/chatter", 1_000_000_000 + i * 10_000_000,
                     serialize("std_msgs/msg/String", {"data": text}))
    writer.close()

    oracle.call("subscribe", topic="/huge/chatter", type="std_msgs/msg/String")
    played = run_bounded(1 << 20, domain_id, "bag", "play", str(bag), "-d", PLAY_DELAY)
    assert played.returncode == 1 and "Traceback" not in played.stderr, played.stderr
    line = error_line(played.stderr)
    assert line.startswith(f"rcan-rtps: error: 1 message(s) of '{bag}' were not published")
    assert "'/huge/chatter' at 1.010000000" in line and "past the largest sample" in line
    assert [m["data"] for m in take_all(oracle, "/huge/chatter", 2)] == ["before", "after"]


def test_a_topic_not_in_cdr_is_not_played(domain_id: int, tmp_path: Path) -> None:
    """A channel whose messages are JSON, with a ROS type's name (red team 22): its bytes
    went out as that type's CDR."""
    from mcap.writer import Writer

    file = tmp_path / "json.mcap"
    with file.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema("std_msgs/msg/String", "ros2msg", b"string data\n")
        channel = writer.register_channel("/json/chatter", "json", schema, {})
        writer.add_message(channel, log_time=1, publish_time=1, data=b'{"data": "hi"}')
        writer.finish()
    played = cli(domain_id, "bag", "play", str(file))
    assert played.returncode == 0, played.stderr
    assert played.stderr.strip() == \
        "warning: '/json/chatter' is encoded 'json', not cdr; not played"
