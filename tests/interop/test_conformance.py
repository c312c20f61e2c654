"""Issue 24 item 9: `rcan-rtps conformance` runs the published suite's cases against a real
`run --sim` (a subprocess, mDNS on loopback, in the test's network namespace) and passes every
in-scope case at L1–L3; against a bridge with a gate removed it names the failing case."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from rcan_rtps.bridge.demo import OWNER_TOKEN_ENV, USER_TOKEN_ENV, VIEWER_TOKEN_ENV, demo_yaml
from rcan_rtps.conformance import load_suite

# Each simulator advertises over mDNS (L1-MDNS-001) under the demo's name: like every test
# that advertises, in the serial phase (tests/bridge/test_mdns.py).
pytestmark = pytest.mark.serial

@dataclass
class Sim:
    url: str
    tokens: dict[str, str]


def _read(proc: subprocess.Popen[str], pattern: str, seen: list[str]) -> str:
    assert proc.stdout is not None
    for line in proc.stdout:
        seen.append(line)
        found = re.search(pattern, line)
        if found:
            return found.group(1)
    raise AssertionError("the simulator exited early:\n" + "".join(seen)
                         + Path(seen[0][9:-2]).read_text())


def _sim(tmp_path: Path, domain_id: int, *args: str) -> Iterator[Sim]:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id), "HOME": str(tmp_path)}
    for name in (OWNER_TOKEN_ENV, USER_TOKEN_ENV, VIEWER_TOKEN_ENV, "XDG_STATE_HOME"):
        env.pop(name, None)
    errors = tmp_path / "sim.err"
    with errors.open("w") as stderr:
        proc = subprocess.Popen(  # mDNS on: L1-MDNS-001 browses for it (loopback only)
            [sys.executable, "-m", "rcan_rtps", "run", "--sim", "--port", "0",
             "--state-dir", str(tmp_path / "state"), *args],
            stdout=subprocess.PIPE, stderr=stderr, text=True, env=env)
    seen: list[str] = [f"(stderr: {errors})\n"]
    try:
        url = _read(proc, r"^rcan-rtps ready api=(\S+)$", seen)
        tokens = {"USER": _read(proc, r"USER \(operator\)\s+(\S+)", seen),
                  "OWNER": _read(proc, r"OWNER \(owner\)\s+(\S+)", seen),
                  "GUEST": _read(proc, r"GUEST \(viewer\)\s+(\S+)", seen)}
        yield Sim(url, tokens)
    finally:
        proc.send_signal(2)
        try:
            proc.wait(timeout=20)
        finally:
            proc.kill()


def _conformance(sim: Sim, *args: str) -> subprocess.CompletedProcess[str]:
    # The OWNER's token from the environment, as the README shows (off the command line).
    return subprocess.run(
        [sys.executable, "-m", "rcan_rtps", "conformance", "--url", sim.url,
         "--token-env", "CONFORMANCE_OWNER_TOKEN", "--token-for", f"USER={sim.tokens['USER']}",
         "--token-for", f"GUEST={sim.tokens['GUEST']}", *args],
        capture_output=True, text=True, timeout=300,
        env={**os.environ, "CONFORMANCE_OWNER_TOKEN": sim.tokens["OWNER"]})


def _lines(out: str) -> dict[str, str]:
    """Case id → its verdict word, from the one line per case."""
    found = re.findall(r"^(PASS|FAIL|N/A |OUT ) (L[1-3]-[A-Z]+-\d{3})", out, re.M)
    return {case: word.strip() for word, case in found}


@pytest.fixture
def sim(tmp_path: Path, domain_id: int) -> Iterator[Sim]:
    yield from _sim(tmp_path, domain_id)


def test_every_in_scope_case_passes_against_the_simulator(sim: Sim) -> None:
    done = _conformance(sim)
    verdicts = _lines(done.stdout)
    suite = load_suite()
    # one line per case (stderr and the exit status too: a run that printed none says why there)
    assert set(verdicts) == {c.id for c in suite.cases}, \
        f"exit {done.returncode}\n{done.stdout}{done.stderr}"
    failing = {case: word for case, word in verdicts.items() if word == "FAIL"}
    assert failing == {}, done.stdout
    assert done.returncode == 0, done.stdout + done.stderr
    out_of_scope = {c.id for c in suite.cases if c.out_of_scope}
    assert {c for c, w in verdicts.items() if w == "OUT"} == out_of_scope
    # The pair of confidence-gate cases: this bridge escalates, so the blocking one is n/a.
    assert (verdicts["L2-CONF-002"], verdicts["L2-CONF-001"]) == ("PASS", "N/A")
    assert "rcan-conformance-v1.4.json" in done.stdout  # the vendored source is named


@pytest.mark.parametrize("role", ["OWNER", "USER"])
def test_a_token_the_bridge_refuses_is_one_line(sim: Sim, role: str) -> None:
    """A mistyped token was a run of FAIL lines (and a few PASSes) ending 'not conformant'."""
    wrong = Sim(sim.url, {**sim.tokens, role: "rcan_not-a-token-of-this-bridge"})
    run = _conformance(wrong)
    assert run.returncode == 2 and "FAIL" not in run.stdout and "PASS" not in run.stdout
    assert run.stderr.strip() == (f"rcan-rtps conformance: the bridge at {sim.url} refused "
                                  f"the {role}'s token (401 UNAUTHENTICATED)")


def test_a_level_runs_the_cases_up_to_it(sim: Sim) -> None:
    done = _conformance(sim, "--level", "L1")
    assert set(_lines(done.stdout)) == {c.id for c in load_suite().upto("L1")}, \
        done.stdout + done.stderr
    assert done.returncode == 0, done.stdout + done.stderr


def test_a_bridge_without_its_hitl_gate_fails_l3_hitl_001(tmp_path: Path,
                                                         domain_id: int) -> None:
    text = demo_yaml(state_dir=tmp_path / "state", port=8765, domain_id=domain_id,  # --port 0
                     namespace="/robot1")
    ungated = re.sub(r"    gates:\n      - \{action: arm_joint[^\n]*\n", "", text)
    assert ungated != text
    config = tmp_path / "ungated.rcan.yaml"
    config.write_text(ungated)
    for sim in _sim(tmp_path, domain_id, "--config", str(config)):
        done = _conformance(sim, "--level", "L3")
        verdicts = _lines(done.stdout)
        assert verdicts["L3-HITL-001"] == "FAIL", done.stdout
        assert re.search(r"^FAIL L3-HITL-001 .*was not held", done.stdout, re.M)
        assert done.returncode == 1
        assert verdicts["L1-RBAC-001"] == "PASS"  # the rest of governance still holds
