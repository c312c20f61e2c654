"""Our writes past the domain's bound on sample size (`max_sample_bytes`, or the user's
CYCLONEDDS_URI `<MaxSampleSize>`), on every write path besides `RosPublisher.publish_cdr`
(red team 33): Cyclone refuses each with a bare DDS_RETCODE_ERROR ("Non specific error"),
which came out of `service call` as a traceback, out of a server's reply task as an
unretrieved task exception, and out of endpoint creation when the node's own
ros_discovery_info no longer fit. Each runs in a process of its own, whose first node sets
the bound (small, so that nothing needs hundreds of MB)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from oracle.client import OracleEnv, RclpyOracle

from .bounded_cli import error_line, run_bounded
from .run_process import RunProcess, child_env, state_args

BOUND = 65536  # the least `ros2.max_sample_bytes` allows; a 100 KB string is past it
BIG = "x" * 100_000

# Serves /big_echo (test_msgs/srv/BasicTypes) with a reply of 100 KB, past BOUND, then
# prints how many requests it served; stops when stdin closes.
_SERVER_BOUNDED = f"""
import asyncio, sys
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.service_server import ServiceServer

async def main():
    node = RosNode("big_server", domain_id=int(sys.argv[1]), max_sample_bytes={BOUND})
    served = []
    async def handle(request):
        served.append(request)
        return {{"string_value": "y" * 100_000}}
    server = ServiceServer(node, "/big_echo", "test_msgs/srv/BasicTypes", handle)
    print("ready", flush=True)
    await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)
    await server.close()
    node.close()
    print("served", len(served), flush=True)

asyncio.run(main())
"""

# A node bounded at 1 KiB making 100 publishers: its ros_discovery_info (16 bytes a gid on
# Jazzy) soon no longer fits.
_MANY_ENDPOINTS = """
import sys
from rcan_rtps.ros.participant import RosNode
node = RosNode("crowded", domain_id=int(sys.argv[1]), max_sample_bytes=1024)
pubs = [node.create_publisher(f"/crowd/t{i}", "std_msgs/msg/String") for i in range(100)]
pubs[0].publish({"data": "still works"})
for pub in pubs:
    pub.close()
node.close()
print("made", len(pubs), flush=True)
"""


def _env(domain_id: int, **extra: str) -> dict[str, str]:
    return {**os.environ, "ROS_DOMAIN_ID": str(domain_id), **extra}


def _python(code: str, domain_id: int, *args: str, env: dict[str, str] | None = None,
            timeout: float = 90) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", code, str(domain_id), *args],
                          capture_output=True, text=True, timeout=timeout,
                          env=env or _env(domain_id))


@pytest.fixture
def oracle(jazzy_oracle: OracleEnv, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_oracle, "size_peer", "/", domain_id=domain_id) as agent:
        yield agent


def test_a_service_request_past_the_bound_is_a_clear_error(oracle: RclpyOracle,
                                                            domain_id: int) -> None:
    """`service call` (and every ServiceClient call: action goals, cancels, results,
    parameters) wrote its request with raw_cdr and let Cyclone's DDSException out."""
    oracle.call("echo_server", name="/echo")
    done = run_bounded(BOUND, domain_id, "service", "call", "/echo",
                       "test_msgs/srv/BasicTypes", f"{{string_value: {BIG}}}")
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    line = error_line(done.stderr)
    assert "test_msgs/srv/BasicTypes_Request" in line, line
    assert f"past the largest sample this process sends on domain {domain_id} " \
           f"({BOUND} bytes: max_sample_bytes)" in line, line
    assert oracle.call("service_requests", name="/echo") == []
    small = run_bounded(BOUND, domain_id, "service", "call", "/echo",
                        "test_msgs/srv/BasicTypes", "{string_value: small}")
    assert small.returncode == 0, small.stderr  # the bound, not the service, refused it


def test_a_reply_past_the_bound_is_not_sent_and_said_once(jazzy_cyclone_python: Path,
                                                          domain_id: int) -> None:
    """A ServiceServer's reply written in the request's task: Cyclone's DDSException ended
    the task, and asyncio logged it with a traceback ("Task exception was never
    retrieved"). Now the reply is not sent (the client times out, as for a failing
    handler) and the log says why in one line."""
    server = subprocess.Popen([sys.executable, "-c", _SERVER_BOUNDED, str(domain_id)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, env=_env(domain_id))
    try:
        assert server.stdout is not None and server.stdout.readline() == "ready\n"
        with RclpyOracle(OracleEnv(jazzy_cyclone_python, "cyclonedds"), "size_client", "/",
                         domain_id=domain_id) as client:  # our server: Cyclone mapping only
            reply = client.call("service_call", name="/big_echo",
                                type="test_msgs/srv/BasicTypes",
                                value={"string_value": "small"}, wait=5.0)
        assert reply == {"timeout": True}
        out, err = server.communicate("", timeout=60)
    finally:
        if server.poll() is None:
            server.kill()
            server.wait()
    assert server.returncode == 0 and "Traceback" not in err, err
    assert out.splitlines()[-1] == "served 1"
    [line] = [line for line in err.splitlines() if "the reply was not sent" in line]
    assert "test_msgs/srv/BasicTypes_Response" in line and f"({BOUND} bytes" in line, line


def test_a_nodes_discovery_info_past_the_bound_does_not_fail_its_endpoints(
        domain_id: int) -> None:
    """Each endpoint made or deleted writes the node's whole ros_discovery_info: past the
    bound, Cyclone's DDSException came out of `create_publisher` (and of `close`). The
    endpoints work without it (DDS discovery matches them): said once, not raised."""
    done = _python(_MANY_ENDPOINTS, domain_id)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    assert done.stdout.splitlines() == ["made 100"]
    warned = [line for line in done.stderr.splitlines() if "ros_discovery_info" in line
              and "past the largest sample" in line]
    assert len(warned) == 1, done.stderr
    assert "/crowded's ros_discovery_info" in warned[0] and "(1024 bytes" in warned[0]


def test_a_write_past_the_bound_cyclonedds_uri_sets_says_so(domain_id: int) -> None:
    """CYCLONEDDS_URI's MaxSampleSize wins over max_sample_bytes: a sample between the two
    came out of `topic pub` as Cyclone's bare "Non specific error", a traceback."""
    uri = ('<CycloneDDS><Domain Id="any"><Internal><MaxSampleSize>64 KiB</MaxSampleSize>'
           '</Internal></Domain></CycloneDDS>')
    done = subprocess.run(
        [sys.executable, "-m", "rcan_rtps", "topic", "pub", "--once", "/sized",
         "std_msgs/msg/String", f"{{data: {BIG}}}"], capture_output=True, text=True,
        timeout=90, env=_env(domain_id, CYCLONEDDS_URI=uri))
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    line = error_line(done.stderr)
    assert "a std_msgs/msg/String of 100009 bytes was not sent: Cyclone refused it on " \
           f"domain {domain_id}, most likely as past the MaxSampleSize CYCLONEDDS_URI sets" \
           in line, line


def test_run_with_the_sim_takes_the_configs_bound(tmp_path: Path, domain_id: int,
                                                   jazzy_share: Path) -> None:
    """`run --sim` made its simulated robot's node first, without the config's bound: that
    node set the domain's (256 MiB), and `ros2.max_sample_bytes` was silently not applied.
    A peer writes a 100 KB ros_discovery_info: the bridge's Cyclone drops it as past 64 KiB."""
    config = tmp_path / "robot.rcan.yaml"
    config.write_text(textwrap.dedent(f"""\
        robot: {{ruri: rcan://registry.local/acme/rover/unit-0001}}
        bridge:
          ros2: {{namespace: /robot1, domain_id: {domain_id}, max_sample_bytes: {BOUND}}}
          api: {{host: 127.0.0.1, auth_token_env: RCAN_BRIDGE_TOKEN}}
          safety: {{max_linear_vel: 1.0, max_angular_vel: 1.0}}
          audit: {{path: {tmp_path / "audit.jsonl"}, key_path: {tmp_path / "audit.key"}}}
        """))
    env = child_env(domain_id, RCAN_BRIDGE_TOKEN="t" * 32)
    proc = RunProcess(["run", "--sim", "--config", str(config), "--port", "0", "--no-mdns",
                       *state_args(tmp_path, "state")], env, demo=False)
    flooder = subprocess.Popen(
        [sys.executable, str(Path(__file__).with_name("info_flooder.py")), "1", "100000",
         str(domain_id), str(jazzy_share)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        text=True, env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path),
                        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"})  # (as the demo's)
    try:
        assert flooder.stdout is not None and flooder.stdin is not None
        # (bounded: a peer that never matches; the read ends when the flooder is killed)
        ready = ThreadPoolExecutor(1).submit(flooder.stdout.readline)
        assert ready.result(timeout=60) == "ready\n"
        flooder.stdin.write("go\n")
        flooder.stdin.flush()
        proc.wait_for(rf"dropping oversize \(\d+ > {BOUND}\)", 60, stderr=True)
    finally:
        flooder.kill()
        flooder.wait()
        proc.stop()
