"""`rcan-rtps doctor` in the test network namespace: alone, and beside an rclpy node."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from oracle.client import RclpyOracle


def doctor(domain_id: int, *args: str, **env: str) -> subprocess.CompletedProcess[str]:
    full_env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id), **env}
    for name in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOCALHOST_ONLY"):
        if name not in env:
            full_env.pop(name, None)
    return subprocess.run([sys.executable, "-m", "rcan_rtps", "doctor", *args],
                          capture_output=True, text=True, env=full_env, timeout=60)


def test_doctor_alone_passes_with_the_localhost_hint(domain_id: int) -> None:
    done = doctor(domain_id, "--spin-time", "1")
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.rstrip().endswith("All 6 checks passed")
    assert f"WARNING (graph): nothing found on ROS domain {domain_id}" in done.stdout
    assert "--localhost" in done.stdout


def test_doctor_report_finds_the_rclpy_node(jazzy_python: Path, domain_id: int) -> None:
    with RclpyOracle(jazzy_python, "talker", "/demo", domain_id=domain_id) as oracle:
        oracle.call("publisher", topic="/demo/chatter", type="std_msgs/msg/String")
        done = doctor(domain_id, "--report")
    assert done.returncode == 0, done.stdout + done.stderr
    out = done.stdout
    for section in ("PLATFORM INFORMATION", "RMW MIDDLEWARE", "ROS 2 ENVIRONMENT",
                    "NETWORK CONFIGURATION", "INTERFACE DEFINITIONS", "ROS 2 GRAPH"):
        assert f"\n   {section}\n" in out
    assert "/demo/talker" in out
    assert "WARNING (graph): nothing found" not in out
    assert "WARNING (graph): publisher without subscription on /demo/chatter" in out
    assert out.rstrip().endswith("All 6 checks passed")


def test_doctor_fails_on_a_bad_setting(domain_id: int) -> None:
    done = doctor(domain_id, "--spin-time", "0.2", ROS_AUTOMATIC_DISCOVERY_RANGE="moon")
    assert done.returncode == 1
    assert "ROS_AUTOMATIC_DISCOVERY_RANGE='moon' is not one of" in done.stdout
    assert "1/6 check(s) failed\nFailed modules: environment" in done.stdout


def _domain_row(out: str) -> str:
    return next(line.split(":", 1)[1].strip() for line in out.splitlines()
                if line.startswith("ROS_DOMAIN_ID "))


def test_doctor_report_says_where_the_domain_id_comes_from(domain_id: int,
                                                           another_domain_id: int) -> None:
    unset = {k: v for k, v in os.environ.items() if k != "ROS_DOMAIN_ID"}
    done = subprocess.run([sys.executable, "-m", "rcan_rtps", "doctor", "--report",
                           "--spin-time", "0.2"], capture_output=True, text=True, env=unset,
                          timeout=60)
    assert _domain_row(done.stdout) == "0 (ROS_DOMAIN_ID is not set: the default)", done.stdout
    done = doctor(domain_id, "--report", "--spin-time", "0.2")
    assert _domain_row(done.stdout) == f"{domain_id} (from the environment)"
    done = doctor(domain_id, "--report", "--spin-time", "0.2",
                  "--domain-id", str(another_domain_id))
    assert _domain_row(done.stdout) == f"{another_domain_id} (from --domain-id)"
