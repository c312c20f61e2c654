"""A simulated robot started where another robot already publishes its odometry (a second
`rcan-rtps sim` or `run --sim` on the domain, or a real robot's driver): both would obey the
same cmd_vel and odometry would jump between them. The later one warns, once, naming the
other participant, and runs all the same; one alone says it found none."""

from __future__ import annotations

import re
import signal
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path

from oracle.client import OracleEnv, RclpyOracle

from tests.interop.run_process import RunProcess, child_env, state_args

SIM_READY = r"^rcan-rtps sim ready node=(\S+)"
LOOKED = r"(no other robot publishes|another robot on ROS domain \d+ already publishes)"
NONE_FOUND = r"INFO rcan_rtps\.sim\.others: no other robot publishes /robot1/odom on ROS"
LOOK_S = 60.0  # against a hang only: the look ends within the CLI's discovery window


@contextmanager
def running(args: list[str], domain_id: int, *, demo: bool = False,
            ready: str = r"^rcan-rtps ready api=(\S+)$") -> Iterator[RunProcess]:
    """`rcan-rtps --log-level info <args>`, stopped (SIGTERM: exit 0) when done."""
    proc = RunProcess(["--log-level", "info", *args], child_env(domain_id), demo=demo,
                      ready=ready)
    try:
        yield proc
        proc.signal(signal.SIGTERM)
        assert proc.wait(60) == 0, proc.output()
    finally:
        proc.kill()


def sim(domain_id: int) -> AbstractContextManager[RunProcess]:
    return running(["sim"], domain_id, ready=SIM_READY)


def run_sim(tmp_path: Path, domain_id: int) -> AbstractContextManager[RunProcess]:
    return running(["run", "--sim", "--port", "0", "--no-mdns", *state_args(tmp_path, "state")],
                   domain_id, demo=True)


def warnings_of_others(proc: RunProcess) -> list[str]:
    return [line for line in proc.stderr if "WARNING rcan_rtps.sim.others:" in line]


def _the_look(proc: RunProcess) -> str:
    return proc.wait_for(LOOKED, LOOK_S, stderr=True).group(0)


def test_a_sim_alone_warns_of_nobody(domain_id: int) -> None:
    with sim(domain_id) as alone:
        _the_look(alone)
        assert re.search(NONE_FOUND, "".join(alone.stderr)), alone.output()
        assert warnings_of_others(alone) == [], alone.output()


def test_a_second_sim_warns_once_naming_the_first(domain_id: int) -> None:
    with sim(domain_id) as first:
        _the_look(first)
        with sim(domain_id) as second:
            _the_look(second)
            warned = warnings_of_others(second)
            assert len(warned) == 1, second.output()
            assert re.search(
                r"WARNING rcan_rtps\.sim\.others: another robot on ROS domain \d+ already "
                r"publishes /robot1/odom: node /robot1/sim_robot \(participant "
                r"[0-9a-f]{2}(\.[0-9a-f]{2}){11}, Eclipse Cyclone DDS\)\. Both take the same "
                r"velocity commands", warned[0]), warned
        assert warnings_of_others(first) == [], first.output()  # it was there first


def test_a_second_run_sim_warns_naming_the_first_sim(tmp_path: Path, domain_id: int) -> None:
    with run_sim(tmp_path / "first", domain_id) as first:
        _the_look(first)  # done before the second starts (started together, both would warn)
        with run_sim(tmp_path / "second", domain_id) as second:
            _the_look(second)
            warned = warnings_of_others(second)
            assert len(warned) == 1 and "node /robot1/sim_robot (participant " in warned[0], \
                second.output()
        assert warnings_of_others(first) == [], first.output()


def test_run_sim_beside_a_sim_on_loopback_warns(tmp_path: Path, domain_id: int) -> None:
    """`run --sim` keeps to loopback: a sim started as the README says to reach it."""
    with running(["--localhost", "sim"], domain_id, ready=SIM_READY) as first:
        _the_look(first)
        with run_sim(tmp_path, domain_id) as demo:
            _the_look(demo)
            warned = warnings_of_others(demo)
            assert len(warned) == 1 and "node /robot1/sim_robot (participant " in warned[0], \
                demo.output()
        assert warnings_of_others(first) == [], first.output()


def test_run_sim_alone_warns_of_nobody(tmp_path: Path, domain_id: int) -> None:
    with run_sim(tmp_path, domain_id) as demo:
        _the_look(demo)
        assert re.search(NONE_FOUND, "".join(demo.stderr)), demo.output()
        assert warnings_of_others(demo) == [], demo.output()


def test_a_sim_beside_a_real_robots_driver_names_its_node(jazzy_oracle: OracleEnv,
                                                          domain_id: int) -> None:
    with RclpyOracle(jazzy_oracle, "base_driver", "/robot1", domain_id=domain_id) as driver:
        driver.call("publisher", topic="/robot1/odom", type="nav_msgs/msg/Odometry")
        with sim(domain_id) as late:
            _the_look(late)
            warned = warnings_of_others(late)
            assert len(warned) == 1, late.output()
            assert "publishes /robot1/odom: node /robot1/base_driver (participant " in warned[0]
            assert ", eProsima Fast DDS)" in warned[0], warned


def test_a_stop_during_the_look_ends_the_sim_cleanly(tmp_path: Path, domain_id: int) -> None:
    """SIGTERM at the ready line, the look (its discovery window) still under way: the look
    is cancelled, the robot stops as always (exit 0), and nothing is said of other robots."""
    for proc in (RunProcess(["sim"], child_env(domain_id), demo=False, ready=SIM_READY),
                 RunProcess(["run", "--sim", "--port", "0", "--no-mdns",
                             *state_args(tmp_path, "state")], child_env(domain_id), demo=True)):
        try:
            proc.signal(signal.SIGTERM)
            assert proc.wait(60) == 0, proc.output()
            assert "Traceback" not in "".join(proc.stderr), proc.output()
        finally:
            proc.kill()
