"""`rcan-rtps doctor` in the test network namespace: alone, and beside an rclpy node."""

from __future__ import annotations

import importlib.metadata
import os
import platform
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
    assert done.stdout.rstrip().endswith("All 7 checks passed")
    assert f"WARNING (graph): nothing found on ROS domain {domain_id}" in done.stdout
    assert "--localhost" in done.stdout


def test_doctor_report_finds_the_rclpy_node(jazzy_python: Path, domain_id: int) -> None:
    with RclpyOracle(jazzy_python, "talker", "/demo", domain_id=domain_id) as oracle:
        oracle.call("publisher", topic="/demo/chatter", type="std_msgs/msg/String")
        done = doctor(domain_id, "--report")
    assert done.returncode == 0, done.stdout + done.stderr
    out = done.stdout
    for section in ("PLATFORM INFORMATION", "RMW MIDDLEWARE", "DDS SECURITY", "ROS 2 ENVIRONMENT",
                    "NETWORK CONFIGURATION", "INTERFACE DEFINITIONS", "ROS 2 GRAPH"):
        assert f"\n   {section}\n" in out
    assert "/demo/talker" in out
    assert "WARNING (graph): nothing found" not in out
    assert "WARNING (graph): publisher without subscription on /demo/chatter" in out
    assert out.rstrip().endswith("All 7 checks passed")


def test_doctor_fails_on_a_bad_setting(domain_id: int) -> None:
    done = doctor(domain_id, "--spin-time", "0.2", ROS_AUTOMATIC_DISCOVERY_RANGE="moon")
    assert done.returncode == 1
    assert "ROS_AUTOMATIC_DISCOVERY_RANGE='moon' is not one of" in done.stdout
    assert "1/7 check(s) failed\nFailed modules: environment" in done.stdout


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


def _rows(out: str) -> dict[str, str]:
    """The report's `key : value` rows (the first of each key)."""
    rows: dict[str, str] = {}
    for line in out.splitlines():
        key, sep, value = line.partition(" : ")
        if sep and not line.startswith(("WARNING", "ERROR")):
            rows.setdefault(key.strip(), value.strip())
    return rows


def test_doctor_report_names_the_cyclone_build_and_the_platform(domain_id: int) -> None:
    done = doctor(domain_id, "--report", "--spin-time", "0.2")
    assert done.returncode == 0, done.stdout + done.stderr
    rows = _rows(done.stdout)
    import cyclonedds

    binding = importlib.metadata.version("cyclonedds")
    assert rows["cyclonedds version"] == f"{binding} ({Path(cyclonedds.__file__).parent})"
    # the suite runs on PyPI's wheel: its own libddsc, of the binding's release, no security
    library = rows["Cyclone DDS C library"]
    assert library.startswith(f"{binding} at ") and "/cyclonedds.libs/libddsc" in library
    assert library.endswith("(bundled in the binding's wheel)")
    assert rows["C build options"] == ("type library: yes, type discovery: yes, "
                                       "topic discovery: yes, DDS-Security: no")
    assert rows["built into the C library"].startswith("no (PyPI's cyclonedds wheel")
    assert rows["plugin dds_security_auth"] == "not found"
    assert rows["available"] == "no"
    assert rows["processor"] == platform.machine()
    assert rows["python"] == (f"{platform.python_implementation()} "
                              f"{platform.python_version()} ({sys.executable})")
    assert rows["system"] == platform.system()


def test_doctor_report_says_how_far_discovery_reaches(domain_id: int, tmp_path: Path) -> None:
    def scope(*args: str, **env: str) -> dict[str, str]:
        done = doctor(domain_id, "--report", "--spin-time", "0.2", *args, **env)
        return _rows(done.stdout)

    assert scope()["discovery"] == "the subnet (multicast on the interfaces that have it)"
    local = "this machine only, unicast over loopback (from {})"
    assert scope("--localhost")["discovery"] == local.format("--localhost")
    assert scope(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")["discovery"] == local.format(
        "ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST")
    assert scope(ROS_LOCALHOST_ONLY="1")["discovery"] == local.format("ROS_LOCALHOST_ONLY=1")
    config = tmp_path / "cyclone.xml"
    config.write_text("<CycloneDDS/>")
    assert scope(CYCLONEDDS_URI=f"file://{config}")["CYCLONEDDS_URI"] == f"file://{config}"


def test_doctor_refuses_enforced_ros_security_without_dds_security(domain_id: int) -> None:
    wanted = {"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_KEYSTORE": "/nowhere"}
    problem = "ROS_SECURITY_ENABLE=true but this Cyclone DDS cannot do DDS-Security"
    enforced = doctor(domain_id, "--spin-time", "0.2", ROS_SECURITY_STRATEGY="Enforce", **wanted)
    assert enforced.returncode == 1
    assert f"ERROR (security): {problem}" in enforced.stdout
    # the graph check fails too: Enforce without security never starts a participant
    assert "2/7 check(s) failed\nFailed modules: security graph" in enforced.stdout
    permissive = doctor(domain_id, "--spin-time", "0.2", **wanted)
    assert permissive.returncode == 0, permissive.stdout
    assert f"WARNING (security): {problem}" in permissive.stdout
