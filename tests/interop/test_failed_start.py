"""A start that fails leaves no trace: nothing on the robot's graph, no audit entry.

`rcan-rtps run --config` is run as a real subprocess with a bad token, a short token, a port in
use and a bad audit key. Meanwhile a plain DDS participant of the test watches the domain for
new participants and an rclpy robot listens on `cmd_vel`: neither may see the failed bridge.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsParticipant
from oracle.client import RclpyOracle
from waiting import eventually_sync

from rcan_rtps.ros.participant import RosNode

TOKEN = "t" * 32


DEFAULT_API = "auth_token_env: RCAN_BRIDGE_TOKEN"


def _config(tmp: Path, domain_id: int, port: int, api: str | None = None) -> Path:
    path = tmp / "robot.rcan.yaml"
    path.write_text(textwrap.dedent(f"""\
        robot:
          ruri: rcan://registry.local/acme/rover/unit-0001
          name: Test Rover
        bridge:
          ros2: {{namespace: /robot1, node_name: rcan_bridge, domain_id: {domain_id}}}
          api: {{host: 127.0.0.1, port: {port}, {api or DEFAULT_API}}}
          safety: {{max_linear_vel: 1.0, max_angular_vel: 1.0}}
          audit: {{path: {tmp / "audit" / "audit.jsonl"}, key_path: {tmp / "audit.key"}}}
        """))
    return path


def _run(config: Path, token: str | None) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "RCAN_BRIDGE_TOKEN"}
    if token is not None:
        env["RCAN_BRIDGE_TOKEN"] = token
    return subprocess.run([sys.executable, "-m", "rcan_rtps", "run", "--config", str(config),
                           "--no-mdns"], capture_output=True, text=True, env=env, timeout=60)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ParticipantWatch:
    """Every DDS participant that appears on the domain (taken without a listener)."""

    def __init__(self, domain_id: int) -> None:
        self.node = RosNode("failed_start_watch", domain_id=domain_id)
        self.reader = BuiltinDataReader(self.node.participant, BuiltinTopicDcpsParticipant)
        self.node.track_reader(self.reader)
        self.seen: set[bytes] = set()

    def poll(self) -> set[bytes]:
        for sample in self.reader.take(N=256):
            key = getattr(sample, "key", None)
            if key is not None:
                self.seen.add(key.bytes)
        return self.seen


@pytest.fixture
def robot(jazzy_python: Path, domain_id: int):  # type: ignore[no-untyped-def]
    with RclpyOracle(jazzy_python, "robot", "/robot1", domain_id=domain_id) as oracle:
        oracle.call("subscribe", topic="/robot1/cmd_vel", type="geometry_msgs/msg/Twist")
        yield oracle


SENTINEL = {"linear": {"x": 0.125, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.0}}


def _sentinel(domain_id: int, watch: ParticipantWatch, robot: RclpyOracle) -> tuple[bytes, list]:
    """A participant that joins now and a Twist it sends the robot, once both arrived.

    Returns its participant key and the Twists the robot took before the sentinel one. Sound
    because the failed bridge had exited before this starts: whatever it sent was already in
    the host's socket buffers, while the sentinel must first be discovered (and, for the
    Twist, matched) before anything of it can arrive.
    """
    with RosNode("failed_start_sentinel", "/robot1", domain_id=domain_id) as node:
        key = node.participant.guid.bytes
        eventually_sync(lambda: key in watch.poll(), what="the sentinel participant is seen")
        pub = node.create_publisher("cmd_vel", "geometry_msgs/msg/Twist")
        eventually_sync(lambda: pub.matched_count() >= 1, what="the robot matched the sentinel")
        pub.publish(SENTINEL)
        got: list = []

        def arrived() -> bool:
            got.extend(robot.call("take", topic="/robot1/cmd_vel"))
            return SENTINEL in got

        eventually_sync(arrived, what=lambda: f"the sentinel Twist: {got}")
    return key, got[:got.index(SENTINEL)]


def _bad_key(tmp: Path) -> None:
    (tmp / "audit.key").write_text("not a key")
    os.chmod(tmp / "audit.key", 0o600)


def _bad_signing_key(tmp: Path) -> str:
    """A principal whose signing key file is one byte short of an Ed25519 key."""
    (tmp / "ops.pub").write_bytes(b"\0" * 31)
    return ("principals: [{name: ops, role: OWNER, token_env: RCAN_BRIDGE_TOKEN, signatures: "
            f"{{keys: [{{kid: k1, alg: ed25519, public_key_file: {tmp / 'ops.pub'}}}]}}}}]")


CASES = {  # case: (token, set-up, what the error must say)
    "token unset": (None, None, "unset or empty"),
    "token too short": ("short", None, "at least"),
    "bad audit key": (TOKEN, _bad_key, "cannot load audit key"),
    "bad signing key": (TOKEN, _bad_signing_key, "signatures kid 'k1': the public key is "
                        "neither the 32 raw bytes"),
    "port in use": (TOKEN, "occupy", "cannot listen on 127.0.0.1"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_failed_start_leaves_no_trace(case: str, tmp_path: Path, domain_id: int,
                                        robot: RclpyOracle) -> None:
    token, setup, says = CASES[case]
    port = _free_port()
    occupied, api = None, None
    if setup == "occupy":
        occupied = socket.socket()
        occupied.bind(("127.0.0.1", port))
        occupied.listen(1)
    elif callable(setup):
        api = setup(tmp_path)
    config = _config(tmp_path, domain_id, port, api)
    watch = ParticipantWatch(domain_id)
    # The robot and the watcher know each other.
    eventually_sync(lambda: len(watch.poll()) >= 2, what=lambda: f"two participants: {watch.seen}")
    before = set(watch.poll())
    try:
        done = _run(config, token)
    finally:
        if occupied is not None:
            occupied.close()
    sentinel, twists = _sentinel(domain_id, watch, robot)
    assert done.returncode != 0
    assert done.stderr.startswith("rcan-rtps: error:") and says in done.stderr, done.stderr
    assert "Traceback" not in done.stderr
    assert watch.poll() - {sentinel} == before, "the failed bridge joined the domain"
    assert twists == []
    assert not (tmp_path / "audit" / "audit.jsonl").exists(), "an audit entry was written"
    watch.node.close()


def test_the_watch_does_see_a_bridge_that_starts(tmp_path: Path, domain_id: int) -> None:
    """The control case: the same watch notices a bridge that did join."""
    config = _config(tmp_path, domain_id, _free_port())
    watch = ParticipantWatch(domain_id)
    before = set(watch.poll())
    env = {**os.environ, "RCAN_BRIDGE_TOKEN": TOKEN}
    proc = subprocess.Popen([sys.executable, "-m", "rcan_rtps", "run", "--config", str(config),
                             "--no-mdns"], stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stdout is not None and "ready" in proc.stdout.readline()
        eventually_sync(lambda: watch.poll() != before, what="the bridge joins the domain")
        assert (tmp_path / "audit" / "audit.jsonl").exists()
    finally:
        proc.terminate()
        proc.wait(30)
        watch.node.close()
