"""Issue 9, item 0: the bridge froze for good when it wrote to a topic it also read while a
remote sample arrived on it (the GIL against Cyclone's reader lock, through a DDS listener).

The three reproductions, each against `rcan-rtps run` as a real subprocess for at least
RCAN_DEADLOCK_SECONDS (default 60) while the API keeps taking commands: every request must
get a reply within REQUEST_TIMEOUT, the e-stop must work at the end and SIGTERM must end
the process. On the code before the fix each of them hung within seconds.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest
from oracle.client import RclpyOracle

from .run_process import HammerReport, RunProcess, child_env, hammer, post, state_args

SECONDS = float(os.environ.get("RCAN_DEADLOCK_SECONDS", "60"))
pytestmark = pytest.mark.slow

USER, OWNER = "u" * 32, "o" * 32
DIAGNOSTICS_OK = {"header": {"frame_id": ""}, "status": [
    {"level": 0, "name": "robot: motors", "message": "ok", "hardware_id": "robot"}]}


def _robot_config(tmp_path: Path, domain_id: int) -> Path:
    """A real robot's config: HiTL holds every arm command (each posts a WARN on the
    /robot1/diagnostics topic the bridge also reads)."""
    path = tmp_path / "robot.rcan.yaml"
    path.write_text(textwrap.dedent(f"""\
        robot:
          ruri: rcan://registry.local/acme/rover/unit-0009
          name: Deadlock Rover
        bridge:
          ros2:
            namespace: /robot1
            node_name: rcan_bridge
            domain_id: {domain_id}
            distro: jazzy
            match_timeout_s: 5.0  # a loaded 2-core machine can take over 1 s to match
          hitl:
            timeout_seconds: 300
            gates:
              - {{action: arm_joint, require_auth: true, authorized_roles: [OWNER]}}
          api:
            host: 127.0.0.1
            port: 8765
            principals:
              - {{name: operator, role: USER, token_env: DL_USER_TOKEN}}
              - {{name: owner, role: OWNER, token_env: DL_OWNER_TOKEN}}
          rbac:
            rate_limits_per_min: {{USER: null, OWNER: null}}
          safety:
            max_linear_vel: 1.0
            max_angular_vel: 1.5
            session_timeout_s: 5.0
            workspace: [[-20, -20], [20, -20], [20, 20], [-20, 20]]
          audit:
            path: {tmp_path / "audit.jsonl"}
            key_path: {tmp_path / "audit.key"}
        """))
    return path


def _assert_answered(report: HammerReport, proc: RunProcess, what: str) -> None:
    assert report.hang is None, f"{what}: the API stopped answering: {report.hang}\n" \
                                f"{proc.output()}"
    assert report.seconds >= SECONDS, report
    assert report.total > 0 and all(code < 500 for code in report.replies), (
        report.replies, report.errors)


async def _estop_and_stop(proc: RunProcess, token: str) -> None:
    code, body = await post(proc.url, token, {"action": "estop"})
    assert code == 200 and body["outcome"] == "executed", body
    proc.signal(signal.SIGTERM)
    rc = await asyncio.to_thread(proc.wait, 30.0)
    assert rc == 0, f"SIGTERM did not end the bridge cleanly (rc={rc})\n{proc.output()}"


def _move(i: int) -> dict[str, Any] | None:
    if i % 5 == 4:
        return None  # a status read now and then
    return {"action": "move", "params": {"linear_x": 0.2 + 0.01 * (i % 10),
                                         "angular_z": 0.0}}


async def test_hitl_with_rclpy_robot_publishing_diagnostics_at_100hz(
        tmp_path: Path, jazzy_python: Path, domain_id: int) -> None:
    """(1) `run --config` with HiTL in front of an rclpy robot whose /diagnostics runs at
    100 Hz; every held command posts a WARN on that topic."""
    config = _robot_config(tmp_path, domain_id)
    env = child_env(domain_id, DL_USER_TOKEN=USER, DL_OWNER_TOKEN=OWNER)
    with RclpyOracle(jazzy_python, "robot", "/robot1", domain_id=domain_id) as robot:
        topic = "/robot1/diagnostics"
        await robot.acall("publisher", topic=topic, type="diagnostic_msgs/msg/DiagnosticArray")
        await robot.acall("publish_periodic", topic=topic,
                          type="diagnostic_msgs/msg/DiagnosticArray",
                          value=DIAGNOSTICS_OK, rate=100.0)
        await robot.acall("subscribe", topic="/robot1/cmd_vel", type="geometry_msgs/msg/Twist")
        proc = RunProcess(["run", "--config", str(config), "--port", "0", "--no-mdns"], env,
                          demo=False)
        try:
            assert await robot.acall("wait_subscribers", topic=topic, count=1, timeout=20.0) >= 1
            assert await robot.acall("wait_matched", topic="/robot1/cmd_vel", timeout=20.0) >= 1

            def held(i: int) -> dict[str, Any] | None:
                if i % 4 == 3:
                    return None
                return {"action": "arm_joint", "params": {
                    "joints": ["elbow"], "positions": [0.1 * (i % 7)], "duration_s": 1}}

            held_report, move_report = await asyncio.gather(
                hammer(proc.url, USER, held, SECONDS, rate_hz=10.0),
                hammer(proc.url, OWNER, _move, SECONDS, rate_hz=10.0))
            published = await robot.acall("stop_periodic", topic=topic)
            _assert_answered(held_report, proc, "held arm commands")
            _assert_answered(move_report, proc, "moves")
            # Every arm command was held (and every status read answered), every move
            # executed: how many a busy machine fits in SECONDS is no concern of this test
            # (at load 18 the held ones came at 3.9/s, not the 5/s once asserted).
            assert set(held_report.replies) == {200, 202}, held_report.replies
            assert set(move_report.replies) == {200}, move_report.replies
            assert await robot.acall("take", topic="/robot1/cmd_vel"), "no move reached the robot"
            # The race this reproduces: remote samples arriving while the bridge writes its
            # WARNs on the same topic; the robot's outnumber the bridge's writes.
            assert published > held_report.replies[202], (published, held_report.replies)
            await _estop_and_stop(proc, USER)
        finally:
            proc.kill()


async def test_sim_with_remote_cmd_vel_publisher_at_100hz(tmp_path: Path,
                                                           domain_id: int) -> None:
    """(2) `run --sim` while `rcan-rtps topic pub` writes the same cmd_vel at 100 Hz and the
    API keeps moving the robot."""
    env = child_env(domain_id)
    proc = RunProcess(["run", "--sim", "--port", "0", "--no-mdns",
                       *state_args(tmp_path, "state")], env, demo=True)
    pub = subprocess.Popen(
        [sys.executable, "-m", "rcan_rtps", "--localhost", "topic", "pub", "/robot1/cmd_vel",
         "geometry_msgs/msg/Twist", "{linear: {x: 0.05}}", "-r", "100",
         "--ungoverned"],  # beside the bridge on purpose
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    try:
        report = await hammer(proc.url, proc.owner, _move, SECONDS, rate_hz=12.0)
        assert pub.poll() is None, pub.stderr.read() if pub.stderr else ""
        _assert_answered(report, proc, "moves")
        assert report.replies.get(200, 0) >= 5 * SECONDS, report.replies
        await _estop_and_stop(proc, proc.user)
    finally:
        pub.terminate()
        try:
            pub.wait(timeout=20)
        except subprocess.TimeoutExpired:
            pub.kill()
        proc.kill()


async def test_two_demos_side_by_side(tmp_path: Path, domain_id: int) -> None:
    """(3) Two `run --sim` on one domain: each reads the topics the other writes."""
    env = child_env(domain_id)
    first = RunProcess(["run", "--sim", "--port", "0", "--no-mdns",
                        *state_args(tmp_path, "a")], env, demo=True)
    second: RunProcess | None = None
    try:
        second = RunProcess(["run", "--sim", "--port", "0", "--no-mdns",
                             *state_args(tmp_path, "b")], env, demo=True)
        a, b = await asyncio.gather(
            hammer(first.url, first.owner, _move, SECONDS, rate_hz=12.0),
            hammer(second.url, second.owner, _move, SECONDS, rate_hz=12.0))
        _assert_answered(a, first, "first demo")
        _assert_answered(b, second, "second demo")
        await _estop_and_stop(first, first.user)
        await _estop_and_stop(second, second.user)
    finally:
        first.kill()
        if second is not None:
            second.kill()
