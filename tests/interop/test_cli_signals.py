"""Every long-running command ends on SIGTERM (a supervisor) and SIGHUP (its terminal or ssh
session closed) as on Ctrl-C: in order, quietly, with exit status 128 + the signal (`sim`:
0, as on Ctrl-C). Before, `sim`, `topic pub|echo|hz|bw`, `bag play`, `service call` and
the graph commands were killed on the spot by SIGHUP, and all but `sim` by SIGTERM.

The ordered end shows on the graph: the command's participant is deleted, so its rclpy peer
drops its node at once. Each command runs with a participant lease of an hour
(CYCLONEDDS_URI), so a command killed instead would stay on the peer's graph for the test's
whole wait. The peer is rclpy on rmw_cyclonedds: rclpy on Fast DDS keeps a participant that
left in order on its graph until its lease ends, as one killed (measured: 10 s either way).
"""

from __future__ import annotations

import os
import pty
import re
import shlex
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest
from oracle.client import OracleEnv, RclpyOracle
from waiting import eventually_sync

from .run_process import child_env, state_args
from .test_cli_bag import _wait_until_counted, write_rosbags_bag

# A killed participant stays on its peers' graph until its lease ends: longer than any wait.
LONG_LEASE = "<Discovery><LeaseDuration>3600s</LeaseDuration></Discovery>"
READY_S = 60.0  # generous: a busy machine
END_S = 30.0  # the command's ordered end, and its node leaving the peer's graph
SIGNALS = pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=lambda s: s.name)


class Command:
    """`python -m rcan_rtps ARGS`, its output drained by threads (a full pipe never blocks
    it), waited for line by line."""

    def __init__(self, domain_id: int, args: Sequence[str], **popen: Any) -> None:
        env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id), "CYCLONEDDS_URI": LONG_LEASE}
        self.proc = subprocess.Popen([sys.executable, "-m", "rcan_rtps", *args], env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, **popen)
        self.stdout: list[str] = []
        self.stderr: list[str] = []
        self._threads = [threading.Thread(target=self._drain, args=(stream, sink), daemon=True)
                         for stream, sink in ((self.proc.stdout, self.stdout),
                                              (self.proc.stderr, self.stderr))]
        for thread in self._threads:
            thread.start()

    @staticmethod
    def _drain(stream: Any, sink: list[str]) -> None:
        for line in stream:
            sink.append(line)

    @property
    def node_name(self) -> str:
        """The hidden node a graph command makes (`cli._common.make_node`)."""
        return f"_rcan_rtps_cli_{self.proc.pid}"

    def output(self) -> str:
        return f"stdout:\n{''.join(self.stdout)}\nstderr:\n{''.join(self.stderr)}"

    def wait_for(self, pattern: str) -> None:
        eventually_sync(lambda: any(re.search(pattern, line) for line in self.stdout),
                        timeout=READY_S, what=lambda: f"{pattern!r} in\n{self.output()}")

    def end_by(self, sig: signal.Signals) -> int:
        self.proc.send_signal(sig)
        code = self.proc.wait(END_S)
        for thread in self._threads:
            thread.join(END_S)
        return code

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@pytest.fixture
def peer(jazzy_cyclone_python: Path, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(OracleEnv(jazzy_cyclone_python, "cyclonedds"), "signal_peer", "/sig",
                     domain_id=domain_id) as agent:
        yield agent


def on_graph(peer: RclpyOracle, name: str) -> bool:
    return any(node == name for node, _ in peer.call("node_names"))


def wait_on_graph(peer: RclpyOracle, command: Command, name: str) -> None:
    eventually_sync(lambda: on_graph(peer, name), timeout=READY_S,
                    what=lambda: f"{name} on the peer's graph\n{command.output()}")


def assert_ended_in_order(peer: RclpyOracle, command: Command, code: int, expected: int,
                          name: str) -> None:
    """The exit status, no traceback, and the command's node gone from the peer's graph (its
    participant deleted, as on Ctrl-C)."""
    assert code == expected, f"exit {code}, expected {expected}\n{command.output()}"
    assert "Traceback" not in "".join(command.stderr), command.output()
    eventually_sync(lambda: not on_graph(peer, name), timeout=END_S,
                    what=f"{name} gone from the peer's graph")


@SIGNALS
def test_topic_pub_stops_publishing(peer: RclpyOracle, domain_id: int,
                                    sig: signal.Signals) -> None:
    peer.call("subscribe", topic="/sig/chatter", type="std_msgs/msg/String")
    command = Command(domain_id, ["topic", "pub", "/sig/chatter", "std_msgs/msg/String",
                                  "{data: hello}", "-r", "20"])
    try:
        eventually_sync(lambda: peer.call("take", topic="/sig/chatter"), timeout=READY_S,
                        what=command.output)
        code = command.end_by(sig)
    finally:
        command.kill()
    assert_ended_in_order(peer, command, code, 128 + sig, command.node_name)
    assert peer.call("publishers_info", topic="/sig/chatter") == []


@SIGNALS
@pytest.mark.parametrize("verb", ["echo", "hz", "bw"])
def test_a_topic_reader_ends_with_its_subscription(peer: RclpyOracle, domain_id: int,
                                                  verb: str, sig: signal.Signals) -> None:
    peer.call("publisher", topic="/sig/heard", type="std_msgs/msg/String")
    peer.call("publish_periodic", topic="/sig/heard", type="std_msgs/msg/String",
              value={"data": "tick"}, rate=20.0)
    command = Command(domain_id, ["topic", verb, "/sig/heard"])
    try:
        eventually_sync(lambda: peer.call("subscriptions_info", topic="/sig/heard"),
                        timeout=READY_S, what=command.output)
        if verb == "echo":
            command.wait_for(r"^---$")  # it printed a whole message
        code = command.end_by(sig)
    finally:
        command.kill()
        peer.call("stop_periodic", topic="/sig/heard")
    assert_ended_in_order(peer, command, code, 128 + sig, command.node_name)
    if verb == "echo":  # nothing cut short: the last message printed whole
        assert command.stdout[-1] == "---\n", command.output()


@SIGNALS
def test_bag_play_stops_publishing(peer: RclpyOracle, domain_id: int, tmp_path: Path,
                                   sig: signal.Signals) -> None:
    bag = tmp_path / "looped"
    write_rosbags_bag(bag, [0.0, 0.1, 0.2])
    peer.call("subscribe", topic="/played/cmd_vel", type="geometry_msgs/msg/Twist")
    command = Command(domain_id, ["bag", "play", str(bag), "--loop"])
    try:
        eventually_sync(lambda: peer.call("take", topic="/played/cmd_vel"), timeout=READY_S,
                        what=command.output)
        code = command.end_by(sig)
    finally:
        command.kill()
    assert_ended_in_order(peer, command, code, 128 + sig, command.node_name)
    assert peer.call("publishers_info", topic="/played/cmd_vel") == []


@SIGNALS
def test_a_pending_service_call_ends(peer: RclpyOracle, domain_id: int,
                                     sig: signal.Signals) -> None:
    peer.call("service_server", name="/sig/slow", type="std_srvs/srv/Trigger", delay=3600.0)
    command = Command(domain_id, ["service", "call", "/sig/slow", "std_srvs/srv/Trigger",
                                  "--timeout", "3600"])
    try:
        command.wait_for(r"^requester: making request")
        eventually_sync(lambda: peer.call("service_requests", name="/sig/slow"),
                        timeout=READY_S, what=command.output)  # the call is pending
        code = command.end_by(sig)
    finally:
        command.kill()
    assert_ended_in_order(peer, command, code, 128 + sig, command.node_name)
    assert "response:" not in "".join(command.stdout)


@SIGNALS
def test_param_get_waiting_for_its_node_ends(peer: RclpyOracle, domain_id: int,
                                             sig: signal.Signals) -> None:
    command = Command(domain_id, ["param", "get", "/sig/nobody_here", "speed",
                                  "--timeout", "3600"])
    try:
        wait_on_graph(peer, command, command.node_name)
        code = command.end_by(sig)
    finally:
        command.kill()
    assert_ended_in_order(peer, command, code, 128 + sig, command.node_name)


@SIGNALS
def test_sim_stops_its_robot_as_on_ctrl_c(peer: RclpyOracle, domain_id: int,
                                          sig: signal.Signals) -> None:
    """Its loop ends, its goal servers close, its node leaves the graph; exit 0, as on
    Ctrl-C (a stop is how a simulator is meant to end)."""
    peer.call("subscribe", topic="/sigbot/odom", type="nav_msgs/msg/Odometry", qos="sensor")
    command = Command(domain_id, ["sim", "--namespace", "/sigbot"])
    try:
        command.wait_for(r"^rcan-rtps sim ready")
        eventually_sync(lambda: peer.call("take", topic="/sigbot/odom"), timeout=READY_S,
                        what=command.output)
        code = command.end_by(sig)
    finally:
        command.kill()
    assert_ended_in_order(peer, command, code, 0, "sim_robot")
    assert peer.call("publishers_info", topic="/sigbot/odom") == []


@SIGNALS
def test_send_goal_waiting_for_its_server_ends_without_sending(
        domain_id: int, sig: signal.Signals) -> None:
    """A stop before the goal is sent ends the command then: before, the signal was only
    noted, the command waited out --timeout for a server and would have sent the goal."""
    command = Command(domain_id, ["action", "send_goal", "/sig/nobody", "nav2_msgs/action/"
                                  "NavigateToPose", "{}", "--timeout", "3600"])
    try:
        command.wait_for(r"^Waiting for an action server")
        code = command.end_by(sig)
    finally:
        command.kill()
    assert code == 128 + sig, command.output()
    assert "Traceback" not in "".join(command.stderr), command.output()
    assert "Sending goal" not in "".join(command.stdout), command.output()


# -- a real closed terminal: two SIGHUPs ---------------------------------------------------
# Closing a terminal (or dropping an ssh session) hangs up its foreground job twice: its
# shell passes the SIGHUP on to its jobs, then the kernel sends one more as the shell, the
# session leader, exits. `run` and `action send_goal` took a second signal as someone
# insisting and exited at once, skipping the ordered end the first had begun.

def closed_terminal(args: Sequence[str], env: dict[str, str], tmp_path: Path,
                    ready: str) -> int:
    """`python -m rcan_rtps ARGS` as the foreground job of an interactive bash in a
    terminal, which is closed once `ready` is in its output; its exit status."""
    out, status = tmp_path / "terminal.out", tmp_path / "terminal.status"
    line = " ".join(shlex.quote(word) for word in [sys.executable, "-m", "rcan_rtps", *args])
    # The sh between them outlives the hangup (a trap, which its child does not inherit) to
    # write down how the command ended.
    job = (f"sh -c {shlex.quote(f'trap : HUP; {line} >{out} 2>&1; echo $? >{status}')}\n")
    pid, terminal = pty.fork()
    if pid == 0:  # the child: bash, leading a session on the terminal
        os.execve("/bin/bash", ["bash", "--norc", "--noprofile", "-i"], env)
    try:
        os.write(terminal, job.encode())
        eventually_sync(lambda: out.exists() and ready in out.read_text(), timeout=READY_S,
                        what=lambda: f"{ready!r} in\n{out.read_text() if out.exists() else ''}")
    finally:
        os.close(terminal)  # the terminal goes away
        os.waitpid(pid, 0)
    eventually_sync(lambda: status.exists() and status.read_text().strip(), timeout=END_S,
                    what=lambda: f"the command's end\n{out.read_text()}")
    assert "Traceback" not in out.read_text(), out.read_text()
    return int(status.read_text())


def test_run_in_a_closed_terminal_stops_in_order(tmp_path: Path, domain_id: int) -> None:
    code = closed_terminal(["run", "--sim", "--port", "0", "--no-mdns",
                            *state_args(tmp_path, "state")], child_env(domain_id), tmp_path,
                           "rcan-rtps ready")
    assert code == 0, (tmp_path / "terminal.out").read_text()  # not 130: "exiting now"
    audit = (tmp_path / "state" / "audit.jsonl").read_text()
    assert '"event":"BRIDGE_STOPPED"' in audit  # the robot halted, the stop audited


def test_send_goal_in_a_closed_terminal_cancels_its_goal(peer: RclpyOracle, domain_id: int,
                                                         jazzy_share: Path,
                                                         tmp_path: Path) -> None:
    peer.call("action_server", name="/sig/fibonacci", mode="slow")
    status = "/sig/fibonacci/_action/status"
    peer.call("subscribe", topic=status, type="action_msgs/msg/GoalStatusArray")
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    code = closed_terminal(["--idl-path", str(jazzy_share), "action", "send_goal",
                            "/sig/fibonacci", "test_msgs/action/Fibonacci", "{order: 1000}"],
                           env, tmp_path, "Goal accepted")
    assert code == 128 + signal.SIGHUP, (tmp_path / "terminal.out").read_text()
    seen: list[int] = []

    def canceled() -> bool:
        for message in peer.call("take", topic=status):
            seen.extend(s["status"] for s in message["status_list"])
        return CANCELED in seen

    eventually_sync(canceled, timeout=END_S, what=lambda: f"CANCELED among {seen}")


CANCELED = 5  # action_msgs/msg/GoalStatus.STATUS_CANCELED


# -- nohup: a SIGHUP ignored from the start stays ignored ------------------------------------

def test_bag_record_under_nohup_outlives_a_hangup(peer: RclpyOracle, domain_id: int,
                                                  tmp_path: Path) -> None:
    """`nohup rcan-rtps bag record …` promises to outlive its terminal: it records what comes
    after a SIGHUP, and ends (bag closed) on SIGTERM. Before, the recorder put its own handler
    over nohup's and ended on the SIGHUP."""
    peer.call("publisher", topic="/sig/kept", type="std_msgs/msg/String")
    bag = tmp_path / "kept"
    command = Command(domain_id, ["bag", "record", "/sig/kept", "-o", str(bag)],
                      preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
    try:
        command.wait_for(r"^Subscribed to topic '/sig/kept'")
        command.proc.send_signal(signal.SIGHUP)
        peer.call("wait_subscribers_matched", topic="/sig/kept")  # its reader, at DDS level
        peer.call("publish", topic="/sig/kept", type="std_msgs/msg/String",
                  value={"data": "after the hangup"}, count=3, period=0.05)
        _wait_until_counted(bag, 3)
        code = command.end_by(signal.SIGTERM)
    finally:
        command.kill()
    assert code == 0, command.output()
    assert "Recorded 3 messages" in "".join(command.stdout), command.output()


# -- a background job: SIGINT ignored from the start is still a stop --------------------------

def _sigint_ignored() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # as a non-interactive shell starts `cmd &`


def test_run_started_as_a_background_job_stops_on_sigint(tmp_path: Path, domain_id: int) -> None:
    """A script's `rcan-rtps run --sim &` starts with SIGINT ignored (bash does that to the
    background jobs of a non-interactive shell), and `kill -INT` is how such a script stops it
    (scripts/readme_main.sh does). Only nohup's SIGHUP stays ignored: a SIGINT ignored at
    start was kept ignored, and the bridge ran on."""
    command = Command(domain_id, ["run", "--sim", "--port", "0", "--no-mdns",
                                  *state_args(tmp_path, "state")], preexec_fn=_sigint_ignored)
    try:
        command.wait_for(r"^rcan-rtps ready")
        code = command.end_by(signal.SIGINT)
    finally:
        command.kill()
    assert code == 0, command.output()
    assert "Traceback" not in command.output(), command.output()
    audit = (tmp_path / "state" / "audit.jsonl").read_text()
    assert '"event":"BRIDGE_STOPPED"' in audit


def test_topic_pub_started_as_a_background_job_stops_on_sigint(peer: RclpyOracle,
                                                              domain_id: int) -> None:
    peer.call("subscribe", topic="/sig/bg", type="std_msgs/msg/String")
    command = Command(domain_id, ["topic", "pub", "/sig/bg", "std_msgs/msg/String",
                                  "{data: hello}", "-r", "20"], preexec_fn=_sigint_ignored)
    try:
        eventually_sync(lambda: peer.call("take", topic="/sig/bg"), timeout=READY_S,
                        what=command.output)
        code = command.end_by(signal.SIGINT)
    finally:
        command.kill()
    assert_ended_in_order(peer, command, code, 128 + signal.SIGINT, command.node_name)
